"""Safe reading of OSM XML files (OpenStreetMap ``.osm`` and Lanelet2 maps share the format).

Parsing goes through ``defusedxml``, which refuses DTD entity declarations and external
references, so a hostile file cannot expand entities or read local files.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from xml.etree.ElementTree import ParseError

from defusedxml import DefusedXmlException
from defusedxml.ElementTree import parse

from cmtool.core.errors import CmtoolError


@dataclass
class OsmNode:
    lat: float
    lon: float
    tags: dict[str, str] = field(default_factory=dict)


@dataclass
class OsmWay:
    nodes: list[int]
    tags: dict[str, str] = field(default_factory=dict)


@dataclass
class OsmRelation:
    members: list[tuple[str, int, str]]  # (type: node/way/relation, ref, role)
    tags: dict[str, str] = field(default_factory=dict)


@dataclass
class OsmData:
    nodes: dict[int, OsmNode] = field(default_factory=dict)
    ways: dict[int, OsmWay] = field(default_factory=dict)
    relations: dict[int, OsmRelation] = field(default_factory=dict)


def read_osm_xml(path: str | os.PathLike) -> OsmData:
    """Read nodes, ways and relations (with their tags) from an OSM XML file.

    Elements marked ``action="delete"`` (JOSM edits) are skipped. Raises :class:`CmtoolError` for
    a missing file, malformed or unsafe XML, or elements without the attributes OSM requires.
    """
    path = Path(path)
    if not path.is_file():
        raise CmtoolError(f"{path}: no such file")
    try:
        root = parse(str(path), forbid_dtd=True).getroot()
    except ParseError as e:
        raise CmtoolError(f"{path}: malformed XML: {e}") from None
    except DefusedXmlException as e:
        raise CmtoolError(f"{path}: unsafe XML refused ({type(e).__name__})") from None
    if root.tag != "osm":
        raise CmtoolError(f"{path}: not an OSM XML file (root element <{root.tag}>, expected <osm>)")
    data = OsmData()
    try:
        for el in root:
            if el.get("action") == "delete":
                continue
            tags = {t.get("k"): t.get("v", "") for t in el.iter("tag")}
            if el.tag == "node":
                node = OsmNode(float(el.get("lat")), float(el.get("lon")), tags)
                _check_node(path, el, node, data.nodes.get(int(el.get("id"))))
                data.nodes[int(el.get("id"))] = node
            elif el.tag == "way":
                way = OsmWay([int(nd.get("ref")) for nd in el.iter("nd")], tags)
                if data.ways.get(int(el.get("id")), way).nodes != way.nodes:
                    raise CmtoolError(f"{path}: way {el.get('id')}{_line(el)} appears twice with other nodes")
                data.ways[int(el.get("id"))] = way
            elif el.tag == "relation":
                members = [(m.get("type"), int(m.get("ref")), m.get("role", "")) for m in el.iter("member")]
                data.relations[int(el.get("id"))] = OsmRelation(members, tags)
    except (TypeError, ValueError):
        raise CmtoolError(f"{path}: <{el.tag} id={el.get('id')!r}>{_line(el)} lacks a valid id, lat/lon or ref") \
            from None
    return data


def _check_node(path: Path, el, node: OsmNode, before: OsmNode | None) -> None:
    """Refuse a node off the globe (latitude beyond 90 degrees, longitude beyond 180, not finite) or one whose id an
    earlier node of another place has."""
    if not (abs(node.lat) <= 90.0 and abs(node.lon) <= 180.0):  # also false for nan
        raise CmtoolError(f"{path}: node {el.get('id')}{_line(el)} lies off the globe (lat {el.get('lat')}, lon "
                          f"{el.get('lon')}; latitude within [-90, 90], longitude within [-180, 180])")
    if before is not None and (before.lat, before.lon) != (node.lat, node.lon):
        raise CmtoolError(f"{path}: node id {el.get('id')}{_line(el)} appears twice, at two places "
                          f"({before.lat}, {before.lon} and {node.lat}, {node.lon})")


def _line(el) -> str:
    return f" (line {el.sourceline})" if getattr(el, "sourceline", None) else ""
