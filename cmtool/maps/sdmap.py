"""The SD map type: an OpenStreetMap-like road skeleton, one polyline per road.

SD maps come from OpenStreetMap files, from an HD map (as OSM would show it), or from a user's
picture. They carry no lane geometry, only what OSM ways carry: the road's course, its class, its
lane count when known and whether it is one-way.

JSON schema (``*.json``)::

    {"format": "cmtool.sdmap", "version": 1, "city": "PIT", "source": "...",
     "roads": [{"id": "r1", "polyline": [[x, y], ...], "road_class": "primary",
                "lanes": 4, "oneway": 0, "link": false, "layer": 0}, ...],
     "meta": {}}

``lanes`` is the total lane count over both directions, or null when unknown. ``oneway`` follows
OSM: 0 two-way, 1 one-way in polyline order, -1 one-way against polyline order. ``link`` (optional,
default false) marks a ramp or slip road (OSM ``*_link``); ``layer`` (optional, default 0) is OSM's
vertical layer (bridges above 0, tunnels below): roads of different layers cross without meeting.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from cmtool.core.jsonio import Fields, JsonFile

ROAD_CLASSES = ("motorway", "trunk", "primary", "secondary", "tertiary", "unclassified", "residential", "service")
FORMAT = "cmtool.sdmap"


@dataclass
class Road:
    id: str
    polyline: np.ndarray  # (N, 2) float64 metres
    road_class: str = "residential"  # one of ROAD_CLASSES
    lanes: int | None = None  # total over both directions; None = unknown
    oneway: int = 0  # 0 two-way, 1 along the polyline, -1 against it
    link: bool = False  # a ramp or slip road (OSM *_link)
    layer: int = 0  # vertical layer: roads of different layers cross without meeting

    def travel_polyline(self) -> np.ndarray:
        """The polyline in travel direction (reversed for ``oneway == -1``)."""
        return self.polyline[::-1] if self.oneway == -1 else self.polyline


@dataclass
class SDMap(JsonFile):
    city: str | None = None
    roads: list[Road] = field(default_factory=list)
    source: str = ""
    meta: dict = field(default_factory=dict)

    def to_json(self) -> dict:
        return {
            "format": FORMAT,
            "version": 1,
            "city": self.city,
            "source": self.source,
            "roads": [
                {
                    "id": r.id,
                    "polyline": np.round(r.polyline, 3).tolist(),
                    "road_class": r.road_class,
                    "lanes": r.lanes,
                    "oneway": r.oneway,
                }
                | ({"link": True} if r.link else {})
                | ({"layer": r.layer} if r.layer else {})
                for r in self.roads
            ],
            "meta": self.meta,
        }

    @classmethod
    def from_json(cls, obj, where: str = "sdmap") -> "SDMap":
        top = Fields(obj, where)
        top.header(FORMAT, "an SD map file")
        sd = cls(
            city=top.get("city", str, None, allow_none=True),
            source=top.get("source", str, ""),
            meta=top.get("meta", dict, {}),
        )
        seen = set()
        for i, item in enumerate(top.get("roads", list)):
            f = Fields(item, where, f"roads[{i}]")
            road_class = f.get("road_class", str, "residential")
            if road_class not in ROAD_CLASSES:
                f.fail("road_class", f"expected one of {ROAD_CLASSES}, got {road_class!r}")
            lanes = f.get("lanes", int, None, allow_none=True)
            if lanes is not None and not 1 <= lanes <= 16:
                f.fail("lanes", f"expected 1..16 or null, got {lanes}")
            oneway = f.get("oneway", int, 0)
            if oneway not in (-1, 0, 1):
                f.fail("oneway", f"expected -1, 0 or 1, got {oneway}")
            layer = f.get("layer", int, 0)
            if not -5 <= layer <= 5:
                f.fail("layer", f"expected -5..5, got {layer}")
            road = Road(f.get("id", str), f.points("polyline"), road_class, lanes, oneway, f.get("link", bool, False),
                        layer)
            if road.id in seen:
                f.fail("id", f"duplicate road id {road.id!r}")
            seen.add(road.id)
            sd.roads.append(road)
        return sd
