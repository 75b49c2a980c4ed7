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
                data.nodes[int(el.get("id"))] = OsmNode(float(el.get("lat")), float(el.get("lon")), tags)
            elif el.tag == "way":
                data.ways[int(el.get("id"))] = OsmWay([int(nd.get("ref")) for nd in el.iter("nd")], tags)
            elif el.tag == "relation":
                members = [(m.get("type"), int(m.get("ref")), m.get("role", "")) for m in el.iter("member")]
                data.relations[int(el.get("id"))] = OsmRelation(members, tags)
    except (TypeError, ValueError):
        line = f" (line {el.sourceline})" if hasattr(el, "sourceline") else ""
        raise CmtoolError(f"{path}: <{el.tag} id={el.get('id')!r}>{line} lacks a valid id, lat/lon or ref") from None
    return data
