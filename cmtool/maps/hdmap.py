"""The HD map type: a city-scale lane graph in metres, with traffic-light stop lines and crosswalks.

Every HD source (procedural cities, Argoverse 2, Lanelet2, nuPlan) produces an :class:`HDMap`;
everything downstream (SD derivation, scenes, rasters, statistics) reads one.

JSON schema (``*.json``, one map per file)::

    {"format": "cmtool.hdmap", "version": 1,
     "city": "PIT", "drives_on": "right", "source": "procedural:PIT:seed=0",
     "lanes": [{"id": "l12", "centerline": [[x, y], ...], "width": 3.5,
                "successors": ["l13"], "predecessors": ["l11"],
                "left_neighbor": null, "right_neighbor": "l14",
                "is_intersection": false, "lane_type": "vehicle",
                "road_id": "r3", "intersection_id": null}, ...],
     "stop_lines": [{"id": "s1", "line": [[x, y], [x, y]], "state": "green", "lane_ids": ["l12"]}],
     "crosswalks": [{"id": "c1", "polygon": [[x, y], ...]}],
     "meta": {}}

Centerlines run in the driving direction. ``left_neighbor``/``right_neighbor`` name adjacent lanes
of the same direction. ``road_id`` groups the lanes of one road (both directions) where the source
knows it; ``intersection_id`` groups the connector lanes of one intersection. Ids are strings.
Loading validates every field and every reference and names the offending one in the error.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from cmtool.core.errors import CmtoolError
from cmtool.core.jsonio import Fields, JsonFile

LANE_TYPES = ("vehicle", "bus", "bike")
LIGHT_STATES = ("green", "red", "unknown")
FORMAT = "cmtool.hdmap"
LEFT_HAND = frozenset({"SGP"})  # city labels that drive on the left (Singapore); all others drive on the right


def drives_on(city: str | None) -> str:
    """The side a city label drives on, "left" or "right" (unknown and no label: right)."""
    return "left" if city and city.upper() in LEFT_HAND else "right"


@dataclass
class Lane:
    id: str
    centerline: np.ndarray  # (N, 2) float64, driving direction
    width: float = 3.5
    successors: list[str] = field(default_factory=list)
    predecessors: list[str] = field(default_factory=list)
    left_neighbor: str | None = None
    right_neighbor: str | None = None
    is_intersection: bool = False
    lane_type: str = "vehicle"
    road_id: str | None = None
    intersection_id: str | None = None

    @property
    def in_intersection(self) -> bool:
        """A connector through an intersection (flagged, or belonging to one)."""
        return self.is_intersection or self.intersection_id is not None


@dataclass
class StopLine:
    id: str
    line: np.ndarray  # (N, 2)
    state: str = "unknown"  # one of LIGHT_STATES
    lane_ids: list[str] = field(default_factory=list)  # lanes this light controls


@dataclass
class Crosswalk:
    id: str
    polygon: np.ndarray  # (N, 2), N >= 3, not closed (first point not repeated)


@dataclass
class HDMap(JsonFile):
    city: str
    lanes: dict[str, Lane] = field(default_factory=dict)
    stop_lines: list[StopLine] = field(default_factory=list)
    crosswalks: list[Crosswalk] = field(default_factory=list)
    drives_on: str = "right"  # "right" or "left"
    source: str = ""
    meta: dict = field(default_factory=dict)

    def add_lane(self, lane: Lane) -> Lane:
        if lane.id in self.lanes:
            raise ValueError(f"duplicate lane id {lane.id!r}")
        self.lanes[lane.id] = lane
        return lane

    def link(self, a: str, b: str) -> None:
        """Record that lane ``a`` flows into lane ``b`` (both directions of the relation)."""
        if b not in self.lanes[a].successors:
            self.lanes[a].successors.append(b)
        if a not in self.lanes[b].predecessors:
            self.lanes[b].predecessors.append(a)

    def bounds(self) -> tuple[float, float, float, float]:
        """(xmin, ymin, xmax, ymax) over all lane centerlines."""
        pts = np.concatenate([lane.centerline for lane in self.lanes.values()])
        return (*pts.min(axis=0), *pts.max(axis=0))

    def reference_errors(self) -> list[str]:
        """Dangling or one-sided references, as readable messages (empty when consistent)."""
        errors = []
        for lane in self.lanes.values():
            for s in lane.successors:
                if s not in self.lanes:
                    errors.append(f"lane {lane.id}: successor {s!r} does not exist")
                elif lane.id not in self.lanes[s].predecessors:
                    errors.append(f"lane {lane.id}: successor {s} does not list it as predecessor")
            for p in lane.predecessors:
                if p not in self.lanes:
                    errors.append(f"lane {lane.id}: predecessor {p!r} does not exist")
                elif lane.id not in self.lanes[p].successors:
                    errors.append(f"lane {lane.id}: predecessor {p} does not list it as successor")
            for side in ("left_neighbor", "right_neighbor"):
                n = getattr(lane, side)
                if n is not None and n not in self.lanes:
                    errors.append(f"lane {lane.id}: {side} {n!r} does not exist")
        for sl in self.stop_lines:
            errors += [f"stop line {sl.id}: lane {i!r} does not exist" for i in sl.lane_ids if i not in self.lanes]
        return errors

    # ------------------------------------------------------------------ JSON
    def to_json(self) -> dict:
        return {
            "format": FORMAT,
            "version": 1,
            "city": self.city,
            "drives_on": self.drives_on,
            "source": self.source,
            "lanes": [
                {
                    "id": l.id,
                    "centerline": _round(l.centerline),
                    "width": round(float(l.width), 3),
                    "successors": list(l.successors),
                    "predecessors": list(l.predecessors),
                    "left_neighbor": l.left_neighbor,
                    "right_neighbor": l.right_neighbor,
                    "is_intersection": bool(l.is_intersection),
                    "lane_type": l.lane_type,
                    "road_id": l.road_id,
                    "intersection_id": l.intersection_id,
                }
                for l in self.lanes.values()
            ],
            "stop_lines": [
                {"id": s.id, "line": _round(s.line), "state": s.state, "lane_ids": list(s.lane_ids)}
                for s in self.stop_lines
            ],
            "crosswalks": [{"id": c.id, "polygon": _round(c.polygon)} for c in self.crosswalks],
            "meta": self.meta,
        }

    @classmethod
    def from_json(cls, obj, where: str = "map") -> "HDMap":
        top = Fields(obj, where)
        top.header(FORMAT, "an HD map file")
        drives_on = top.get("drives_on", str, "right")
        if drives_on not in ("right", "left"):
            top.fail("drives_on", f"expected 'right' or 'left', got {drives_on!r}")
        hd = cls(
            city=top.get("city", str),
            drives_on=drives_on,
            source=top.get("source", str, ""),
            meta=top.get("meta", dict, {}),
        )
        for i, item in enumerate(top.get("lanes", list)):
            f = Fields(item, where, f"lanes[{i}]")
            lane_type = f.get("lane_type", str, "vehicle")
            if lane_type not in LANE_TYPES:
                f.fail("lane_type", f"expected one of {LANE_TYPES}, got {lane_type!r}")
            width = f.number("width", 3.5)
            if not 0.5 <= width <= 20.0:
                f.fail("width", f"implausible lane width {width} m")
            lane = Lane(
                id=f.get("id", str),
                centerline=f.points("centerline"),
                width=width,
                successors=_ids(f, "successors"),
                predecessors=_ids(f, "predecessors"),
                left_neighbor=f.get("left_neighbor", str, None, allow_none=True),
                right_neighbor=f.get("right_neighbor", str, None, allow_none=True),
                is_intersection=f.get("is_intersection", bool, False),
                lane_type=lane_type,
                road_id=f.get("road_id", str, None, allow_none=True),
                intersection_id=f.get("intersection_id", str, None, allow_none=True),
            )
            if lane.id in hd.lanes:
                f.fail("id", f"duplicate lane id {lane.id!r}")
            hd.lanes[lane.id] = lane
        for i, item in enumerate(top.get("stop_lines", list, [])):
            f = Fields(item, where, f"stop_lines[{i}]")
            state = f.get("state", str, "unknown")
            if state not in LIGHT_STATES:
                f.fail("state", f"expected one of {LIGHT_STATES}, got {state!r}")
            hd.stop_lines.append(StopLine(f.get("id", str), f.points("line"), state, _ids(f, "lane_ids")))
        for i, item in enumerate(top.get("crosswalks", list, [])):
            f = Fields(item, where, f"crosswalks[{i}]")
            hd.crosswalks.append(Crosswalk(f.get("id", str), f.points("polygon", min_points=3)))
        errors = hd.reference_errors()
        if errors:
            more = f" (and {len(errors) - 1} more)" if len(errors) > 1 else ""
            raise CmtoolError(f"{where}: {errors[0]}{more}")
        return hd


def _ids(f: Fields, key: str) -> list[str]:
    ids = f.get(key, list, [])
    if not all(isinstance(i, str) for i in ids):
        f.fail(key, "expected a list of id strings")
    return list(ids)


def _round(points: np.ndarray, decimals: int = 3) -> list:
    return np.round(np.asarray(points, dtype=np.float64), decimals).tolist()
