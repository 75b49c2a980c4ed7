"""``cmtool sample``: lane-level HD maps from SD maps, every denoising step recorded."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import click

from cmtool.cli.common import (CITY_CFG_HELP, LANE_COUNTS_OPTION, PRECISION_OPTION, SEED, SMOOTH_OPTION, Finite, InPath,
                               OutPath, _device, _generator, attach_init, check_map_inputs, init_options,
                               map_input_options, map_inputs, sampler_options)
from cmtool.core.errors import CmtoolError

SAMPLE_HELP = """Generate lane-level HD maps from SD maps with ControlMap, recording every denoising step.

\b
SD input (at most one kind; none: maps from the city label alone):
  --sd PNG|DIR              control rasters, or plain road drawings (converted)
  --osm FILE --center LAT,LON [--heading DEG]
  --from-hd MAP.json [--pose X,Y,YAW]   (the ground truth is shown beside the map)
--center and --pose also take a .jsonl file of points for many inputs at once.

One map of a whole area, tiled, generated and stitched (docs/area.md):
  --osm FILE --area all|LAT0,LON0,LAT1,LON1
  --from-hd MAP.json --area all|X0,Y0,X1,Y1
  --sd PICTURE --area all|X0,Y0,X1,Y1 [--px-m 0.5]   (a road drawing or SD raster, north up)

Large sets in several processes (CPU or GPUs), the same maps as one process:
  torchrun --nproc_per_node 2 -m cmtool -- sample ... --no-log
"""


@click.command(help=SAMPLE_HELP)
@click.option("--ckpt", type=InPath(),
              help="ControlMap (or DiT) checkpoint or run folder [default: the weights shipped with cmtool].")
@click.option("--sd", "sd_paths", multiple=True, type=InPath(),
              help="SD raster / road drawing picture, or a folder of them (repeatable).")
@map_input_options
@click.option("--area", help="With --osm, --from-hd or one --sd picture: one map of a whole area instead of frames: "
                             "all (the map's extent) or two opposite corners, LAT0,LON0,LAT1,LON1 (--osm) or "
                             "X0,Y0,X1,Y1 metres (--from-hd, --sd). Written as OUT/NAME_area.json and .png; its "
                             "tiles start from the area's rule layout (--init rules --strength 0.3) unless --init is "
                             "given (docs/area.md).")
@click.option("--px-m", default=0.5, show_default=True, type=Finite(min=0, min_open=True),
              help="With --sd PICTURE --area: metres per pixel of the picture (north up).")
@click.option("--num", default=1, show_default=True, type=click.IntRange(1, 100_000), help="Maps per SD input.")
@click.option("--candidates", default=1, show_default=True, type=click.IntRange(1, 100),
              help="Draw this many maps for each one and keep the best: the highest mean of its validity score, "
                   "SD road covered and legal one-way share (every candidate is in the recording).")
@click.option("--seed", default=0, show_default=True, type=SEED, help="Random seed.")
@sampler_options
@click.option("--eta", default=0.0, show_default=True, type=Finite(min=0),
              help="DDIM noise (0 deterministic, 1 like DDPM).")
@click.option("--city", default="auto", show_default=True,
              help="City label of the checkpoint, or none; auto: the HD map's city, else none.")
@click.option("--cfg", default=1.0, show_default=True, type=Finite(min=0),
              help="Guidance weight w >= 0 on the SD control (0: ignore it).")
@click.option("--city-cfg", default=1.0, show_default=True, type=Finite(min=0), help=CITY_CFG_HELP)
@init_options
@SMOOTH_OPTION
@click.option("--batch", default=16, show_default=True, type=click.IntRange(min=1), help="Maps per forward pass.")
@click.option("--out", default=Path("samples"), show_default=True, type=OutPath(file_okay=False),
              help="Folder for the lane graphs and pictures.")
@click.option("--rrd", type=OutPath(dir_okay=False),
              help="Recording to write [default: OUT/sample.rrd].")
@click.option("--grid", type=OutPath(dir_okay=False),
              help="Also write all maps' pictures stacked into this PNG (a gallery).")
@click.option("--spawn", is_flag=True, help="Also stream live to a newly started Rerun viewer.")
@click.option("--connect", "connect_url", help="Also stream live to a running viewer at this gRPC URL.")
@click.option("--serve", is_flag=True, help="Also serve the recording and Rerun's web viewer from this machine "
                                            "(ports 9876 and 9090), until Ctrl-C: for a browser elsewhere.")
@click.option("--raw", is_flag=True, help="Keep the model's maps as it drew them (by default each map is composed "
                                          "from its SD map: every SD road carries its lanes and nothing else does, "
                                          "the model deciding the junctions' movements; docs/sampling.md).")
@LANE_COUNTS_OPTION
@click.option("--no-log", is_flag=True, help="No recording (fastest).")
@click.option("--no-pictures", is_flag=True, help="No picture per map (the lane graphs only; faster).")
@click.option("--workers", type=click.IntRange(min=1),
              help="Processes that check the maps (--area: the tiles' maps) and make their files while the model "
                   "denoises the next batches (1: a thread beside it; the files are the same) [default: one per CPU "
                   "core with more than two, else 1].")
@click.option("--device", help="torch device [default: cuda when available, else cpu].")
@PRECISION_OPTION
@click.option("--quiet", is_flag=True, help="No progress line.")
def sample(ckpt, sd_paths, osm, center, heading, from_hd, pose, area, px_m, num, candidates, seed, steps, sampler, eta,
           city, cfg, city_cfg, init, strength, encoder_path, smooth, batch, out, rrd, grid, spawn, connect_url, serve,
           raw, lane_counts, no_log, no_pictures, workers, device, precision, quiet):
    kinds = [name for name, given in (("--sd", sd_paths), ("--osm", osm), ("--from-hd", from_hd)) if given]
    if len(kinds) > 1:
        raise CmtoolError(f"give one kind of SD input, not {' and '.join(kinds)}")
    if no_log and (rrd or spawn or connect_url or serve):
        raise CmtoolError("--no-log cannot be combined with --rrd, --spawn, --connect or --serve")
    if no_pictures and grid:
        raise CmtoolError("--grid stacks the maps' pictures: leave out --no-pictures")
    if spawn + bool(connect_url) + serve > 1:
        raise CmtoolError("give one of --spawn, --connect and --serve")
    if area is None:
        check_map_inputs(osm, center, from_hd, pose)
    elif no_pictures:
        raise CmtoolError("--area writes one picture of the area: leave out --no-pictures")
    _check_paths(sd_paths, osm, from_hd, pose, center, ckpt, encoder_path, out, rrd, grid)
    if connect_url:
        from cmtool.viz.viewer import check_viewer

        check_viewer(connect_url, f"--connect {connect_url}")
    if area is not None:
        return _area(ckpt, sd_paths, px_m, osm, center, from_hd, pose, area, num, candidates, seed, steps, sampler,
                     eta, city, cfg, city_cfg, init, strength, encoder_path, smooth, batch, out, rrd, grid, spawn,
                     connect_url, serve, raw, lane_counts, no_log, workers, device, precision, quiet)
    import shlex

    from cmtool.core import dist as D
    from cmtool.sample import inputs as src
    from cmtool.sample.job import SampleSettings
    from cmtool.sample.pool import default_workers
    from cmtool.sample.run import plan, run_sample
    from cmtool.sample.summary import summary_table

    settings = SampleSettings(num=num, seed=seed, steps=steps, sampler=sampler, eta=eta, cfg=cfg, city=city,
                              city_cfg=city_cfg, batch=batch, init=init, strength=strength if init != "none" else 1.0,
                              guarantee=not raw, lane_counts=lane_counts, candidates=candidates)
    settings.check()
    inputs = src.image_inputs(sd_paths) if sd_paths else map_inputs(osm, center, heading, from_hd, pose, seed)
    if not inputs:
        inputs = [src.ControlInput("uncond", None, "no SD input")]
    info = D.setup(str(_device(device)))
    gen = _generator(ckpt, str(info.device), smooth, precision)
    attach_init(gen, init, encoder_path)
    jobs = plan(gen, inputs, settings)
    for item in inputs:
        if item.note and info.main:
            click.echo(f"note: {item.note}", err=True)
    if not no_log and rrd is None:
        rrd = out / "sample.rrd"
    viewer = "spawn" if spawn else "serve" if serve else connect_url
    if serve:
        from cmtool.viz.recording import serve_web_viewer

        click.echo(serve_web_viewer(), err=True)
    command = shlex.join(["cmtool", *sys.argv[1:]])
    try:
        maps = run_sample(gen, jobs, settings, out, None if no_log else rrd, viewer, command, progress=not quiet,
                          grid=grid, info=info, pictures=not no_pictures, workers=workers or default_workers())
    finally:
        D.cleanup()
    if not info.main:
        return
    click.echo(summary_table(maps))
    plural = "s" if len(maps) > 1 else ""
    click.echo(f"wrote {len(maps)} lane graph{plural}{'' if no_pictures else f' and picture{plural}'} to {out}"
               + ("" if no_log or rrd is None else f"; recording {rrd}"))
    if serve:
        import time

        click.echo("serving until Ctrl-C", err=True)
        while True:
            time.sleep(3600)


AREA_INIT, AREA_STRENGTH = "rules", 0.3  # where --area's tiles start unless --init is given


def _area(ckpt, sd_paths, px_m, osm, center, from_hd, pose, area, num, candidates, seed, steps, sampler, eta, city,
          cfg, city_cfg, init, strength, encoder_path, smooth, batch, out, rrd, grid, spawn, connect_url, serve, raw,
          lane_counts, no_log, workers, device, precision, quiet):
    """``sample --area``: one map of a whole area (:mod:`cmtool.sample.area`)."""
    if osm is None and from_hd is None and not sd_paths:
        raise CmtoolError("--area needs --osm FILE, --from-hd MAP or --sd PICTURE (the SD map of the area)")
    if len(sd_paths) > 1 or (sd_paths and sd_paths[0].is_dir()):
        raise CmtoolError("--area makes one map of one SD picture: give one --sd file, not several or a folder")
    ctx = click.get_current_context()
    given = [name for name, v in (("--center", center), ("--pose", pose), ("--grid", grid), ("--spawn", spawn),
                                  ("--connect", connect_url), ("--serve", serve)) if v]
    given += ["--heading"] * (ctx.get_parameter_source("heading").name != "DEFAULT")
    given += ["--num"] * (num > 1) + ["--candidates"] * (candidates > 1)
    if given:
        raise CmtoolError(f"--area makes one map of the whole area, recorded to a file: leave out {', '.join(given)}")
    if no_log and rrd:
        raise CmtoolError("--no-log cannot be combined with --rrd")
    if ctx.get_parameter_source("init").name == "DEFAULT":
        init, strength = AREA_INIT, AREA_STRENGTH
    import shlex

    from cmtool.core import dist as D
    from cmtool.data.tiles import check_extent
    from cmtool.sample import inputs as src
    from cmtool.sample.area import area_box, run_area
    from cmtool.sample.job import SampleSettings
    from cmtool.sample.pool import default_workers

    settings = SampleSettings(seed=seed, steps=steps, sampler=sampler, eta=eta, cfg=cfg, city=city, city_cfg=city_cfg,
                              batch=batch, init=init, strength=strength if init != "none" else 1.0, guarantee=not raw,
                              lane_counts=lane_counts)
    settings.check()
    if osm is not None:
        sd_map, name = src.osm_sd_map(osm), Path(osm).name.split(".")[0]
    elif sd_paths:
        from cmtool.data.sd_trace import trace_sd

        sd_map, name = trace_sd(sd_paths[0], px_m, None if city in ("auto", "none") else city), sd_paths[0].stem
    else:
        hd, sd_map = src.hd_sd_map(from_hd)
        sd_map.meta |= {k: hd.meta[k] for k in ("lat0", "lon0") if k in hd.meta}
        name = Path(from_hd).name.split(".")[0]
    box = area_box(sd_map, area, latlon=osm is not None)
    check_extent(sd_map, box, f"--area {area}" + (f" at --px-m {px_m:g}" if sd_paths else ""))
    info = D.setup(str(_device(device)))
    gen = _generator(ckpt, str(info.device), smooth, precision)
    attach_init(gen, init, encoder_path)
    try:
        done = run_area(gen, sd_map, box, settings, out, name, progress=not quiet, info=info,
                        rrd=None if no_log else rrd or out / "area.rrd", command=shlex.join(["cmtool", *sys.argv[1:]]),
                        workers=workers or default_workers())
    finally:
        D.cleanup()
    if done is None:
        return
    scores = done[1]
    click.echo(f"{name}: {scores['lanes']} lanes, {scores['successors']} successor joins from {scores['tiles']} tiles "
               f"in {scores['seconds']:.0f} s ({(box[2] - box[0]) * (box[3] - box[1]) / 1e6:.2f} km2 box); seams where "
               f"tiles disagreed {scores['seams_disagreed']}, left open {scores['open_seams']} "
               f"({scores['open_seams_on_roads']} where an SD road goes on); SD road-end pairs "
               f"routed {_share(scores['sd_end_pairs_routed'])} of {scores['sd_end_pairs']}; over "
               f"{scores['windows']} 64 m windows: validity {scores['validity']:.3f}, legal one-way "
               f"{_share(scores['legal_oneway'])}, SD covered {_share(scores['sd_coverage'])}")
    recorded = "" if no_log else f"; recording {rrd or out / 'area.rrd'}"
    click.echo(f"wrote {out / (name + '_area.json')} and {out / (name + '_area.png')}{recorded}")


def _check_paths(sd_paths, osm, from_hd, pose, center, ckpt, encoder_path, out, rrd, grid) -> None:
    """Refuse a missing or unreadable input and an output that cannot be written, before the seconds that the
    imports and the model take."""
    for path in sd_paths:
        _readable(path, str(path), folder=True)
    for path in (osm, from_hd):
        if path is not None:
            _readable(path, str(path))
    for option, value in (("--pose", pose), ("--center", center)):  # a .jsonl file of points (see parse_points)
        if value is not None and (Path(value).suffix == ".jsonl" or Path(value).is_file()):
            _readable(Path(value), f"{option} {value}")
    for path in (ckpt, encoder_path):
        if path is not None and not path.exists():
            raise CmtoolError(f"{path}: no such checkpoint")
    for path in (out, rrd, grid):
        if path is not None:
            _writable(path)


def _readable(path: Path, name: str, folder: bool = False) -> None:
    """Refuse (naming it ``name``) a path that is not a file that can be opened, or with ``folder`` a folder that
    can be listed."""
    try:
        if path.is_dir() and folder:
            os.scandir(path).close()
        elif path.is_file():
            open(path, "rb").close()
        else:
            raise CmtoolError(f"{name}: {'a folder, not a file' if path.is_dir() else 'no such file'}")
    except OSError as e:
        raise CmtoolError(f"{name}: cannot read it: {(e.strerror or str(e)).lower()}") from None


def _writable(path: Path) -> None:
    """Refuse an output file or folder whose nearest existing folder (itself, for a folder) cannot be written."""
    where = path if path.is_dir() else path.parent
    while not where.exists():
        where = where.parent
    if not where.is_dir():
        raise CmtoolError(f"cannot write {path}: {where} is a file, not a folder")
    if not os.access(where, os.W_OK | os.X_OK):
        raise CmtoolError(f"cannot write {path}: permission denied")


def _share(value) -> str:
    return "-" if value is None else f"{value:.3f}"
