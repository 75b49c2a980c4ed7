"""``cmtool baseline``: rule-based maps of the same SD inputs, to hold the learned maps against."""

from __future__ import annotations

from pathlib import Path

import click

from cmtool.cli.common import SEED, OutPath, map_input_options, map_inputs
from cmtool.core.errors import CmtoolError

INPUTS_HELP = """
\b
SD input (one kind):
  --osm FILE --center LAT,LON [--heading DEG]
  --from-hd MAP.json [--pose X,Y,YAW]   (the SD map derived from it; the ground truth is written beside)
--center and --pose also take a .jsonl file of points. Frames are written as `cmtool sample` writes its maps
(lane graph JSON, ground truth, picture), and all of them in OUT/METHOD.jsonl (and OUT/truth.jsonl) for
`cmtool metrics`. --whole writes the layout of the whole SD map as one HD map JSON, with or without frames.
"""
RULES_HELP = """The rule-based lane layout of an SD map, written here: lanes from the lane-count tags or the road class,
one-way roads one way, divided roads as their two carriageways, connectors through junctions.
""" + INPUTS_HELP
NETCONVERT_HELP = """SUMO's netconvert (the converter CARLA's Osm2Odr runs) on the same SD map, with SUMO's recommended
OpenStreetMap options and no U-turns; needs SUMO (pip install eclipse-sumo).
""" + INPUTS_HELP


@click.group()
def baseline():
    """Rule-based maps of the same SD inputs, to hold the learned maps against."""


def _inputs(command):
    for option in reversed([
        map_input_options,
        click.option("--seed", default=0, show_default=True, type=SEED, help="Seed of the random pose."),
        click.option("--side", default="auto", show_default=True, type=click.Choice(["auto", "right", "left"]),
                     help="Driving side; auto: the HD map's city's, else right."),
        click.option("--out", default=Path("baseline"), show_default=True,
                     type=OutPath(file_okay=False), help="Folder for the lane graphs and pictures."),
        click.option("--grid", type=OutPath(dir_okay=False),
                     help="Also write all maps' pictures stacked into this PNG."),
        click.option("--whole", type=OutPath(dir_okay=False),
                     help="Write the layout of the whole SD map as an HD map JSON here."),
    ]):
        command = option(command)
    return command


@baseline.command(help=RULES_HELP)
@_inputs
def rules(**options):
    _run("rules", **options)


@baseline.command(help=NETCONVERT_HELP)
@_inputs
def netconvert(**options):
    _run("netconvert", **options)


def _run(method, osm, center, heading, from_hd, pose, seed, side, out, grid, whole):
    from cmtool.data.layouts import LAYOUTS
    from cmtool.maps.hdmap import drives_on
    from cmtool.sample import inputs as src
    from cmtool.sample.baseline import baseline_maps, write_baseline_maps
    from cmtool.sample.summary import summary_table

    if (osm is None) == (from_hd is None):
        raise CmtoolError("give one SD input: --osm or --from-hd")
    if osm is not None and center is None and whole is None:
        raise CmtoolError("--osm needs --center LAT,LON (or a .jsonl of centres), or --whole")
    side = None if side == "auto" else side
    inputs = map_inputs(osm, center, heading, from_hd, pose, seed, whole=whole is not None)
    if whole is not None:
        if inputs:
            sd_map, city = inputs[0].sd_map, inputs[0].city
        elif osm is not None:
            sd_map, city = src.osm_sd_map(osm), None
        else:
            source, sd_map = src.hd_sd_map(from_hd)
            city = source.city
        hd = LAYOUTS[method](sd_map, side or drives_on(city))
        hd.save(whole)
        click.echo(f"wrote the {method} layout of {len(sd_map.roads)} SD roads: {len(hd.lanes)} lanes -> {whole}")
    if inputs:
        maps = baseline_maps(inputs, method, side)
        write_baseline_maps(maps, method, out, grid)
        click.echo(summary_table(maps))
        click.echo(f"wrote {len(maps)} {method} lane graph{'s' if len(maps) > 1 else ''} and pictures to {out}")
