"""Any map file, told apart by its content: what lets every command take every map cmtool writes or imports.

Kinds (:func:`map_kind`): ``hdmap`` (cmtool HD map JSON), ``lanegraph`` (lane graph ``.json`` or ``.jsonl``, as
``sample`` writes them), ``sdmap`` (cmtool SD map JSON), ``av2`` (an Argoverse 2 map JSON), ``lanelet2`` (a
Lanelet2 ``.osm``), ``osm`` (OpenStreetMap, ``.osm`` or ``.osm.pbf``: roads without lanes) and ``nuplan``
(a nuPlan ``.gpkg``). :func:`read_lane_graphs` and :func:`read_hd_map` read whichever holds lanes, converting
between a whole HD map and one lane graph (:meth:`LaneGraph.from_hd`, :meth:`LaneGraph.to_hd`); a file without
lanes gets one line saying what it is and which command makes lanes of it; so does a picture (:func:`picture_format`),
and :func:`what_file` names what any file holds for the messages of readers of other things.
"""

from __future__ import annotations

import os
from pathlib import Path

from cmtool.core.errors import CmtoolError
from cmtool.core.jsonio import MalformedJson, loads, read_text
from cmtool.formats.importers import import_hd_map
from cmtool.maps.hdmap import FORMAT as HD_FORMAT
from cmtool.maps.hdmap import HDMap
from cmtool.maps.lanegraph import LaneGraph, read_jsonl
from cmtool.maps.sdmap import FORMAT as SD_FORMAT

NO_LANES = {
    "sdmap": "an SD map (roads, no lanes); this command needs lanes, which `cmtool sample` and `cmtool baseline` "
             "make from OpenStreetMap files (--osm) and HD maps (--from-hd)",
    "osm": "an OpenStreetMap file (roads, no lanes): `cmtool sample --osm` or `cmtool baseline rules --osm ... "
           "--whole MAP.json` makes lanes of it",
}


PICTURES = {b"\x89PNG\r\n\x1a\n": "PNG", b"\xff\xd8\xff": "JPEG", b"BM": "BMP", b"II*\x00": "TIFF", b"MM\x00*": "TIFF",
            b"GIF8": "GIF", b"\x93NUMPY": ".npy array"}  # how a picture file starts -> its format
WORDS = {"hdmap": "an HD map (JSON)", "sdmap": "an SD map (JSON)", "av2": "an Argoverse 2 map (JSON)",
         "lanelet2": "a Lanelet2 map (OSM XML)", "osm": "an OpenStreetMap file", "nuplan": "a nuPlan map (GeoPackage)",
         "lanegraph": "a lane graph (JSON)"}


def picture_format(path: str | os.PathLike) -> str | None:
    """The format of a picture file (PNG, JPEG, ...), told by its first bytes; None: not a picture (or unreadable)."""
    try:
        with open(path, "rb") as f:
            head = f.read(8)
    except OSError:
        return None
    return next((name for magic, name in PICTURES.items() if head.startswith(magic)), None)


def what_file(path: str | os.PathLike) -> str | None:
    """What a file holds, in words for a message (e.g. "a lane graph (JSON)", "a picture (PNG)"); None: nothing
    cmtool reads."""
    picture = picture_format(path)
    if picture is not None:
        return f"a picture ({picture})"
    try:
        kind, obj = map_kind(path)
    except CmtoolError:
        return None
    if kind == "lanegraph" and not (isinstance(obj, dict) and "lanes" in obj):
        return "lane graphs (JSON Lines)" if obj is None and Path(path).suffix == ".jsonl" else None
    return WORDS[kind]


def map_kind(path: str | os.PathLike) -> tuple[str, object]:
    """The kind of map in ``path`` and, for JSON files, the parsed object (None otherwise); a picture is refused."""
    path = Path(path)
    picture = picture_format(path)
    if picture is not None:
        raise CmtoolError(f"{path} is a picture ({picture}); this command takes a map file (a lane graph, HD map, "
                          "Lanelet2, Argoverse 2 or nuPlan map); for a map of a picture use `cmtool sample --sd`")
    if path.suffix == ".gpkg":
        return "nuplan", None
    if path.name.endswith(".pbf"):
        return "osm", None
    text = read_text(path)
    if text.lstrip().startswith("<"):
        return ("lanelet2" if "lanelet" in text else "osm"), None
    try:
        obj = loads(text, str(path))
    except MalformedJson:
        return "lanegraph", None  # JSON Lines, or broken JSON: the lane graph reader names the line
    if isinstance(obj, dict):
        if obj.get("format") == HD_FORMAT:
            return "hdmap", obj
        if obj.get("format") == SD_FORMAT:
            return "sdmap", obj
        if "lane_segments" in obj:
            return "av2", obj
    return "lanegraph", obj


def read_lane_graphs(path: str | os.PathLike) -> list[LaneGraph]:
    """The lane graphs of a lane graph file, or a whole HD map (of any kind that holds lanes) as one."""
    kind, obj = map_kind(path)
    if kind == "lanegraph":
        return read_jsonl(path)
    return [LaneGraph.from_hd(hd_map_of(path, kind, obj))]


def read_hd_map(path: str | os.PathLike) -> HDMap:
    """The HD map of any map file that holds lanes: an HD map JSON, an imported format, or a lane graph file of
    one map (:meth:`LaneGraph.to_hd`)."""
    return hd_map_of(path, *map_kind(path))


def hd_map_of(path, kind: str, obj) -> HDMap:
    """:func:`read_hd_map` of a file whose kind and parsed JSON (:func:`map_kind`) are known (no second read)."""
    if kind in NO_LANES:
        raise CmtoolError(f"{path}: {NO_LANES[kind]}")
    if kind == "hdmap":
        return HDMap.from_json(obj, str(path))
    if kind == "lanegraph":
        graphs = read_jsonl(path)
        if len(graphs) != 1:
            raise CmtoolError(f"{path}: {len(graphs)} lane graphs; this command takes one map (write the one you "
                              "mean to a file of its own)")
        return graphs[0].to_hd()
    return import_hd_map(kind, path)
