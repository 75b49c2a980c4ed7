"""``cmtool validate`` and ``cmtool export``: checking lane graphs and writing them for other tools."""

from __future__ import annotations

import tempfile
from pathlib import Path

import click

from cmtool.cli.common import Finite, InPath, OutPath, _origin
from cmtool.core.errors import CmtoolError

LARGE_SCENE = 2000  # lanes; export announces itself for scenes this large


@click.command()
@click.argument("maps", type=InPath(dir_okay=False))
@click.option("--json", "json_out", type=OutPath(dir_okay=False), help="Write the full report here.")
@click.option("--repair", is_flag=True, help="Snap near-miss joints, drop lanes under 2 m, merge duplicates; "
              "report the repaired maps.")
@click.option("--out", type=OutPath(dir_okay=False),
              help="With --repair: the repaired maps (.jsonl).")
def validate(maps, json_out, repair, out):
    """Check lane graphs (a .json scene or a .jsonl of scenes, or a whole HD map: cmtool's JSON, Argoverse 2,
    Lanelet2) for what planners need: dangling lanes,
    bad successor joins, crossings outside intersections, self-intersections, short lanes, kinks;
    routability; a validity score in [0, 1] per scene."""
    import numpy as np

    from cmtool.core.jsonio import write_json
    from cmtool.formats.mapfile import read_lane_graphs
    from cmtool.maps.lanegraph import write_jsonl
    from cmtool.metrics.repair import repair as repair_graph
    from cmtool.metrics.validity import check

    if repair != (out is not None):
        raise CmtoolError("--repair needs --out FILE.jsonl for the repaired maps" if repair
                          else "--out goes with --repair")
    graphs = read_lane_graphs(maps)
    if repair:
        repaired = [repair_graph(g) for g in graphs]
        for i, (_, changes) in enumerate(repaired):
            for change in changes:
                click.echo(f"scene {i}: {change}")
        graphs = [g for g, _ in repaired]
        write_jsonl(out, graphs)
        click.echo(f"wrote {len(graphs)} repaired scene{'s' if len(graphs) != 1 else ''} to {out} "
                   f"({sum(len(c) for _, c in repaired)} changes); the report below is of the repaired maps")
    reports = [check(g) for g in graphs]
    if not reports:
        raise CmtoolError(f"{maps}: no scenes")
    totals: dict[str, int] = {}
    for r in reports:
        for k, v in r.counts().items():
            totals[k] = totals.get(k, 0) + v
    click.echo(f"{'scene':>5} {'score':>6} {'lanes':>5} {'routable':>8} {'+changes':>8} {'scc':>4}  problems")
    for i, r in enumerate(reports):
        problems = ", ".join(f"{k} {v}" for k, v in sorted(r.counts().items())) or "none"
        click.echo(f"{i:>5} {r.score:>6.3f} {r.lanes:>5} {r.routable_pairs:>8.3f} {r.routable_with_changes:>8.3f} "
                   f"{r.largest_scc:>4}  {problems}")
    summary = {"scenes": len(reports), "mean_score": float(np.mean([r.score for r in reports])), "problems": totals}
    click.echo(f"{len(reports)} scenes, mean validity score {summary['mean_score']:.3f}; problems: "
               + (", ".join(f"{k} {v}" for k, v in sorted(totals.items())) or "none"))
    if json_out is not None:
        write_json(json_out, {**summary, "reports": [r.to_json() for r in reports]})
        click.echo(f"wrote {json_out}")


@click.command()
@click.option("--format", "fmt", required=True, type=click.Choice(["lanelet2", "opendrive", "geojson", "sumo"]),
              help="lanelet2: a Lanelet2 OSM map (.osm); opendrive: an OpenDRIVE 1.6 map (.xodr); "
                   "geojson: GeoJSON features; sumo: a SUMO network for traffic (.net.xml; needs SUMO: "
                   "pip install eclipse-sumo).")
@click.argument("map_path", metavar="MAP", type=InPath(dir_okay=False))
@click.option("--origin", help="LAT,LON where the scene's origin (the ego) lies [default: what the map's meta.geo "
                               "records, as maps from `sample --osm` do].")
@click.option("--heading", type=Finite(),
              help="Compass heading of the scene's forward axis, degrees [default: meta.geo's, else 0].")
@click.option("--scene", default=0, show_default=True, type=click.IntRange(min=0), help="Scene of a .jsonl file.")
@click.option("--lane-width", default=3.5, show_default=True, type=Finite(min=0.5, max=10.0),
              help="Lane width where the map records none and no neighbours give one, metres.")
@click.option("--out", required=True, type=OutPath(dir_okay=False), help="File to write.")
@click.option("--verify", is_flag=True,
              help="Load the export in an independent reader (opendrive: CARLA's, from the carla wheel; lanelet2: the "
                   "lanelet2 wheel's routing graph) and check that it routes the lane graph's successor joins and "
                   "nothing else, keeping every lane; exit 1 where it does not.")
def export(fmt, map_path, origin, heading, scene, lane_width, out, verify):
    """Export a lane graph (a generated or ground-truth scene) or a whole HD map (cmtool's JSON, Argoverse 2,
    Lanelet2: it records where it lies when imported) for simulators and GIS tools."""
    import math

    import numpy as np

    from cmtool.core.jsonio import write_json, write_text_atomic
    from cmtool.formats.consumers import READERS, reader
    from cmtool.formats.geojson import to_geojson
    from cmtool.formats.mapfile import read_lane_graphs
    from cmtool.maps.neighbours import Crowded, graph_neighbours
    from cmtool.metrics.validity import check

    if verify:
        if fmt not in READERS:
            raise CmtoolError(f"--verify checks {' and '.join(READERS)} exports, not {fmt}")
        reader(fmt)  # before any work: a missing reader is known at once
    graphs = read_lane_graphs(map_path)
    if scene >= len(graphs):
        raise CmtoolError(f"{map_path}: no scene {scene} ({len(graphs)} scene{'s' if len(graphs) != 1 else ''})")
    graph = graphs[scene]
    if not graph.lanes:
        raise CmtoolError(f"{map_path}: scene {scene} has no lanes to export")
    short = [k for k, lane in enumerate(graph.lanes) if np.linalg.norm(np.diff(lane, axis=0), axis=1).sum() < 0.01]
    if short:
        raise CmtoolError(f"{map_path}: scene {scene}: lane {short[0]} has no length (all its points coincide)")
    geo = graph.geo
    if origin is not None:
        lat0, lon0 = _origin(origin)
    elif geo is not None:
        lat0, lon0 = geo[0], geo[1]
    else:
        raise CmtoolError(f"{map_path}: scene {scene} records no place on the globe (meta.geo); "
                          "give --origin LAT,LON (and --heading)")
    if heading is None:
        heading = geo[2] if geo is not None and origin is None else 0.0
    if not math.isfinite(heading):
        raise CmtoolError(f"--heading {heading}: expected a finite number of degrees")
    if len(graph.lanes) >= LARGE_SCENE:  # seconds of work ahead: say so before it starts
        click.echo(f"{map_path}: exporting {len(graph.lanes):,} lanes to {fmt} (about a second per 1,000)...", err=True)
    if fmt == "sumo":
        from cmtool.formats.sumo import write_sumo_net

        warning = write_sumo_net(graph, out, lat0, lon0, heading, lane_width)
        click.echo(f"{out}: SUMO network of {len(graph.lanes)} lanes (netconvert on the OpenDRIVE export); origin "
                   f"{lat0:.7f},{lon0:.7f}, heading {heading:g}" + (f"; netconvert: {warning}" if warning else ""))
        return
    if fmt in ("lanelet2", "opendrive"):
        if fmt == "lanelet2":
            from cmtool.formats.lanelet2_export import to_lanelet2 as export_text
        else:
            from cmtool.formats.opendrive_export import to_opendrive as export_text
        try:
            text = export_text(graph, lat0, lon0, heading, lane_width)
        except Crowded as e:
            raise CmtoolError(f"{map_path}: {e}") from None
        verdict = _verified(fmt, graph, text, out, lat0, lon0) if verify else None
        write_text_atomic(out, text)  # only now: a failed export or verification leaves an earlier file as it was
        left, oncoming = graph_neighbours(graph)
        click.echo(f"{out}: {len(graph.lanes)} lanes, {len(graph.successors)} successor joins, {len(left)} lane-change "
                   f"neighbours, {len(oncoming)} oncoming pairs, {len(graph.green_lights) + len(graph.red_lights)} "
                   f"light lines; origin {lat0:.7f},{lon0:.7f}, heading {heading:g}")
        report = check(graph)
        bad = {i for p in report.problems for i in p.lanes}
        if bad:
            click.echo(f"warning: {len(bad)} of {len(graph.lanes)} lanes have validity problems ("
                       + ", ".join(f"{k} {v}" for k, v in sorted(report.counts().items()))
                       + "); simulators may not route through sharply turning or crossing lanes "
                         "(see cmtool validate)", err=True)
        if verdict is not None:
            click.echo(f"{out}: {verdict.line()}")
        return
    collection = to_geojson(graph, lat0, lon0, heading, lane_width)
    write_json(out, collection)
    kinds: dict[str, int] = {}
    for f in collection["features"]:
        kinds[f["properties"]["kind"]] = kinds.get(f["properties"]["kind"], 0) + 1
    plural = {"lane": "lanes", "boundary": "boundaries", "light": "lights"}
    click.echo(f"{out}: " + ", ".join(f"{v} {plural[k]}" for k, v in kinds.items()))


def _verified(fmt: str, graph, text: str, out, lat0: float, lon0: float):
    """The reader's verdict on the export ``text`` of ``graph``, read from a temporary file named as ``out`` (the
    reader tells formats by the name); one that does not route as the lane graph does is an error."""
    from cmtool.formats.consumers import verify

    with tempfile.TemporaryDirectory(prefix="cmtool-verify-") as folder:
        path = Path(folder) / Path(out).name
        path.write_text(text, encoding="utf-8")
        try:
            verdict = verify(fmt, graph, path, lat0, lon0)
        except CmtoolError as e:
            raise CmtoolError(f"{str(e).replace(str(path), str(out))} (not written)") from None
    if not verdict.ok:
        raise CmtoolError(f"{out}: {verdict.line()} (not written)")
    return verdict


@click.command()
@click.argument("map_path", metavar="MAP", type=InPath(dir_okay=False))
@click.option("--to", "kind", required=True, type=click.Choice(["hdmap", "lanegraph"]),
              help="hdmap: cmtool's HD map JSON (what `data sd`, `data stats` and `sample --from-hd` read as a whole "
                   "map); lanegraph: a lane graph JSON (what `sample` writes, and `metrics` and `export` read).")
@click.option("--out", required=True, type=OutPath(dir_okay=False), help="File to write.")
def convert(map_path, kind, out):
    """Convert a map between cmtool's own formats: any map file that holds lanes (an HD map of any source, a lane
    graph of one map) to an HD map JSON or a lane graph JSON."""
    from cmtool.core.jsonio import write_json
    from cmtool.formats.mapfile import read_hd_map, read_lane_graphs

    if kind == "hdmap":
        hd = read_hd_map(map_path)
        hd.save(out)
        click.echo(f"{out}: HD map of {hd.city or 'no city'}, {len(hd.lanes)} lanes, {len(hd.stop_lines)} stop lines")
    else:
        graphs = read_lane_graphs(map_path)
        if len(graphs) != 1:
            raise CmtoolError(f"{map_path}: already {len(graphs)} lane graphs (a .jsonl); nothing to convert")
        write_json(out, graphs[0].to_json())
        click.echo(f"{out}: lane graph of {graphs[0].city or 'no city'}, {len(graphs[0].lanes)} lanes, "
                   f"{len(graphs[0].successors)} successors")
