"""Importers for real HD maps: Argoverse 2 log maps, Lanelet2 OSM maps, nuPlan GeoPackage maps and Apollo HD maps
(binary or text protobuf).

Each importer turns one file into an :class:`~cmtool.maps.hdmap.HDMap` in metres whose references
are consistent (``hd.reference_errors() == []``). User errors (missing file, malformed content, a
file of another format) raise :class:`~cmtool.core.errors.CmtoolError` with one line naming the file.
"""

from __future__ import annotations

import os

from cmtool.core.errors import CmtoolError
from cmtool.maps.hdmap import HDMap

FORMATS = ("av2", "lanelet2", "nuplan", "apollo")


def import_hd_map(fmt: str, path: str | os.PathLike, city: str | None = None) -> HDMap:
    """Import the HD map in ``path`` of format ``fmt`` (one of :data:`FORMATS`).

    ``city`` overrides the city code the importer derives from the file (name).
    """
    if fmt == "av2":
        from cmtool.formats.importers.av2 import import_av2 as importer
    elif fmt == "lanelet2":
        from cmtool.formats.importers.lanelet2 import import_lanelet2 as importer
    elif fmt == "nuplan":
        from cmtool.formats.importers.nuplan import import_nuplan as importer
    elif fmt == "apollo":
        from cmtool.formats.importers.apollo import import_apollo as importer
    else:
        raise CmtoolError(f"unknown format {fmt!r} (choose from {', '.join(FORMATS)})")
    return importer(path, city=city)
