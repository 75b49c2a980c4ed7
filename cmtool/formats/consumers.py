"""What independent readers make of cmtool's exports: the lanes and successor joins that CARLA's OpenDRIVE reader
(the ``carla`` wheel, offline: no server) and Lanelet2's routing graph (the ``lanelet2`` wheel) find, by lane graph
index (every exported lane carries it as ``cmtool:lane``), held against the lane graph's own successors."""

from __future__ import annotations

import importlib
import os
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

from cmtool.core.errors import CmtoolError
from cmtool.core.reach import Reach

READERS = {"opendrive": ("carla", "CARLA"), "lanelet2": ("lanelet2", "Lanelet2")}  # format -> (wheel, reader)


@dataclass
class Verdict:
    """Whether a reader routes as the lane graph does: each successor join of either leads (through a chain of
    joins) where the other's does, so both join the same ordered pairs of lanes (lane changes aside)."""

    reader: str  # e.g. "CARLA 0.9.16"
    joins: int  # the lane graph's successor joins
    unrouted: list  # its joins (i, j) along which the reader cannot drive from lane i to lane j
    unjoined: list  # the reader's joins that the lane graph cannot drive along
    dropped: list  # lanes the reader left out

    @property
    def ok(self) -> bool:
        return not (self.unrouted or self.unjoined or self.dropped)

    def line(self) -> str:
        if self.ok:
            return f"{self.reader} routes the lane graph's {self.joins:,} successor joins and nothing else"
        return (f"{self.reader} routes otherwise than the lane graph: {len(self.unrouted):,} of its {self.joins:,} "
                f"successor joins not routed {self.unrouted[:3]}, {len(self.unjoined):,} routed that it does not "
                f"join {self.unjoined[:3]}, {len(self.dropped):,} lanes left out {self.dropped[:3]}")


INSTALL = "pip install -e '.[verify]' in a source checkout"  # the readers of --verify (pyproject.toml's extra)


def reader(fmt: str):
    """The module that reads ``fmt`` exports (a CmtoolError naming what to install when it is missing)."""
    wheel = READERS[fmt][0]
    try:
        return importlib.import_module(wheel)
    except ImportError as e:
        raise CmtoolError(f"--verify for {fmt} needs the {wheel} wheel: {INSTALL} (carla exists for Linux x86_64, "
                          f"Python 3.10 to 3.12): {e}") from None


def verify(fmt: str, graph, path: str | os.PathLike, lat0: float, lon0: float) -> Verdict:
    """Load the ``fmt`` export of ``graph`` (written at ``(lat0, lon0)``) at ``path`` in its reader; compare."""
    wheel, name = READERS[fmt]
    module = reader(fmt)
    try:
        if fmt == "opendrive":
            edges, seen = _carla(module, Path(path).read_text(encoding="utf-8"))
        else:
            edges, seen = _lanelet2(module, path, lat0, lon0)
    except (RuntimeError, ValueError) as e:
        raise CmtoolError(f"{path}: {name} cannot read it: {e}") from None
    except (ImportError, AttributeError) as e:  # a package of that name without what its reader has
        raise CmtoolError(f"--verify for {fmt}: the installed {wheel} is not {name}'s reader as cmtool knows it "
                          f"({type(e).__name__}: {e}); reinstall it: {INSTALL}") from None
    n = len(graph.lanes)
    joins = sorted({(int(i), int(j)) for i, j in graph.successors})
    between = [(a, b) for a, b in edges if a != b]  # a reader's join of a lane's parts is no join of the lane graph's
    return Verdict(f"{name} {_version(wheel)}".strip(), len(joins), unreached(n, joins, edges),
                   unreached(n, between, joins), sorted(set(range(n)) - seen))


def unreached(n: int, edges, paths) -> list[tuple[int, int]]:
    """The ``edges`` (i, j) between ``n`` lanes where no chain of ``paths`` leads from i to j (for a self-loop (i, i):
    a chain of one path or more)."""
    reach = Reach(n, set(paths))
    after = {}
    for a, b in set(paths):
        after.setdefault(a, set()).add(b)
    return [(i, j) for i, j in sorted(set(edges))
            if not (any(i in reach(k) for k in after.get(i, ())) if i == j else j in reach(i))]


def _carla(carla, xodr: str) -> tuple[list, set]:
    """(the lane-to-lane joins of CARLA's topology, the lanes in it)."""
    lane_of = {(int(road.get("id")), int(lane.get("id"))): int(data.get("value"))
               for road in ET.fromstring(xodr.encode()).iter("road") for lane in road.iter("lane")
               for data in lane.iter("userData") if data.get("code") == "cmtool:lane"}
    topology = [(lane_of[(a.road_id, a.lane_id)], lane_of[(b.road_id, b.lane_id)])
                for a, b in carla.Map("cmtool", xodr).get_topology()]
    return topology, {k for edge in topology for k in edge}


def _lanelet2(lanelet2, path, lat0: float, lon0: float) -> tuple[list, set]:
    """(the lane-to-lane joins of Lanelet2's routing graph for a car, lane changes aside; the lanes loaded)."""
    from lanelet2.io import Origin
    from lanelet2.projection import UtmProjector

    lanelet_map, errors = lanelet2.io.loadRobust(str(path), UtmProjector(Origin(lat0, lon0)))
    if errors:
        raise CmtoolError(f"{path}: Lanelet2 reports {len(errors)} load errors, the first: {errors[0]}")
    rules = lanelet2.traffic_rules.create(lanelet2.traffic_rules.Locations.Germany,
                                          lanelet2.traffic_rules.Participants.Vehicle)
    routing = lanelet2.routing.RoutingGraph(lanelet_map, rules)
    lane = {ll.id: int(ll.attributes["cmtool:lane"]) for ll in lanelet_map.laneletLayer}
    edges = [(lane[ll.id], lane[f.id]) for ll in lanelet_map.laneletLayer for f in routing.following(ll)]
    return edges, set(lane.values())


def _version(wheel: str) -> str:
    try:
        return version(wheel)
    except PackageNotFoundError:
        return ""
