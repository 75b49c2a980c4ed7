"""OpenStreetMap files (``.osm`` XML, ``.osm.pbf``) <-> :class:`SDMap` in local metres.

Only drivable highway ways are kept: motorway, trunk, primary, secondary, tertiary, unclassified,
residential, service (``*_link`` ways join their parent class, ``living_street`` counts as
residential); footways, cycleways, paths, steps, tracks and the like are skipped. Tags read:
``lanes`` (an integer 1-16, else unknown), ``oneway`` (yes/true/1 -> 1, -1/reverse -> -1, else 0;
motorways, motorway links and roundabouts are one-way unless tagged otherwise), ``*_link`` (a
ramp or slip road) and ``layer`` (an integer -5..5; else bridges 1, tunnels -1, other ways 0).
Coordinates are projected with a transverse Mercator projection centred on the mean of the nodes used
(:func:`~cmtool.core.geo.centre_of`: across the antimeridian too). A way whose
nodes are partly missing from the file (a clipped extract) keeps each run of >= 2 present nodes.

:func:`write_osm` writes an SD map as ``.osm`` XML (roads as ``highway`` ways with ``lanes``,
``oneway`` and ``layer`` tags, points at the same spot sharing one node), placed at a chosen
latitude and longitude, so procedural maps can stand in for OpenStreetMap extracts.
"""

from __future__ import annotations

import os
from pathlib import Path
from xml.sax.saxutils import quoteattr

import numpy as np

from cmtool.core.errors import CmtoolError
from cmtool.core.geo import LocalProjection, centre_of
from cmtool.core.jsonio import write_text_atomic
from cmtool.formats.osmxml import read_osm_xml
from cmtool.maps.sdmap import ROAD_CLASSES, Road, SDMap

_ALIASES = {"living_street": "residential"}
_ONEWAY_BY_DEFAULT = ("motorway", "motorway_link")


def road_class_of(highway: str | None) -> str | None:
    """The SD road class of an OSM ``highway`` value, or None when it is not a drivable road."""
    if highway is None:
        return None
    base = highway.removesuffix("_link")
    base = _ALIASES.get(base, base)
    return base if base in ROAD_CLASSES else None


def parse_lanes(value: str | None) -> int | None:
    try:
        lanes = int(value.strip())
    except (AttributeError, ValueError):
        return None
    return lanes if 1 <= lanes <= 16 else None


def parse_oneway(tags: dict[str, str]) -> int:
    value = tags.get("oneway", "").strip().lower()
    if value in ("yes", "true", "1"):
        return 1
    if value in ("-1", "reverse"):
        return -1
    if not value and (tags.get("highway") in _ONEWAY_BY_DEFAULT or tags.get("junction") == "roundabout"):
        return 1
    return 0


def parse_layer(tags: dict[str, str]) -> int:
    try:
        layer = int(tags.get("layer", "").strip())
    except ValueError:
        layer = None
    if layer is not None and -5 <= layer <= 5:
        return layer
    if tags.get("bridge", "no") not in ("no", ""):
        return 1
    return -1 if tags.get("tunnel", "no") not in ("no", "") else 0


def read_osm(path: str | os.PathLike) -> SDMap:
    """Read the road network of an OpenStreetMap ``.osm`` or ``.osm.pbf`` file."""
    path = Path(path)
    if not path.is_file():
        raise CmtoolError(f"{path}: no such file")
    hint = ""
    if path.name.endswith(".pbf"):
        nodes, ways = _read_pbf(path)
    elif path.suffix == ".osm" or path.name.endswith(".osm.xml"):
        data = read_osm_xml(path)
        nodes = {i: (n.lat, n.lon) for i, n in data.nodes.items()}
        ways = [(i, w.nodes, w.tags) for i, w in data.ways.items() if road_class_of(w.tags.get("highway"))]
        if any(w.tags.get("type") in ("line_thin", "line_thick") for w in data.ways.values()):
            hint = "; it looks like a Lanelet2 map (`cmtool data import --format lanelet2`)"
    else:
        from cmtool.formats.mapfile import what_file

        what = what_file(path)
        raise CmtoolError(f"{path}{f' is {what};' if what else ':'} expected an OpenStreetMap .osm or .osm.pbf file")
    runs = []  # (way id, part, node ids, tags)
    for way_id, refs, tags in ways:
        run: list[int] = []
        parts = 0
        for ref in list(refs) + [None]:
            if ref is not None and ref in nodes:
                run.append(ref)
                continue
            if len(run) >= 2:
                runs.append((way_id, parts, run, tags))
                parts += 1
            run = []
    if not runs:
        raise CmtoolError(f"{path}: no drivable roads (ways tagged highway=motorway ... service, with their nodes)"
                          f"{hint}")
    sd = SDMap(city=None, source=f"osm:{path.name}")
    used = np.array([nodes[r] for _, _, run, _ in runs for r in set(run)])
    lat0, lon0 = centre_of(used)
    proj = LocalProjection(lat0, lon0)
    sd.meta = {"lat0": float(lat0), "lon0": float(lon0)}
    for way_id, part, run, tags in runs:
        latlon = np.array([nodes[r] for r in run])
        sd.roads.append(Road(
            id=f"w{way_id}" + (f".{part}" if part else ""),
            polyline=proj.to_metres(latlon[:, 0], latlon[:, 1]),
            road_class=road_class_of(tags.get("highway")),
            lanes=parse_lanes(tags.get("lanes")),
            oneway=parse_oneway(tags),
            link=tags.get("highway", "").endswith("_link"),
            layer=parse_layer(tags),
        ))
    return sd


def _read_pbf(path: Path) -> tuple[dict[int, tuple[float, float]], list[tuple[int, list[int], dict]]]:
    """Highway ways, then the nodes they use, in two passes over a PBF file (via pyosmium)."""
    try:
        import osmium
    except ImportError:
        raise CmtoolError(f"{path}: reading .osm.pbf needs pyosmium, a dependency of cmtool that is missing here: "
                          "pip install osmium") from None
    ways, wanted = [], set()
    try:
        for way in osmium.FileProcessor(str(path), osmium.osm.WAY):
            tags = {t.k: t.v for t in way.tags}
            if road_class_of(tags.get("highway")):
                refs = [n.ref for n in way.nodes]
                ways.append((way.id, refs, tags))
                wanted.update(refs)
        nodes = {}
        for node in osmium.FileProcessor(str(path), osmium.osm.NODE):
            if node.id in wanted and node.location.valid():
                nodes[node.id] = (node.location.lat, node.location.lon)
    except RuntimeError as e:
        raise CmtoolError(f"{path}: cannot read OSM PBF: {e}") from None
    return nodes, ways


def write_osm(sd: SDMap, path: str | os.PathLike, lat0: float, lon0: float) -> None:
    """Write ``sd`` as an OSM XML file, its metre origin placed at ``(lat0, lon0)``."""
    proj = LocalProjection(lat0, lon0)
    node_ids: dict[tuple[int, int], int] = {}
    coords: list[tuple[float, float]] = []
    ways = []
    for road in sd.roads:
        refs = []
        for x, y in np.asarray(road.polyline, dtype=np.float64):
            key = (round(x * 1000), round(y * 1000))  # points within a millimetre share a node
            if key not in node_ids:
                node_ids[key] = len(coords) + 1
                coords.append((x, y))
            if not refs or refs[-1] != node_ids[key]:
                refs.append(node_ids[key])
        tags = {"highway": road.road_class + ("_link" if road.link else "")}
        if road.lanes is not None:
            tags["lanes"] = str(road.lanes)
        if road.oneway:
            tags["oneway"] = "yes" if road.oneway == 1 else "-1"
        if road.layer:
            tags["layer"] = str(road.layer)
        if len(refs) >= 2:
            ways.append((refs, tags))
    latlon = proj.to_latlon(np.array(coords).reshape(-1, 2))
    lines = ['<?xml version="1.0" encoding="UTF-8"?>', '<osm version="0.6" generator="cmtool">']
    lines += [f'  <node id="{i}" lat="{lat:.9f}" lon="{lon:.9f}" version="1"/>'
              for i, (lat, lon) in enumerate(latlon, start=1)]
    for k, (refs, tags) in enumerate(ways, start=1):
        lines.append(f'  <way id="{k}" version="1">')
        lines += [f'    <nd ref="{r}"/>' for r in refs]
        lines += [f"    <tag k={quoteattr(key)} v={quoteattr(value)}/>" for key, value in tags.items()]
        lines.append("  </way>")
    lines.append("</osm>")
    write_text_atomic(path, "\n".join(lines) + "\n")

