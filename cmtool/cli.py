"""The ``cmtool`` command line.

Commands are thin: they parse options, call the library and print. Library modules are imported
inside each command so ``cmtool --help`` stays fast. Every user error (a :class:`CmtoolError` or a
bad option) ends with one ``Error: ...`` line on stderr and a non-zero exit, never a traceback.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import click

from cmtool import __version__
from cmtool.errors import CmtoolError
from cmtool.sample import DEFAULT_SAMPLER, DEFAULT_SMOOTH, SAMPLERS
from cmtool.train import PRECISIONS

CITY_CHOICES = ("LAV", "PIT", "SGP", "BOS")
CITY_CFG_HELP = ("Guidance weight on the city label (1: the label as trained; > 1 strengthens the city's style, "
                 "such as its driving side, at one more model pass per step).")

SMOOTH_OPTION = click.option(
    "--smooth", default=DEFAULT_SMOOTH, show_default=True, type=click.IntRange(min=0),
    help="Replace each decoded lane and light line by its least-squares Bezier curve with this many control points "
         "(0: the decoder's raw points).")


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="cmtool")
def cli():
    """cmtool: controllable lane-level HD map generation from SD maps (ControlMap)."""


@cli.group()
def data():
    """Maps and datasets: procedural cities, real-map import, SD maps, dataset cache."""


@data.command()
@click.option("--city", required=True, callback=lambda ctx, param, v: _city(v), help="City style: LAV, PIT, SGP or BOS.")
@click.option("--seed", default=0, show_default=True, help="Random seed.")
@click.option("--extent", default=800.0, show_default=True, help="Side of the square city, metres.")
@click.option("--out", required=True, type=click.Path(dir_okay=False, path_type=Path), help="HD map JSON to write.")
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


IMPORT_FORMATS = ("av2", "lanelet2", "nuplan", "osm")


@data.command("import")
@click.option("--format", "fmt", required=True, type=click.Choice(IMPORT_FORMATS),
              help="av2, lanelet2, nuplan: HD maps; osm: an OpenStreetMap .osm/.osm.pbf file to an SD map.")
@click.argument("file", type=click.Path(path_type=Path))
@click.option("--out", required=True, type=click.Path(dir_okay=False, path_type=Path), help="Map JSON to write.")
@click.option("--city", default=None, help="City code to record (default: from the file or format).")
def import_(fmt, file, out, city):
    """Import a real map into cmtool's HD (or, for osm, SD) map JSON."""
    if fmt == "osm":
        from cmtool.data.osm import read_osm

        sd = read_osm(file)
        if city:
            sd.city = city
        sd.save(out)
        click.echo(f"{out}: SD map, {len(sd.roads)} roads")
        return
    from cmtool.data.importers import import_hd_map

    hd = import_hd_map(fmt, file, city=city)
    hd.save(out)
    click.echo(
        f"{out}: HD map of {hd.city}, {len(hd.lanes)} lanes, {sum(len(l.successors) for l in hd.lanes.values())} "
        f"successor edges, {len(hd.stop_lines)} stop lines, {len(hd.crosswalks)} crosswalks"
    )


@data.command()
@click.argument("hd_map", type=click.Path(path_type=Path))
@click.option("--out", required=True, type=click.Path(dir_okay=False, path_type=Path),
              help="SD map to write: cmtool JSON, or OpenStreetMap XML when the name ends in .osm.")
@click.option("--origin", help="With an .osm output: LAT,LON where the map's (0, 0) lies.")
@click.option("--offset", default=0.0, show_default=True, help="Jitter: random shift of up to this many metres.")
@click.option("--rotation", default=0.0, show_default=True, help="Jitter: random rotation of up to this many degrees.")
@click.option("--drop-minor", default=0.0, show_default=True, help="Jitter: probability of dropping each minor road.")
@click.option("--seed", default=0, show_default=True, help="Seed of the jitter.")
def sd(hd_map, out, origin, offset, rotation, drop_minor, seed):
    """Derive the SD map (one polyline per road, as OpenStreetMap shows it) of an HD map."""
    from cmtool.data.hdmap import HDMap
    from cmtool.data.sd_derive import SDJitter, derive_sd

    if offset < 0 or rotation < 0 or not 0.0 <= drop_minor <= 1.0:
        raise CmtoolError("jitter must be non-negative and --drop-minor within [0, 1]")
    to_osm = out.suffix == ".osm"
    if to_osm != (origin is not None):
        raise CmtoolError("an .osm output needs --origin LAT,LON" if to_osm else "--origin goes with an .osm output")
    if to_osm:
        lat0, lon0 = _origin(origin)
    jitter = SDJitter(offset, rotation, drop_minor)
    sd_map = derive_sd(HDMap.load(hd_map), jitter=jitter if jitter.enabled else None, seed=seed)
    if to_osm:
        from cmtool.data.osm import write_osm

        write_osm(sd_map, out, lat0, lon0)
    else:
        sd_map.save(out)
    click.echo(f"{out}: SD map, {len(sd_map.roads)} roads")


@data.command()
@click.argument("sd_map", type=click.Path(path_type=Path))
@click.option("--x", "x", type=float, default=None, help="Frame centre x, metres [default: map centre].")
@click.option("--y", "y", type=float, default=None, help="Frame centre y, metres [default: map centre].")
@click.option("--yaw", default=90.0, show_default=True, help="Heading of the frame's forward axis, degrees (90 = north up).")
@click.option("--png", required=True, type=click.Path(dir_okay=False, path_type=Path), help="SD raster PNG to write.")
def raster(sd_map, x, y, yaw, png):
    """Rasterise a 64 m window of an SD map into the 128 x 128 RGB control image (README: SD raster)."""
    import cv2
    import numpy as np

    from cmtool.data.sd_raster import rasterize_sd
    from cmtool.data.sdmap import SDMap

    sd_obj = SDMap.load(sd_map)
    if not sd_obj.roads:
        raise CmtoolError(f"{sd_map}: the SD map has no roads")
    pts = np.concatenate([r.polyline for r in sd_obj.roads])
    cx, cy = (pts.min(0) + pts.max(0)) / 2.0
    image = rasterize_sd(sd_obj, cx if x is None else x, cy if y is None else y, np.radians(yaw))
    png.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(png), cv2.cvtColor(image, cv2.COLOR_RGB2BGR)):
        raise CmtoolError(f"{png}: could not write the picture (is the extension .png?)")
    click.echo(f"{png}: SD raster, {int((image[..., 0] > 0).sum())} road pixels")


@data.command()
@click.argument("map_file", type=click.Path(path_type=Path))
@click.option("--n", default=1, show_default=True, type=click.IntRange(min=1), help="Poses to print.")
@click.option("--seed", default=0, show_default=True, help="Random seed.")
@click.option("--kind", help="Only these kinds of frame, comma-separated: junction, approach, exit, end, curve, "
              "straight [default: all, in the dataset's mix].")
@click.option("--near-junction", type=click.FloatRange(min=0), help="Only poses within this many metres of a junction.")
@click.option("--latlon", is_flag=True, help="Print {lat, lon, heading} (compass degrees) for `sample --osm --center`; "
              "needs a map with a geographic origin (an OpenStreetMap file or its import).")
@click.option("--out", type=click.Path(dir_okay=False, path_type=Path), help="Write the lines to this .jsonl file.")
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
        from cmtool.data.geo import LocalProjection

        proj = LocalProjection(sd_map.meta["lat0"], sd_map.meta["lon0"])
        latlons = proj.to_latlon(np.array([[r["x"], r["y"]] for r in rows]))
        rows = [{"lat": round(float(lat), 7), "lon": round(float(lon), 7),
                 "heading": round((90.0 - r["yaw"]) % 360.0, 1), "kind": r["kind"]}
                for (lat, lon), r in zip(latlons, rows)]
    text = "".join(json.dumps(r) + "\n" for r in rows)
    if out is None:
        click.echo(text, nl=False)
        return
    from cmtool.data.jsonio import write_text_atomic

    write_text_atomic(out, text)
    click.echo(f"{out}: {len(rows)} poses")


@data.command()
@click.argument("sources", nargs=-1, type=click.Path(path_type=Path))
@click.option("--recipe", type=click.Path(dir_okay=False, path_type=Path),
              help="Also the SD maps of this data recipe's procedural cities, framed and jittered as its build does.")
@click.option("--maps", default=4, show_default=True, type=click.IntRange(min=1),
              help="With --recipe: maps per city, each with the recipe's scenes_per_map frames.")
@click.option("--n", default=500, show_default=True, type=click.IntRange(min=1), help="Frames per map file.")
@click.option("--seed", default=0, show_default=True, help="Seed of the frames.")
@click.option("--png", type=click.Path(dir_okay=False, path_type=Path),
              help="Also write the SD rasters of some frames of each source, a row each.")
@click.option("--json", "json_out", type=click.Path(dir_okay=False, path_type=Path), help="Write the numbers here.")
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
        columns += recipe_columns(recipe, maps, seed)
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
        from cmtool.data.jsonio import write_json

        write_json(json_out, {"n": n, "maps": maps, "seed": seed, "sources": [str(s) for s in sources],
                              "recipe": str(recipe) if recipe else None, "columns": stats})
        click.echo(f"wrote {json_out}")


@data.command()
@click.argument("maps", nargs=-1, type=click.Path(path_type=Path))
@click.option("--seeds", default=2, show_default=True, help="Without MAPS: procedural seeds per city style.")
@click.option("--extent", default=800.0, show_default=True, help="Without MAPS: side of each procedural city, metres.")
def stats(maps, seeds, extent):
    """Per-city statistics of HD maps: lanes per road, block length, intersection degree, curvature,
    one-way share. Without MAPS, of procedural cities of all four styles."""
    from cmtool.data.hdmap import HDMap
    from cmtool.data.stats import map_stats

    if maps:
        rows = {}
        for path in maps:
            hd = HDMap.load(path)
            rows.setdefault(hd.city, []).append(map_stats(hd))
    else:
        from cmtool.data.synth import generate_city

        if seeds < 1:
            raise CmtoolError("--seeds must be at least 1")
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
@click.option("--recipe", required=True, type=click.Path(path_type=Path), help="Recipe TOML (see recipes/).")
@click.option("--out", required=True, type=click.Path(file_okay=False, path_type=Path), help="Dataset directory.")
@click.option("--workers", default=None, type=click.IntRange(min=1), help="Worker processes [default: min(2, CPUs)].")
def build(recipe, out, workers):
    """Build (or resume building) a sharded dataset cache from a recipe."""
    from cmtool.data.cache import build_dataset

    summary = build_dataset(recipe, out, workers=workers)
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
@click.argument("data_dir", type=click.Path(file_okay=False, path_type=Path))
@click.option("--n", default=16, show_default=True, type=click.IntRange(min=1), help="Number of scenes.")
@click.option("--png", type=click.Path(dir_okay=False, path_type=Path), help="Picture grid to write.")
@click.option("--rrd", type=click.Path(dir_okay=False, path_type=Path), help="Rerun recording to write.")
@click.option("--split", default=None, help="Split to show [default: all].")
@click.option("--seed", default=0, show_default=True, help="Seed of the scene choice.")
def show(data_dir, n, png, rrd, split, seed):
    """Show scenes of a dataset: HD lanes beside their SD raster, as a PNG grid and/or a Rerun recording."""
    from cmtool.viz.show import show_dataset

    if png is None and rrd is None:
        raise CmtoolError("nothing to write: give --png and/or --rrd")
    show_dataset(data_dir, n=n, png=png, rrd=rrd, split=split, seed=seed)
    for path in (png, rrd):
        if path is not None:
            click.echo(f"wrote {path}")


@cli.command("train")
@click.argument("stage", type=click.Choice(["rvae", "decoder", "dit", "controlnet", "pipeline"]))
@click.option("--recipe", required=True, type=click.Path(path_type=Path), help="Recipe TOML (see recipes/).")
@click.option("--out", type=click.Path(file_okay=False, path_type=Path), help="Run folder [default: the recipe's train.out].")
@click.option("--resume", is_flag=True, help="Continue from the run folder's newest checkpoint (pipeline: from where "
              "it stopped, finished stages skipped).")
@click.option("--data", "data_dir", type=click.Path(file_okay=False, path_type=Path),
              help="Override train.data (the dataset cache); pipeline: a dataset built before, instead of its data "
                   "stage.")
@click.option("--steps", type=click.IntRange(min=1), help="Override train.steps (e.g. for a quick try).")
@click.option("--precision", type=click.Choice(PRECISIONS),
              help="Override train.precision: bf16 autocast pays on CUDA and on CPUs with native bf16 "
                   "(AVX512-BF16, AMX); fp32 elsewhere on CPU.")
@click.option("--device", help="torch device [default: cuda when available, else cpu].")
@click.option("--quiet", is_flag=True, help="No progress line.")
def train_cmd(stage, recipe, out, resume, data_dir, steps, precision, device, quiet):
    """Train one stage: rvae (stage 1), dit (stage 2) or controlnet (stage 3); decoder trains a
    finished RVAE's decoder further on its frozen encoder's latents (DiTs trained on them stay valid).
    pipeline runs the whole chain of a pipeline recipe (recipes/tiny-cpu/pipeline.toml): data, RVAE,
    decoder, DiT, ControlMap, packed weights and their evaluation, each stage into a folder of --out.

    Multi-GPU / multi-node: launch with torchrun, e.g.
    torchrun --nproc_per_node 8 -m cmtool train dit --recipe recipes/paper/dit-b.toml
    """
    from cmtool.recipe import load_recipe

    rec = load_recipe(recipe)
    if stage == "pipeline":
        _train_pipeline(rec, out, resume, data_dir, steps, precision, device, quiet)
        return
    if rec.pipeline.rvae:
        raise CmtoolError(f"{recipe}: a pipeline recipe; run it with `cmtool train pipeline`")
    if rec.train.stage and rec.train.stage != stage:
        raise CmtoolError(f"{recipe}: a recipe for the {rec.train.stage} stage, not {stage}")
    if steps is not None:
        rec.train.steps = steps
    if precision is not None:
        rec.train.precision = precision
    if data_dir is not None:
        rec.train.data = str(data_dir)
    run_dir = out or (Path(rec.train.out) if rec.train.out else None)
    if run_dir is None:
        raise CmtoolError(f"{recipe}: no run folder: give --out or set train.out")

    from cmtool.train.loop import train
    from cmtool.train.stages import STAGES

    final = train(STAGES[stage](rec, _device(device)), run_dir, resume=resume, progress=not quiet)
    click.echo(f"checkpoint: {final}")


def _train_pipeline(rec, out, resume, data_dir, steps, precision, device, quiet):
    from cmtool.train.pipeline import Pipeline, summary

    if not rec.pipeline.rvae:
        raise CmtoolError(f"{rec.path}: no [pipeline] table; `train pipeline` takes a pipeline recipe "
                          "(recipes/tiny-cpu/pipeline.toml)")
    if steps is not None:
        raise CmtoolError("--steps: set train.steps in the stage recipes a pipeline names")
    if out is None:
        raise CmtoolError("train pipeline: give --out, the folder of its stages")
    if (out / "pipeline.json").exists() and not resume and os.environ.get("RANK", "0") == "0":
        raise CmtoolError(f"{out}: holds a pipeline run; pass --resume to continue it or choose another --out")
    if data_dir is not None and not (data_dir / "manifest.json").is_file():
        raise CmtoolError(f"--data {data_dir}: not a dataset (no manifest.json); build one with `cmtool data build`")
    if precision is not None:
        rec.pipeline.precision = precision
    report = Pipeline(rec, out, _device(device), progress=not quiet, data_dir=data_dir).run()
    click.echo(summary(report))
    if (out / "eval" / "summary.md").is_file():
        click.echo(f"evaluation: {out / 'eval' / 'summary.md'}; weights: {out / 'weights'}")


def _origin(value: str) -> tuple[float, float]:
    """``--origin LAT,LON`` as numbers within the range the local projection serves."""
    from cmtool.sample.inputs import parse_points

    lat0, lon0 = parse_points(value, ("lat", "lon"), {}, "--origin")[0]
    if not (-80.0 <= lat0 <= 80.0 and -180.0 <= lon0 <= 180.0):
        raise CmtoolError(f"--origin {value}: latitude must be within [-80, 80], longitude within [-180, 180]")
    return lat0, lon0


def _device(name: str | None):
    import torch

    dev = torch.device(name) if name else torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise CmtoolError(f"--device {name}: CUDA is not available on this machine")
    return dev


def _checkpoint(path: Path | None) -> Path:
    """``--ckpt``, or the ControlMap shipped with the package when it is not given."""
    from cmtool.release import bundled_checkpoint

    return bundled_checkpoint() if path is None else path


SAMPLE_HELP = """Generate lane-level HD maps from SD maps with ControlMap, recording every denoising step.

\b
SD input (at most one kind; none: maps from the city label alone):
  --sd PNG|DIR              control rasters, or plain road drawings (converted)
  --osm FILE --center LAT,LON [--heading DEG]
  --from-hd MAP.json [--pose X,Y,YAW]   (the ground truth is shown beside the map)
--center and --pose also take a .jsonl file of points for many inputs at once.
"""


@cli.command(help=SAMPLE_HELP)
@click.option("--ckpt", type=click.Path(path_type=Path),
              help="ControlMap (or DiT) checkpoint or run folder [default: the weights shipped with cmtool].")
@click.option("--sd", "sd_paths", multiple=True, type=click.Path(path_type=Path),
              help="SD raster / road drawing picture, or a folder of them (repeatable).")
@click.option("--osm", type=click.Path(path_type=Path), help="OpenStreetMap .osm/.osm.pbf file.")
@click.option("--center", help="With --osm: LAT,LON of the frame centre, or a .jsonl of {lat, lon, heading}.")
@click.option("--heading", default=0.0, show_default=True, help="With --osm: compass heading that points up, degrees.")
@click.option("--from-hd", "from_hd", type=click.Path(path_type=Path), help="HD map JSON (procedural or imported).")
@click.option("--pose", help="With --from-hd: X,Y,YAW (m, m, degrees) or a .jsonl of {x, y, yaw} [default: a random "
              "drivable pose].")
@click.option("--num", default=1, show_default=True, type=click.IntRange(min=1), help="Maps per SD input.")
@click.option("--seed", default=0, show_default=True, help="Random seed.")
@click.option("--steps", default=50, show_default=True, type=click.IntRange(min=1), help="Denoising steps.")
@click.option("--sampler", default=DEFAULT_SAMPLER, show_default=True, type=click.Choice(SAMPLERS))
@click.option("--eta", default=0.0, show_default=True, help="DDIM noise (0 deterministic, 1 like DDPM).")
@click.option("--city", default="auto", show_default=True,
              help="City label of the checkpoint, or none; auto: the HD map's city, else none.")
@click.option("--cfg", default=1.0, show_default=True, help="Guidance weight w >= 0 on the SD control (0: ignore it).")
@click.option("--city-cfg", default=1.0, show_default=True, help=CITY_CFG_HELP)
@SMOOTH_OPTION
@click.option("--batch", default=16, show_default=True, type=click.IntRange(min=1), help="Maps per forward pass.")
@click.option("--out", default=Path("samples"), show_default=True, type=click.Path(file_okay=False, path_type=Path),
              help="Folder for the lane graphs and pictures.")
@click.option("--rrd", type=click.Path(dir_okay=False, path_type=Path), help="Recording to write [default: OUT/sample.rrd].")
@click.option("--grid", type=click.Path(dir_okay=False, path_type=Path),
              help="Also write all maps' pictures stacked into this PNG (a gallery).")
@click.option("--spawn", is_flag=True, help="Also stream live to a newly started Rerun viewer.")
@click.option("--connect", "connect_url", help="Also stream live to a running viewer at this gRPC URL.")
@click.option("--no-log", is_flag=True, help="No recording (fastest).")
@click.option("--device", help="torch device [default: cuda when available, else cpu].")
@click.option("--quiet", is_flag=True, help="No progress line.")
def sample(ckpt, sd_paths, osm, center, heading, from_hd, pose, num, seed, steps, sampler, eta, city, cfg, city_cfg,
           smooth, batch, out, rrd, grid, spawn, connect_url, no_log, device, quiet):
    import shlex

    from cmtool.sample import inputs as src
    from cmtool.sample.generator import Generator
    from cmtool.sample.run import SampleSettings, plan, run_sample, summary_table

    kinds = [name for name, given in (("--sd", sd_paths), ("--osm", osm), ("--from-hd", from_hd)) if given]
    if len(kinds) > 1:
        raise CmtoolError(f"give one kind of SD input, not {' and '.join(kinds)}")
    if center is not None and osm is None:
        raise CmtoolError("--center goes with --osm")
    if pose is not None and from_hd is None:
        raise CmtoolError("--pose goes with --from-hd")
    if no_log and (rrd or spawn or connect_url):
        raise CmtoolError("--no-log cannot be combined with --rrd, --spawn or --connect")
    if spawn and connect_url:
        raise CmtoolError("give --spawn or --connect, not both")
    settings = SampleSettings(num=num, seed=seed, steps=steps, sampler=sampler, eta=eta, cfg=cfg, city=city,
                              city_cfg=city_cfg, batch=batch)
    settings.check()
    if sd_paths:
        inputs = src.image_inputs(sd_paths)
    elif osm is not None:
        if center is None:
            raise CmtoolError("--osm needs --center LAT,LON (or a .jsonl of centres)")
        inputs = src.osm_inputs(osm, src.parse_points(center, ("lat", "lon", "heading"), {"heading": heading},
                                                      "--center"))
    elif from_hd is not None:
        poses = src.parse_points(pose, ("x", "y", "yaw"), {}, "--pose") if pose is not None else None
        inputs = src.hd_inputs(from_hd, poses, seed)
    else:
        inputs = [src.ControlInput("uncond", None, "no SD input")]
    gen = Generator.load(_checkpoint(ckpt), _device(device), smooth)
    jobs = plan(gen, inputs, settings)
    for item in inputs:
        if item.note:
            click.echo(f"note: {item.note}", err=True)
    if not no_log and rrd is None:
        rrd = out / "sample.rrd"
    viewer = "spawn" if spawn else connect_url
    command = shlex.join(["cmtool", *sys.argv[1:]])
    maps = run_sample(gen, jobs, settings, out, None if no_log else rrd, viewer, command, progress=not quiet,
                      grid=grid)
    click.echo(summary_table(maps))
    click.echo(f"wrote {len(maps)} lane graph{'s' if len(maps) > 1 else ''} and picture{'s' if len(maps) > 1 else ''} "
               f"to {out}" + ("" if no_log or rrd is None else f"; recording {rrd}"))


@cli.command()
@click.option("--generated", required=True, type=click.Path(dir_okay=False, path_type=Path),
              help="Generated lane graphs (.jsonl).")
@click.option("--reference", required=True, type=click.Path(dir_okay=False, path_type=Path),
              help="Reference (ground-truth) lane graphs (.jsonl), paired line by line.")
@click.option("--control", type=click.Path(path_type=Path),
              help="SD controls, paired in order: a folder of SD pictures or a .npy stack (N, 128, 128, 3).")
@click.option("--json", "json_out", type=click.Path(dir_okay=False, path_type=Path), help="Write all numbers here.")
@click.option("--backbone", default="resnet50-seeded", show_default=True,
              type=click.Choice(["resnet50-seeded", "resnet50-imagenet"]), help="Feature network of the recall metrics.")
@click.option("--weights", type=click.Path(dir_okay=False, path_type=Path),
              help="ImageNet ResNet-50 weights file [default: torchvision's file in the torch hub cache].")
@click.option("--no-features", is_flag=True, help="Skip the feature metrics (precision/recall, Control/GT Recall).")
@click.option("--device", help="torch device [default: cuda when available, else cpu].")
def metrics(generated, reference, control, json_out, backbone, weights, no_features, device):
    """Score generated lane graphs against a reference set (and their SD controls): topology FDs,
    improved precision/recall, Control / GT Recall with p-values, and geometric lane metrics."""
    from cmtool.data.jsonio import write_json
    from cmtool.data.lanegraph import read_jsonl
    from cmtool.eval.features import FeatureExtractor
    from cmtool.eval.metrics import evaluate, load_controls, summary_table

    gen, ref = read_jsonl(generated), read_jsonl(reference)
    controls = load_controls(control) if control is not None else None
    extractor = None if no_features else FeatureExtractor(backbone, weights, _device(device))
    result = evaluate(gen, ref, controls, extractor, features=not no_features)
    click.echo(summary_table({generated.name: result}))
    click.echo(f"{result['scenes']} scene pairs in {sum(result['seconds'].values()):.1f} s ("
               + ", ".join(f"{k} {v:.1f} s" for k, v in result["seconds"].items()) + ")"
               + ("" if no_features else f"; features: {result['backbone']['name']}"))
    if json_out is not None:
        write_json(json_out, {"generated": str(generated), "reference": str(reference),
                              "control": str(control) if control else None, **result})
        click.echo(f"wrote {json_out}")


@cli.command("eval")
@click.option("--ckpt", type=click.Path(path_type=Path),
              help="ControlMap checkpoint or run folder [default: the weights shipped with cmtool].")
@click.option("--data", "data_dir", required=True, type=click.Path(file_okay=False, path_type=Path),
              help="Dataset cache (cmtool data build).")
@click.option("--split", default="test", show_default=True, help="Split to evaluate on.")
@click.option("--n", default=3904, show_default=True, type=click.IntRange(min=1), help="Scenes (the first N of the split).")
@click.option("--cfg", default=1.0, show_default=True, help="ControlMap's guidance weight.")
@click.option("--steps", default=50, show_default=True, type=click.IntRange(min=1), help="Denoising steps.")
@click.option("--sampler", default=DEFAULT_SAMPLER, show_default=True, type=click.Choice(SAMPLERS))
@click.option("--seed", default=0, show_default=True, help="Random seed (the same noise for both methods).")
@SMOOTH_OPTION
@click.option("--batch", default=64, show_default=True, type=click.IntRange(min=1), help="Maps per forward pass.")
@click.option("--out", required=True, type=click.Path(file_okay=False, path_type=Path),
              help="Folder for metrics.json, summary.md, eval.rrd and the generation cache.")
@click.option("--backbone", default="resnet50-seeded", show_default=True,
              type=click.Choice(["resnet50-seeded", "resnet50-imagenet"]), help="Feature network of the recall metrics.")
@click.option("--weights", type=click.Path(dir_okay=False, path_type=Path), help="ImageNet ResNet-50 weights file.")
@click.option("--no-features", is_flag=True, help="Skip the feature metrics.")
@click.option("--rrd-samples", default=64, show_default=True, type=click.IntRange(min=0),
              help="Scenes whose maps go into eval.rrd (scores go in for all).")
@click.option("--device", help="torch device [default: cuda when available, else cpu].")
@click.option("--quiet", is_flag=True, help="No progress line.")
def eval_cmd(ckpt, data_dir, split, n, cfg, steps, sampler, seed, smooth, batch, out, backbone, weights, no_features,
             rrd_samples, device, quiet):
    """Evaluate a ControlMap checkpoint on a test split against its unguided DiT (paper Tables 1-2)."""
    import math

    from cmtool.eval.evaluation import EvalSettings, run_eval
    from cmtool.eval.features import FeatureExtractor
    from cmtool.sample.generator import Generator

    if not (math.isfinite(cfg) and cfg >= 0):
        raise CmtoolError(f"--cfg: guidance weight must be a finite number >= 0, got {cfg}")
    dev = _device(device)
    gen = Generator.load(_checkpoint(ckpt), dev, smooth)
    gen.schedule.timesteps(steps)
    extractor = None if no_features else FeatureExtractor(backbone, weights, dev)
    settings = EvalSettings(data=str(data_dir.resolve()), split=split, n=n, cfg=cfg, steps=steps, sampler=sampler,
                            seed=seed, batch=batch)
    run_eval(gen, settings, out, extractor, rrd_samples=rrd_samples, progress=not quiet)
    click.echo((out / "summary.md").read_text())
    click.echo(f"wrote {out / 'metrics.json'}, {out / 'summary.md'}, {out / 'eval.rrd'}")


@cli.command()
@click.argument("maps", type=click.Path(dir_okay=False, path_type=Path))
@click.option("--json", "json_out", type=click.Path(dir_okay=False, path_type=Path), help="Write the full report here.")
@click.option("--repair", is_flag=True, help="Snap near-miss joints, drop lanes under 2 m, merge duplicates; "
              "report the repaired maps.")
@click.option("--out", type=click.Path(dir_okay=False, path_type=Path), help="With --repair: the repaired maps (.jsonl).")
def validate(maps, json_out, repair, out):
    """Check lane graphs (a .json scene or a .jsonl of scenes) for what planners need: dangling lanes,
    bad successor joins, crossings outside intersections, self-intersections, short lanes, kinks;
    routability; a validity score in [0, 1] per scene."""
    import numpy as np

    from cmtool.data.jsonio import write_json
    from cmtool.data.lanegraph import read_jsonl, write_jsonl
    from cmtool.eval.repair import repair as repair_graph
    from cmtool.eval.validity import check

    if repair != (out is not None):
        raise CmtoolError("--repair needs --out FILE.jsonl for the repaired maps" if repair else "--out goes with --repair")
    graphs = read_jsonl(maps)
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


@cli.command()
@click.option("--format", "fmt", required=True, type=click.Choice(["lanelet2", "opendrive", "geojson"]),
              help="lanelet2: a Lanelet2 OSM map (.osm); opendrive: an OpenDRIVE 1.6 map (.xodr); "
                   "geojson: GeoJSON features.")
@click.argument("map_path", metavar="MAP", type=click.Path(dir_okay=False, path_type=Path))
@click.option("--origin", help="LAT,LON where the scene's origin (the ego) lies [default: what the map's meta.geo "
                               "records, as maps from `sample --osm` do].")
@click.option("--heading", type=float, help="Compass heading of the scene's forward axis, degrees [default: meta.geo's, "
                                            "else 0].")
@click.option("--scene", default=0, show_default=True, type=click.IntRange(min=0), help="Scene of a .jsonl file.")
@click.option("--lane-width", default=3.5, show_default=True, type=click.FloatRange(min=0.5, max=10.0),
              help="Lane width where the map records none and no neighbours give one, metres.")
@click.option("--out", required=True, type=click.Path(dir_okay=False, path_type=Path), help="File to write.")
def export(fmt, map_path, origin, heading, scene, lane_width, out):
    """Export a lane graph (a generated or ground-truth scene) for simulators and GIS tools."""
    import math

    import numpy as np

    from cmtool.data.geojson import to_geojson
    from cmtool.data.jsonio import write_json
    from cmtool.data.lanegraph import read_jsonl
    from cmtool.data.neighbours import graph_neighbours
    from cmtool.eval.validity import check

    graphs = read_jsonl(map_path)
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
    if fmt in ("lanelet2", "opendrive"):
        if fmt == "lanelet2":
            from cmtool.data.lanelet2_export import write_lanelet2 as write
        else:
            from cmtool.data.opendrive_export import write_opendrive as write
        write(graph, out, lat0, lon0, heading, lane_width)
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
        return
    collection = to_geojson(graph, lat0, lon0, heading, lane_width)
    write_json(out, collection)
    kinds: dict[str, int] = {}
    for f in collection["features"]:
        kinds[f["properties"]["kind"]] = kinds.get(f["properties"]["kind"], 0) + 1
    plural = {"lane": "lanes", "boundary": "boundaries", "light": "lights"}
    click.echo(f"{out}: " + ", ".join(f"{v} {plural[k]}" for k, v in kinds.items()))


@cli.group()
def ablate():
    """Ablations on fixed SD maps and seeds: the guidance weight, the city label; what the RVAE keeps."""


def _ablation_setup(ckpt, data_dir, split, n, device, smooth, dit_ok=False):
    from cmtool.data.cache import load_dataset
    from cmtool.sample.generator import Generator

    gen = Generator.load(_checkpoint(ckpt), _device(device), smooth)
    if not gen.has_control and not dit_ok:
        raise CmtoolError(f"{gen.path}: the guidance sweep needs a ControlMap checkpoint")
    data = load_dataset(data_dir, split)
    return gen, [data.scene(i) for i in range(min(n, len(data)))]


def _floats(value: str, option: str) -> list[float]:
    import math

    try:
        out = [float(v) for v in value.split(",") if v.strip()]
    except ValueError:
        raise CmtoolError(f"{option} {value!r}: expected numbers separated by commas") from None
    if not out or any(not math.isfinite(v) or v < 0 for v in out):
        raise CmtoolError(f"{option} {value!r}: expected finite numbers >= 0")
    return out


_ABLATE_COMMON = [
    click.option("--ckpt", type=click.Path(path_type=Path),
                 help="ControlMap checkpoint or run folder [default: the weights shipped with cmtool]."),
    click.option("--data", "data_dir", required=True, type=click.Path(file_okay=False, path_type=Path),
                 help="Dataset cache whose scenes give the SD maps."),
    click.option("--split", default="test", show_default=True),
    click.option("--n", default=64, show_default=True, type=click.IntRange(min=1), help="Scenes (the first N)."),
    click.option("--steps", default=50, show_default=True, type=click.IntRange(min=1), help="Denoising steps."),
    click.option("--sampler", default=DEFAULT_SAMPLER, show_default=True, type=click.Choice(SAMPLERS)),
    SMOOTH_OPTION,
    click.option("--out", required=True, type=click.Path(file_okay=False, path_type=Path), help="Output folder."),
    click.option("--device", help="torch device [default: cuda when available, else cpu]."),
    click.option("--quiet", is_flag=True, help="No progress line."),
]


def _ablate_options(fn):
    for option in reversed(_ABLATE_COMMON):
        fn = option(fn)
    return fn


@ablate.command("cfg")
@_ablate_options
@click.option("--w", "weights", default="0,0.3,0.5,0.7,1.0", show_default=True, help="Guidance weights to sweep.")
@click.option("--seeds", default=2, show_default=True, type=click.IntRange(min=1), help="Maps per scene (diversity).")
@click.option("--backbone", default="resnet50-seeded", show_default=True,
              type=click.Choice(["resnet50-seeded", "resnet50-imagenet"]), help="Feature network of GT Recall.")
@click.option("--weights-file", type=click.Path(dir_okay=False, path_type=Path), help="ImageNet ResNet-50 weights.")
@click.option("--no-features", is_flag=True, help="Skip GT Recall.")
def ablate_cfg(ckpt, data_dir, split, n, steps, sampler, smooth, out, device, quiet, weights, seeds, backbone,
               weights_file, no_features):
    """Sweep the guidance weight w: SD adherence, GT Recall and diversity against w."""
    from cmtool.eval.ablations import cfg_sweep
    from cmtool.eval.features import FeatureExtractor

    ws = _floats(weights, "--w")
    gen, scenes = _ablation_setup(ckpt, data_dir, split, n, device, smooth)
    extractor = None if no_features else FeatureExtractor(backbone, weights_file, gen.device)
    cfg_sweep(gen, scenes, ws, seeds, steps, extractor, out, progress=not quiet, sampler=sampler)
    click.echo((out / "ablate_cfg.md").read_text().rstrip())
    click.echo(f"wrote {out / 'ablate_cfg.md'}, {out / 'ablate_cfg.png'}, {out / 'ablate_cfg.rrd'}")


@ablate.command("city-swap")
@_ablate_options
@click.option("--labels", default="SGP,LAV", show_default=True, help="City labels to compare (or none).")
@click.option("--cfg", default=1.0, show_default=True, help="Guidance weight.")
@click.option("--city-cfg", default=1.0, show_default=True, help=CITY_CFG_HELP)
@click.option("--seed", default=0, show_default=True, help="Random seed (the same noise for every label).")
def ablate_city_swap(ckpt, data_dir, split, n, steps, sampler, smooth, out, device, quiet, labels, cfg, city_cfg, seed):
    """Swap the city label on the same SD maps: the driving side per label (SGP drives on the left).

    --ckpt may also name a DiT: its maps ignore the SD maps, whose two-way roads still judge them
    where they happen to meet (the oncoming-lane columns judge every map)."""
    from cmtool.eval.ablations import city_swap

    names = [v.strip() for v in labels.split(",") if v.strip()]
    gen, scenes = _ablation_setup(ckpt, data_dir, split, n, device, smooth, dit_ok=True)
    for name in names:
        gen.label(name)  # unknown labels fail before any work
    city_swap(gen, scenes, names, steps, cfg, seed, out, progress=not quiet, sampler=sampler, city_cfg=city_cfg)
    click.echo((out / "ablate_city_swap.md").read_text().rstrip())
    click.echo(f"wrote {out / 'ablate_city_swap.md'}, {out / 'ablate_city_swap.png'}")


@ablate.command("dit")
@click.option("--ckpt", "ckpts", multiple=True, required=True, type=click.Path(path_type=Path),
              help="DiT (or ControlMap, sampled without control) checkpoint or run folder (repeatable).")
@click.option("--data", "data_dir", required=True, type=click.Path(file_okay=False, path_type=Path),
              help="Dataset cache whose scenes give the city labels and the reference maps.")
@click.option("--split", default="test", show_default=True)
@click.option("--n", default=128, show_default=True, type=click.IntRange(min=2), help="Scenes (the first N).")
@click.option("--steps", default=50, show_default=True, type=click.IntRange(min=1), help="Denoising steps.")
@click.option("--sampler", default=DEFAULT_SAMPLER, show_default=True, type=click.Choice(SAMPLERS))
@click.option("--seed", default=0, show_default=True, help="Random seed (the same noise for every checkpoint).")
@SMOOTH_OPTION
@click.option("--out", required=True, type=click.Path(file_okay=False, path_type=Path), help="Output folder.")
@click.option("--device", help="torch device [default: cuda when available, else cpu].")
@click.option("--quiet", is_flag=True, help="No progress line.")
def ablate_dit(ckpts, data_dir, split, n, steps, sampler, seed, smooth, out, device, quiet):
    """Compare DiTs on the same city labels and noise: topology Fréchet distances to the scenes' ground
    truth, validity, lanes joined to nothing and crossings per map, driving side by oncoming lanes."""
    from cmtool.data.cache import load_dataset
    from cmtool.eval.ablations import dit_compare
    from cmtool.sample.generator import Generator

    gens = {}
    for path in ckpts:
        gen = Generator.load(_checkpoint(path), _device(device), smooth)
        name = gen.path.parent.parent.name if gen.path.parent.name == "checkpoints" else gen.path.name
        gens[name if name not in gens else str(path)] = gen
    data = load_dataset(data_dir, split)
    dit_compare(gens, [data.scene(i) for i in range(min(n, len(data)))], steps, seed, out, progress=not quiet,
                sampler=sampler)
    click.echo((out / "ablate_dit.md").read_text().rstrip())
    click.echo(f"wrote {out / 'ablate_dit.md'}, {out / 'ablate_dit.png'}")


@ablate.command("rvae")
@click.option("--rvae", "rvae_path", type=click.Path(path_type=Path),
              help="RVAE checkpoint or run folder [default: the decoder shipped with cmtool].")
@click.option("--encoder", "encoder_path", type=click.Path(path_type=Path),
              help="RVAE run whose encoder makes the latents [default: the RVAE's own]; needed for a decoder "
                   "without one, such as the shipped decoder (its encoder does not ship; README: \"Training the "
                   "shipped models further\" recreates it).")
@click.option("--data", "data_dir", required=True, type=click.Path(file_okay=False, path_type=Path),
              help="Dataset cache.")
@click.option("--split", "splits", multiple=True, help="Split to measure (repeatable) [default: every split].")
@click.option("--n", default=64, show_default=True, type=click.IntRange(min=1), help="Scenes per split and city.")
@click.option("--tol", default=1.0, show_default=True, type=click.FloatRange(min=0, min_open=True),
              help="Lane F1 tolerance (m).")
@click.option("--out", required=True, type=click.Path(file_okay=False, path_type=Path), help="Output folder.")
@click.option("--device", help="torch device [default: cuda when available, else cpu].")
@click.option("--quiet", is_flag=True, help="No progress line.")
def ablate_rvae(rvae_path, encoder_path, data_dir, splits, n, tol, out, device, quiet):
    """What the RVAE keeps: lane F1 (at --tol m and at 0.5 m), successor precision, recall and F1 (lanes
    matched within --tol m) and validity of its reconstructions, and the driving side of the ground
    truth and of the reconstructions, per split and city (the ceiling of the city swap)."""
    from cmtool import checkpoint as ckpt
    from cmtool.eval.reconstruction import reconstruction_report
    from cmtool.release import BUNDLED

    dev = _device(device)
    decoder, path = _rvae(rvae_path or BUNDLED / "rvae", "--rvae", dev)
    encoder = decoder
    if encoder_path is not None:
        encoder, enc_path = _rvae(encoder_path, "--encoder", dev)
        if encoder.trunk is None:
            raise CmtoolError(f"--encoder {enc_path}: holds no encoder (a packed decoder); give a `cmtool train "
                              "rvae` run")
        if (encoder.cfg.latent_channels, encoder.cfg.latent_size) != (decoder.cfg.latent_channels,
                                                                       decoder.cfg.latent_size):
            raise CmtoolError(f"--encoder {enc_path}: its latents do not fit the decoder {path}")
        scales = [float(ckpt.load_config(p).get("latent_scale", "nan")) for p in (enc_path, path)]
        if abs(scales[0] - scales[1]) > 1e-6:
            click.echo(f"warning: the decoder was trained on other latents (latent scale {scales[1]:.4f}, the "
                       f"encoder's {scales[0]:.4f}); the numbers measure this pair", err=True)
    elif decoder.trunk is None:
        raise CmtoolError(f"{path}: a decoder without its encoder (the shipped weights hold none); give --encoder "
                          "RUN, the RVAE run it was trained on")
    reconstruction_report(encoder, decoder, data_dir, dev, n, out, progress=not quiet, tol=tol,
                          splits=list(splits) or None)
    click.echo((out / "ablate_rvae.md").read_text().rstrip())
    click.echo(f"wrote {out / 'ablate_rvae.md'}, {out / 'ablate_rvae.json'}")


def _rvae(path: Path, option: str, device):
    from cmtool import checkpoint as ckpt

    path = ckpt.resolve(path)
    model, config = ckpt.load_model(path, device)
    if config["kind"] != "rvae":
        raise CmtoolError(f"{option} {path}: a {config['kind']} checkpoint, not an RVAE")
    return model, path


@cli.group()
def bench():
    """Speed measurements (timings are printed, never asserted by tests)."""


@bench.command("sample")
@click.option("--ckpt", type=click.Path(path_type=Path),
              help="ControlMap (or DiT) checkpoint or run folder [default: the weights shipped with cmtool].")
@click.option("--sd", "sd_path", type=click.Path(path_type=Path), help="SD input [default: a procedural crossing].")
@click.option("--steps", default=50, show_default=True, type=click.IntRange(min=1), help="Denoising steps.")
@click.option("--sampler", default=DEFAULT_SAMPLER, show_default=True, type=click.Choice(SAMPLERS))
@click.option("--cfg", default=1.0, show_default=True, help="Guidance weight.")
@click.option("--batch", default=64, show_default=True, type=click.IntRange(min=2), help="The large batch to compare.")
@click.option("--repeats", default=3, show_default=True, type=click.IntRange(min=1), help="Timed runs per setting.")
@click.option("--device", help="torch device [default: cuda when available, else cpu].")
def bench_sample_cmd(ckpt, sd_path, steps, sampler, cfg, batch, repeats, device):
    """Time sampling: per-step logging against --no-log at batch 1, and batch 1 against a large batch."""
    import torch

    from cmtool.sample.bench import LOG_LIMIT, bench_sample, default_sd
    from cmtool.sample.generator import Generator
    from cmtool.sample.inputs import image_inputs
    from cmtool.sample.run import SampleSettings

    settings = SampleSettings(steps=steps, cfg=cfg, sampler=sampler)
    settings.check()
    sd = image_inputs([sd_path])[0].sd if sd_path else default_sd()
    dev = _device(device)
    gen = Generator.load(_checkpoint(ckpt), dev)
    params = sum(p.numel() for p in gen.model.parameters())
    click.echo(f"{gen.path}: {gen.config['kind']}, {params / 1e6:.1f}M parameters; {dev} "
               f"({torch.get_num_threads()} threads); {steps} {settings.sampler} steps, cfg {cfg}")
    r = bench_sample(gen, sd, settings, batch=batch, repeats=repeats)
    verdict = "within" if r["log_ratio"] <= LOG_LIMIT else "OVER"
    click.echo(f"full logging / --no-log at batch 1: {r['log_ratio']:.3f} ({verdict} the {LOG_LIMIT:.2f} limit)")
    click.echo(f"batch {batch} / batch 1, time per map: {1 / r['batch_speedup']:.3f} "
               f"({r['batch_speedup']:.1f}x faster per map)")


@bench.command("metrics")
@click.option("--eval", "eval_dir", required=True, type=click.Path(file_okay=False, path_type=Path),
              help="A `cmtool eval --out` folder: its cached maps and the scenes they were made for.")
@click.option("--method", default="controlmap", show_default=True, type=click.Choice(["controlmap", "unguided"]))
@click.option("--tile", default=1, show_default=True, type=click.IntRange(min=1),
              help="Repeat the set this many times (512 x 8 = 4,096 is the paper's test-set size).")
@click.option("--repeats", default=3, show_default=True, type=click.IntRange(min=1), help="Timed runs.")
@click.option("--no-features", is_flag=True, help="Leave out the ResNet-50 metrics.")
@click.option("--device", help="torch device [default: cuda when available, else cpu].")
def bench_metrics_cmd(eval_dir, method, tile, repeats, no_features, device):
    """Time each family of metrics (topology, lane distances, validity, SD adherence, driving side, legal
    one-way, features, recall) on an evaluation's maps: minimum and median over the repeats."""
    from cmtool.eval.bench import bench_metrics, eval_set, report_table
    from cmtool.eval.features import FeatureExtractor

    generated, reference, controls = eval_set(eval_dir, method, tile)
    extractor = None if no_features else FeatureExtractor("resnet50-seeded", None, _device(device))
    click.echo(report_table(bench_metrics(generated, reference, controls, extractor, repeats)))


@cli.command()
@click.argument("path", required=False, type=click.Path(path_type=Path))
@click.option("--json", "as_json", is_flag=True, help="Print the checkpoint's full config as JSON.")
def info(path, as_json):
    """What a checkpoint (or run folder) holds, or the model sizes a recipe defines.

    Without PATH: the models shipped with cmtool.
    """
    from cmtool.info import describe
    from cmtool.release import BUNDLED, bundled_checkpoint

    if path is None:
        click.echo(describe(bundled_checkpoint(), as_json=as_json))
        click.echo("")
        click.echo(describe(BUNDLED / "rvae", as_json=as_json))
        return
    click.echo(describe(path, as_json=as_json))


@cli.command()
@click.option("--ckpt", required=True, type=click.Path(path_type=Path), help="ControlMap checkpoint or run folder.")
@click.option("--rvae", default=None, type=click.Path(path_type=Path),
              help="RVAE to ship instead of the one the ControlMap was trained on: a `cmtool train decoder` run "
                   "on that RVAE (same encoder, so the same latent space), or an already packed decoder "
                   "with the same latent scale (e.g. cmtool/weights/rvae).")
@click.option("--out", default=None, type=click.Path(file_okay=False, path_type=Path),
              help="Folder to write [default: the package's own cmtool/weights].")
def pack(ckpt, rvae, out):
    """Pack a trained ControlMap (and its RVAE's decoder) as float16 weights to ship with cmtool."""
    from cmtool.release import BUNDLED, MANIFEST, pack as pack_release

    out = out or BUNDLED
    manifest = pack_release(ckpt, out, rvae=rvae)
    for name, f in manifest["files"].items():
        click.echo(f"{out / name}  {f['bytes'] / 1e6:.2f} MB  sha256 {f['sha256'][:16]}...")
    click.echo(f"total {manifest['total_bytes'] / 1e6:.2f} MB; checksums in {out / MANIFEST}")


def main(argv=None) -> None:
    """Entry point: run the CLI, reducing user errors to one line and a non-zero exit."""
    try:
        cli.main(args=argv, prog_name="cmtool", standalone_mode=False)
    except CmtoolError as e:
        click.echo(f"Error: {e}", err=True)
        sys.exit(1)
    except click.exceptions.Abort:
        click.echo("Aborted.", err=True)
        sys.exit(130)
    except click.UsageError as e:
        hint = f" (see '{e.ctx.command_path} --help')" if e.ctx is not None else ""
        click.echo(f"Error: {e.format_message()}{hint}", err=True)
        sys.exit(2)
    except click.ClickException as e:
        click.echo(f"Error: {e.format_message()}", err=True)
        sys.exit(e.exit_code)
