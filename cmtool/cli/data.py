"""``cmtool data``: procedural cities, real-map import, SD maps, frames and the dataset cache."""

from __future__ import annotations


import click

from cmtool.cli.common import SEED, Finite, InPath, OutPath, _origin
from cmtool.core.errors import CmtoolError
from cmtool.formats.importers import FORMATS as HD_FORMATS

CITY_CHOICES = ("LAV", "PIT", "SGP", "BOS")


MAX_FRAMES = 100_000  # poses or frames one command picks on a map (more say nothing new and take hours)

@click.group()
def data():
    """Maps and datasets: procedural cities, real-map import, SD maps, dataset cache."""


@data.command()
@click.option("--city", required=True, callback=lambda ctx, param, v: _city(v),
              help="City style: LAV, PIT, SGP or BOS.")
@click.option("--seed", default=0, show_default=True, type=SEED, help="Random seed.")
@click.option("--extent", default=800.0, show_default=True, type=Finite(min=100, max=20000),
              help="Side of the square city, metres.")
@click.option("--out", required=True, type=OutPath(dir_okay=False), help="HD map JSON to write.")
def synth(city, seed, extent, out):
    """Generate a procedural city HD map in the style of a nuPlan city."""
    from cmtool.data.synth import generate_city

    hd = generate_city(city, seed=seed, extent=extent)
    hd.save(out)
    n_conn = sum(l.is_intersection for l in hd.lanes.values())
    click.echo(
        f"{out}: {city} seed {seed}, {len(hd.lanes)} lanes ({n_conn} connectors), "
        f"{len(hd.stop_lines)} stop lines, {len(hd.crosswalks)} crosswalks, drives on the {hd.drives_on}"
    )


def _city(value: str) -> str:
    if value.upper() not in CITY_CHOICES:
        raise click.BadParameter(f"unknown city {value!r} (choose from {', '.join(CITY_CHOICES)})")
    return value.upper()


IMPORT_FORMATS = (*HD_FORMATS, "osm")


@data.command("import")
@click.option("--format", "fmt", required=True, type=click.Choice(IMPORT_FORMATS),
              help=f"{', '.join(HD_FORMATS)}: HD maps; osm: an OpenStreetMap .osm/.osm.pbf file to an SD map.")
@click.argument("file", type=InPath())
@click.option("--out", required=True, type=OutPath(dir_okay=False), help="Map JSON to write.")
@click.option("--city", default=None, help="City code to record (default: from the file or format).")
def import_(fmt, file, out, city):
    """Import a real map into cmtool's HD (or, for osm, SD) map JSON."""
    if fmt == "osm":
        from cmtool.formats.osm import read_osm

        sd = read_osm(file)
        if city:
            sd.city = city
        sd.save(out)
        click.echo(f"{out}: SD map, {len(sd.roads)} roads")
        return
    from cmtool.formats.importers import import_hd_map

    hd = import_hd_map(fmt, file, city=city)
    hd.save(out)
    click.echo(
        f"{out}: HD map of {hd.city}, {len(hd.lanes)} lanes, {sum(len(l.successors) for l in hd.lanes.values())} "
        f"successor edges, {len(hd.stop_lines)} stop lines, {len(hd.crosswalks)} crosswalks"
    )


@data.command()
@click.argument("hd_map", type=InPath())
@click.option("--out", required=True, type=OutPath(dir_okay=False),
              help="SD map to write: cmtool JSON, or OpenStreetMap XML when the name ends in .osm.")
@click.option("--origin", help="With an .osm output: LAT,LON where the map's (0, 0) lies.")
@click.option("--offset", default=0.0, show_default=True, type=Finite(min=0, max=1000),
              help="Jitter: random shift of up to this many metres.")
@click.option("--rotation", default=0.0, show_default=True, type=Finite(min=0, max=180),
              help="Jitter: random rotation of up to this many degrees.")
@click.option("--drop-minor", default=0.0, show_default=True, type=Finite(min=0, max=1),
              help="Jitter: probability of dropping each minor road.")
@click.option("--seed", default=0, show_default=True, type=SEED, help="Seed of the jitter.")
def sd(hd_map, out, origin, offset, rotation, drop_minor, seed):
    """Derive the SD map (one polyline per road, as OpenStreetMap shows it) of an HD map."""
    from cmtool.data.sd_derive import SDJitter, derive_sd
    from cmtool.formats.mapfile import read_hd_map

    if offset < 0 or rotation < 0 or not 0.0 <= drop_minor <= 1.0:
        raise CmtoolError("jitter must be non-negative and --drop-minor within [0, 1]")
    to_osm = out.suffix == ".osm"
    if to_osm != (origin is not None):
        raise CmtoolError("an .osm output needs --origin LAT,LON" if to_osm else "--origin goes with an .osm output")
    if to_osm:
        lat0, lon0 = _origin(origin)
    jitter = SDJitter(offset, rotation, drop_minor)
    sd_map = derive_sd(read_hd_map(hd_map), jitter=jitter if jitter.enabled else None, seed=seed)
    if to_osm:
        from cmtool.formats.osm import write_osm

        write_osm(sd_map, out, lat0, lon0)
    else:
        sd_map.save(out)
    click.echo(f"{out}: SD map, {len(sd_map.roads)} roads")


@data.command()
@click.argument("sd_map", type=InPath())
@click.option("--x", "x", type=Finite(), default=None, help="Frame centre x, metres [default: map centre].")
@click.option("--y", "y", type=Finite(), default=None, help="Frame centre y, metres [default: map centre].")
@click.option("--yaw", default=90.0, show_default=True, type=Finite(),
              help="Heading of the frame's forward axis, degrees (90 = north up).")
@click.option("--png", required=True, type=OutPath(dir_okay=False), help="SD raster PNG to write.")
def raster(sd_map, x, y, yaw, png):
    """Rasterise a 64 m window of an SD map into the 128 x 128 RGB control image (docs/data.md). SD_MAP may be
    any map file: an SD map JSON, an OpenStreetMap file, or an HD map or lane graph (the SD map derived from it)."""
    import numpy as np

    from cmtool.data.frames import read_sd_source
    from cmtool.data.sd_raster import ENCODING, ENCODINGS, FRAME_M, decode_sd, rasterize_sd
    from cmtool.viz.show import write_png

    sd_obj = read_sd_source(sd_map)
    if not sd_obj.roads:
        raise CmtoolError(f"{sd_map}: the SD map has no roads")
    pts = np.concatenate([r.polyline for r in sd_obj.roads])
    for name, v, low, high in zip(("--x", "--y"), (x, y), pts.min(0), pts.max(0)):
        if v is not None and not low - FRAME_M <= v <= high + FRAME_M:
            raise CmtoolError(f"{name} {v:g}: more than a frame ({FRAME_M:g} m) outside the map, whose roads span "
                              f"{round(low)} to {round(high)} m; the picture would hold no road")
    cx, cy = (pts.min(0) + pts.max(0)) / 2.0
    image = rasterize_sd(sd_obj, cx if x is None else x, cy if y is None else y, np.radians(yaw))
    write_png(png, image)
    dec = decode_sd(image)
    classes, counts = np.unique(dec["road_class"][dec["road"]] + np.where(dec["link"][dec["road"]], "_link", ""),
                                return_counts=True)
    shown = ", ".join(f"{c or 'unknown class'} {n}" for c, n in sorted(zip(classes, counts), key=lambda t: -t[1]))
    click.echo(f"{png}: SD raster of encoding {ENCODING} ({ENCODINGS[ENCODING]}), {int(dec['road'].sum())} road "
               f"pixels{': ' + shown if shown else ''}")


@data.command()
@click.argument("map_file", type=InPath())
@click.option("--n", default=1, show_default=True, type=click.IntRange(1, MAX_FRAMES), help="Poses to print.")
@click.option("--seed", default=0, show_default=True, type=SEED, help="Random seed.")
@click.option("--kind", help="Only these kinds of frame, comma-separated: junction, approach, exit, end, curve, "
              "straight [default: all, in the dataset's mix].")
@click.option("--near-junction", type=Finite(min=0), help="Only poses within this many metres of a junction.")
@click.option("--latlon", is_flag=True, help="Print {lat, lon, heading} (compass degrees) for `sample --osm --center`; "
              "needs a map with a geographic origin (an OpenStreetMap file or its import).")
@click.option("--out", type=OutPath(dir_okay=False), help="Write the lines to this .jsonl file.")
def poses(map_file, n, seed, kind, near_junction, latlon, out):
    """Ego poses as the dataset frames its scenes: on a road, facing its travel direction, spread over
    straight roads, curves, junctions, approaches and exits. MAP_FILE: an OpenStreetMap .osm/.osm.pbf
    file, an SD map or an HD map JSON (framed on its derived SD map).

    One JSON line per pose: {x, y, yaw, kind} (metres, degrees) for `data raster --x --y --yaw` and
    `sample --from-hd --pose`, or with --latlon {lat, lon, heading, kind} for `sample --osm --center`.
    An SD raster centred anywhere else (between roads, north up) is unlike every training scene.
    """
    import json
    import math

    import numpy as np

    from cmtool.data.frames import DEFAULT_MIX, KINDS, FrameSampler, read_sd_source

    mix = DEFAULT_MIX
    if kind is not None:
        wanted = [k.strip() for k in kind.split(",") if k.strip()]
        unknown = [k for k in wanted if k not in KINDS]
        if unknown or not wanted:
            raise CmtoolError(f"--kind {kind!r}: expected some of {', '.join(KINDS)}")
        mix = {k: DEFAULT_MIX[k] for k in wanted}
    sd_map = read_sd_source(map_file)
    if not sd_map.roads:
        raise CmtoolError(f"{map_file}: no drivable roads in the map")
    if latlon and not {"lat0", "lon0"} <= set(sd_map.meta):
        raise CmtoolError(f"{map_file}: --latlon needs a map with a geographic origin (an OpenStreetMap file or "
                          "its `cmtool data import --format osm`)")
    frames = FrameSampler(sd_map).sample(n, np.random.default_rng(seed), mix, near_junction_m=near_junction)
    if len(frames) < n:
        what = " of kind " + kind if kind else ""
        what += "" if near_junction is None else f" within {near_junction:g} m of a junction"
        raise CmtoolError(f"{map_file}: found {len(frames)} of {n} poses{what}")
    rows = [{"x": round(f.pose.x, 2), "y": round(f.pose.y, 2), "yaw": round(math.degrees(f.pose.yaw), 1),
             "kind": f.label} for f in frames]
    if latlon:
        from cmtool.core.geo import LocalProjection

        proj = LocalProjection(sd_map.meta["lat0"], sd_map.meta["lon0"])
        latlons = proj.to_latlon(np.array([[r["x"], r["y"]] for r in rows]))
        rows = [{"lat": round(float(lat), 7), "lon": round(float(lon), 7),
                 "heading": round((90.0 - r["yaw"]) % 360.0, 1), "kind": r["kind"]}
                for (lat, lon), r in zip(latlons, rows)]
    text = "".join(json.dumps(r) + "\n" for r in rows)
    if out is None:
        click.echo(text, nl=False)
        return
    from cmtool.core.jsonio import write_text_atomic

    write_text_atomic(out, text)
    click.echo(f"{out}: {len(rows)} poses")


@data.command()
@click.argument("sources", nargs=-1, type=InPath())
@click.option("--recipe", type=InPath(dir_okay=False),
              help="Also the SD maps of this data recipe's procedural cities, framed and jittered as its build does.")
@click.option("--maps", default=4, show_default=True, type=click.IntRange(1, 100),
              help="With --recipe: maps per city, each with the recipe's scenes_per_map frames.")
@click.option("--n", default=500, show_default=True, type=click.IntRange(1, MAX_FRAMES), help="Frames per map file.")
@click.option("--seed", default=0, show_default=True, type=SEED, help="Seed of the frames.")
@click.option("--png", type=OutPath(dir_okay=False),
              help="Also write the SD rasters of some frames of each source, a row each.")
@click.option("--json", "json_out", type=OutPath(dir_okay=False), help="Write the numbers here.")
def frames(sources, recipe, maps, n, seed, png, json_out):
    """Per-frame statistics of SD maps side by side: roads, road length, one-way, divided-road,
    lane-count and major-road shares, junctions. SOURCES: OpenStreetMap .osm/.osm.pbf files, SD or HD map JSON
    (framed as `data poses` frames them); --recipe adds the maps a dataset would be built from."""
    import numpy as np

    from cmtool.data.realism import file_column, recipe_columns, stats_table

    if not sources and recipe is None:
        raise CmtoolError("nothing to measure: give map files and/or --recipe")
    columns = [file_column(path, n, seed) for path in sources]
    if recipe is not None:
        from cmtool.train.recipe import load_recipe

        columns += recipe_columns(load_recipe(recipe).data, maps, seed, str(recipe))
    names = [c.name for c in columns]
    if len(set(names)) < len(names):
        raise CmtoolError(f"two sources share a name ({', '.join(names)}); rename a file")
    stats = {c.name: c.stats() for c in columns}
    click.echo(stats_table(stats))
    if png is not None:
        from cmtool.viz.draw import grid, sd_panel, title_strip
        from cmtool.viz.show import write_png

        tiles = [np.concatenate([title_strip(f"{c.name}: {label}", 192), sd_panel(raster, 192)])
                 for c in columns if c.name != "derived" for raster, label in c.rasters(6)]
        write_png(png, grid(tiles, columns=6))
        click.echo(f"wrote {png}")
    if json_out is not None:
        from cmtool.core.jsonio import write_json

        write_json(json_out, {"n": n, "maps": maps, "seed": seed, "sources": [str(s) for s in sources],
                              "recipe": str(recipe) if recipe else None, "columns": stats})
        click.echo(f"wrote {json_out}")


@data.command()
@click.argument("maps", nargs=-1, type=InPath())
@click.option("--seeds", default=2, show_default=True, type=click.IntRange(1, 100),
              help="Without MAPS: procedural seeds per city style.")
@click.option("--extent", default=800.0, show_default=True, type=Finite(min=100, max=20000),
              help="Without MAPS: side of each procedural city, metres.")
def stats(maps, seeds, extent):
    """Per-city statistics of HD maps: lanes per road, block length, intersection degree, curvature,
    one-way share. Without MAPS, of procedural cities of all four styles."""
    from cmtool.data.stats import map_stats
    from cmtool.formats.mapfile import read_hd_map

    if maps:
        rows = {}
        for path in maps:
            hd = read_hd_map(path)
            rows.setdefault(hd.city, []).append(map_stats(hd))
    else:
        from cmtool.data.synth import generate_city

        rows = {c: [map_stats(generate_city(c, seed=s, extent=extent)) for s in range(seeds)] for c in CITY_CHOICES}
    click.echo(_stats_table(rows))


def _stats_table(rows: dict[str, list[dict[str, float]]]) -> str:
    """Mean of each statistic per city, as an aligned text table (cities as columns)."""
    cities = list(rows)
    keys = list(next(iter(rows.values()))[0])
    width = max(len(k) for k in keys)
    lines = [f"{'statistic':<{width}}  " + "  ".join(f"{c:>9}" for c in cities)]
    for k in keys:
        vals = [sum(r[k] for r in rows[c]) / len(rows[c]) for c in cities]
        lines.append(f"{k:<{width}}  " + "  ".join(f"{v:>9.3f}" for v in vals))
    counts = "  ".join(f"{len(rows[c]):>9d}" for c in cities)
    lines.append(f"{'maps':<{width}}  {counts}")
    return "\n".join(lines)


@data.command()
@click.option("--recipe", required=True, type=InPath(), help="Recipe TOML (see recipes/).")
@click.option("--out", required=True, type=OutPath(file_okay=False), help="Dataset directory.")
@click.option("--workers", default=None, type=click.IntRange(min=1), help="Worker processes [default: min(2, CPUs)].")
def build(recipe, out, workers):
    """Build (or resume building) a sharded dataset cache from a recipe."""
    from cmtool.data.cache import build_dataset
    from cmtool.train.recipe import load_recipe

    summary = build_dataset(load_recipe(recipe), out, workers=workers)
    for split, info in summary["splits"].items():
        cities = ", ".join(f"{c} {n}" for c, n in info["cities"].items())
        click.echo(f"{split}: {info['scenes']} scenes ({cities}); {_line_cap(info, summary['num_lines'])}")
        sources = info["line_cap"]["sources"]
        for source, row in sources.items() if len(sources) > 1 else ():
            if row["scenes_cut"]:
                click.echo(f"  {source}: {_lost(row['scenes_cut'], row['pieces_cut'], row['scenes'])}")
        click.echo(f"  frames: {_shares(info['frames']['kinds'], info['scenes'])}")
        if info["frames"]["tags"]:
            click.echo(f"  tags: {_shares(info['frames']['tags'], info['scenes'])}")
    click.echo(f"{out}: built in {summary['seconds']:.1f} s")


def _line_cap(info: dict, num_lines: int) -> str:
    """What the line cap cut from a split, in words."""
    cap = info["line_cap"]
    if not cap["scenes_cut"]:
        return f"no scene hit the line cap ({num_lines} lines)"
    return f"line cap {num_lines}: {_lost(cap['scenes_cut'], cap['pieces_cut'], info['scenes'])}"


def _shares(counts: dict[str, int], total: int) -> str:
    return ", ".join(f"{k} {n} ({100.0 * n / total:.0f}%)" for k, n in counts.items())


def _lost(scenes: int, pieces: int, total: int) -> str:
    return (f"{scenes} scene{'s' * (scenes != 1)} ({100.0 * scenes / total:.1f}%) lost {pieces} lane "
            f"piece{'s' * (pieces != 1)}")


@data.command()
@click.argument("data_dir", type=InPath(file_okay=False))
@click.option("--n", default=16, show_default=True, type=click.IntRange(min=1), help="Number of scenes.")
@click.option("--png", type=OutPath(dir_okay=False), help="Picture grid to write.")
@click.option("--rrd", type=OutPath(dir_okay=False), help="Rerun recording to write.")
@click.option("--split", default=None, help="Split to show [default: all].")
@click.option("--seed", default=0, show_default=True, type=SEED, help="Seed of the scene choice.")
def show(data_dir, n, png, rrd, split, seed):
    """Show scenes of a dataset: HD lanes beside their SD raster, as a PNG grid and/or a Rerun recording."""
    from cmtool.viz.show import show_dataset

    if png is None and rrd is None:
        raise CmtoolError("nothing to write: give --png and/or --rrd")
    show_dataset(data_dir, n=n, png=png, rrd=rrd, split=split, seed=seed)
    for path in (png, rrd):
        if path is not None:
            click.echo(f"wrote {path}")
