"""SUMO networks: an SD map laid out by SUMO's ``netconvert`` (the rule-based converter CARLA's ``Osm2Odr`` also
runs), read back as an HD map, the second baseline of ``cmtool eval`` and ``cmtool baseline``; and a lane graph as
a SUMO network for traffic (:func:`write_sumo_net`, ``cmtool export --format sumo``), when SUMO is installed
(``pip install eclipse-sumo``).

The SD map goes to ``netconvert`` as an OpenStreetMap file (:func:`cmtool.formats.osm.write_osm`) with SUMO's
recommended options for OpenStreetMap input (``OSM_OPTIONS``), and a transverse Mercator projection centred on
the same origin as ours, so the network's coordinates are the SD map's metres. Every lane that passenger cars
may use becomes a lane of the HD map, the junctions' internal lanes as connector lanes; successors follow the
network's connections (through their internal lanes).
"""

from __future__ import annotations

import shutil
import subprocess
import tempfile
from pathlib import Path

import defusedxml.ElementTree as ET
import numpy as np

from cmtool.core.errors import CmtoolError
from cmtool.core.jsonio import write_text_atomic
from cmtool.formats.osm import write_osm
from cmtool.maps.hdmap import HDMap, Lane, drives_on
from cmtool.maps.sdmap import SDMap

# SUMO's recommended options for OpenStreetMap networks (SUMO documentation, "Importing OpenStreetMap"), and no
# turnaround connections (HD maps draw no U-turn lanes)
OSM_OPTIONS = ("--geometry.remove", "--ramps.guess", "--junctions.join", "--tls.guess-signals", "--tls.discard-simple",
               "--tls.join", "--tls.default-type", "actuated", "--no-turnarounds")
TIMEOUT_S = 300


def netconvert_path() -> str | None:
    """The ``netconvert`` executable, or None when SUMO is not installed."""
    return shutil.which("netconvert")


def netconvert_layout(sd: SDMap, side: str | None = None) -> HDMap:
    """``netconvert``'s lane layout of ``sd`` (module doc); ``side``: "right" or "left" [default: the city's]."""
    exe = netconvert_path()
    if exe is None:
        raise CmtoolError("netconvert is not installed (pip install eclipse-sumo)")
    side = side or drives_on(sd.city)
    lat0, lon0 = 0.0, 0.0  # any origin: the projection below undoes it exactly
    with tempfile.TemporaryDirectory(prefix="cmtool-netconvert-") as tmp:
        osm, net = Path(tmp) / "sd.osm", Path(tmp) / "net.net.xml"
        write_osm(sd, osm, lat0, lon0)
        proj = f"+proj=tmerc +lat_0={lat0} +lon_0={lon0} +k=1 +x_0=0 +y_0=0 +ellps=WGS84 +units=m +no_defs"
        args = [exe, "--osm-files", str(osm), "-o", str(net), "--proj", proj, "--offset.disable-normalization",
                "true", *OSM_OPTIONS, "--no-warnings", "true"]
        if side == "left":
            args.append("--lefthand")
        _netconvert(args, net, f"{len(sd.roads)} roads")
        hd = read_sumo_net(net)
    hd.city, hd.drives_on = sd.city or "", side
    hd.source = f"netconvert:{sd.source}" if sd.source else "netconvert"
    return hd


def write_sumo_net(graph, path, lat0: float, lon0: float, heading: float = 0.0, lane_width: float = 3.5) -> str:
    """Write ``graph`` (a LaneGraph) as a SUMO network (``.net.xml``): its OpenDRIVE export
    (:mod:`cmtool.formats.opendrive_export`) read by ``netconvert``; returns netconvert's last warning line, if any."""
    from cmtool.formats.opendrive_export import write_opendrive

    exe = netconvert_path()
    if exe is None:
        raise CmtoolError("--format sumo needs SUMO's netconvert (pip install eclipse-sumo)")
    with tempfile.TemporaryDirectory(prefix="cmtool-sumo-") as tmp:
        xodr, net = Path(tmp) / "map.xodr", Path(tmp) / "map.net.xml"
        write_opendrive(graph, xodr, lat0, lon0, heading, lane_width)
        done = _netconvert([exe, "--opendrive-files", str(xodr), "-o", str(net), "--no-turnarounds"], net,
                           f"{len(graph.lanes)} lanes")
        write_text_atomic(path, net.read_text("utf-8"))
    warnings = [line for line in done.stderr.splitlines() if line.startswith("Warning")]
    return warnings[-1] if warnings else ""


def _netconvert(args: list[str], net: Path, what: str) -> subprocess.CompletedProcess:
    """Run netconvert (``args``) that should write ``net``; its failures and time-outs as one-line errors."""
    try:
        done = subprocess.run(args, capture_output=True, text=True, timeout=TIMEOUT_S)
    except subprocess.TimeoutExpired:
        raise CmtoolError(f"netconvert took over {TIMEOUT_S} s on {what}") from None
    if done.returncode != 0 or not net.is_file():
        raise CmtoolError(f"netconvert failed: {(done.stderr or done.stdout).strip().splitlines()[-1:]}")
    return done


def read_sumo_net(path) -> HDMap:
    """The lanes of a SUMO ``.net.xml`` that passenger cars may use, as an HD map in the network's coordinates."""
    try:
        root = ET.parse(str(path)).getroot()
    except ET.ParseError as e:
        raise CmtoolError(f"{path}: not a SUMO network ({e})") from None
    hd = HDMap(city="", source=f"sumo:{Path(path).name}")
    for edge in root.iter("edge"):
        internal = edge.get("function") == "internal"
        if edge.get("function") not in (None, "", "normal", "internal"):
            continue
        for lane in edge.iter("lane"):
            if not _passenger(lane) or not lane.get("shape"):
                continue
            line = np.array([[float(v) for v in p.split(",")[:2]] for p in lane.get("shape").split()])
            if len(line) < 2 or np.linalg.norm(line[-1] - line[0]) + np.abs(np.diff(line, axis=0)).sum() < 1e-6:
                continue
            hd.add_lane(Lane(lane.get("id"), line, float(lane.get("width", 3.2)), is_intersection=internal,
                             road_id=None if internal else edge.get("id"),
                             intersection_id=edge.get("id").lstrip(":").rsplit("_", 1)[0] if internal else None))
    for c in root.iter("connection"):
        a, b = f"{c.get('from')}_{c.get('fromLane')}", f"{c.get('to')}_{c.get('toLane')}"
        via = c.get("via")
        for x, y in ((a, via), (via, b)) if via else ((a, b),):
            if x in hd.lanes and y in hd.lanes and y not in hd.lanes[x].successors:
                hd.lanes[x].successors.append(y)
                hd.lanes[y].predecessors.append(x)
    return hd


def _passenger(lane) -> bool:
    allow, disallow = lane.get("allow"), lane.get("disallow")
    if allow is not None:
        return "passenger" in allow.split() or allow == "all"
    return disallow is None or "passenger" not in disallow.split()
