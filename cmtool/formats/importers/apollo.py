"""Apollo HD maps (``apollo.hdmap.Map`` of Baidu Apollo's ``modules/map/proto/map*.proto``), binary or text protobuf.

The messages are declared here from the field numbers of Apollo's published ``.proto`` files, only the fields cmtool
reads (a binary map keeps the others as unknown fields; a text map skips them). Binary and text files are told apart
by their content (a text map is printable UTF-8), whatever the suffix (``base_map.bin``, ``sim_map.txt`` ...).

* Lanes: ``lane`` of type ``CITY_DRIVING`` (or no type) -> vehicle lanes; biking, sidewalk, parking and shoulder lanes
  are not lanes here. Centerline: the points of the ``central_curve`` line segments in order (consecutive repeats
  dropped), else the middle of the left and right boundary curves. Width: twice the mean of the left and right
  ``*_sample`` widths where present, else from the boundary curves, else 3.5 m.
* Successors/predecessors from ``successor_id``/``predecessor_id``; left/right neighbours from the *forward*
  neighbour ids (``left_neighbor_forward_lane_id`` ...; the reverse ones run the other way).
* Junctions: a lane is ``is_intersection`` with ``intersection_id`` the junction id when the lane names the junction
  (``junction_id``), the junction names the lane (``lane_id``), or a lane-junction overlap covers (nearly) the whole
  lane (older maps record only the overlaps).
* Traffic lights: each stop line (``stop_line`` curve) of a ``signal`` gives a stop line (state ``unknown``)
  controlling the lanes that overlap the signal; a signal with several stop lines gives each lane to the nearest one.
  Stop signs are not traffic lights and are not read.
* Crosswalks: ``crosswalk`` polygons.
* Coordinates: Apollo maps are in UTM metres (``header.projection.proj``, a PROJ string ``+proj=utm +zone=10 ...``
  or ``+proj=tmerc +lat_0 +lon_0 +k +x_0 +y_0``). They are re-projected to a transverse Mercator
  (:class:`~cmtool.core.geo.LocalProjection`) centred on the map, recorded as ``meta.lat0`` / ``meta.lon0`` as the
  Lanelet2 importer does; without a readable projection they are only shifted so that the map's centre is (0, 0)
  (``meta.offset``).
* City: Apollo's maps are of California (San Mateo, Sunnyvale, ...) and China, right-hand traffic: the city code is
  ``LAV`` (the nuPlan style of the western US grid, wide multi-lane arterials) unless ``city`` is given; the map
  drives on the right whatever its label.
"""

from __future__ import annotations

import math
import os
import re
from pathlib import Path

import numpy as np

from cmtool.core.errors import CmtoolError
from cmtool.core.geo import LocalProjection
from cmtool.formats.importers.common import MAX_WIDTH, MIN_WIDTH, centerline_and_width, tidy_references
from cmtool.maps.hdmap import Crosswalk, HDMap, Lane, StopLine

CITY = "LAV"
LANE_TYPES = {"NONE": "vehicle", "CITY_DRIVING": "vehicle"}  # Lane.LaneType names cmtool reads as lanes
JUNCTION_COVER = 0.9  # a lane-junction overlap over this share of the lane's length puts the lane in the junction

# The messages cmtool reads: name -> [(field, number, repeated, type)], the type a scalar name, an enum (a tuple of
# its value names and numbers) or another message's name. Field numbers as in Apollo's map*.proto and
# modules/common/proto/geometry.proto (PointENU); only the fields read here are declared.
_LANE_TYPE = (("NONE", 1), ("CITY_DRIVING", 2), ("BIKING", 3), ("SIDEWALK", 4), ("PARKING", 5), ("SHOULDER", 6))
_MESSAGES = {
    "PointENU": [("x", 1, False, "double"), ("y", 2, False, "double")],  # apollo.common.PointENU, [default = nan]
    "Id": [("id", 1, False, "string")],
    "LineSegment": [("point", 1, True, "PointENU")],
    "CurveSegment": [("line_segment", 1, False, "LineSegment")],  # the only member of the curve_type oneof
    "Curve": [("segment", 1, True, "CurveSegment")],
    "Polygon": [("point", 1, True, "PointENU")],
    "LaneBoundary": [("curve", 1, False, "Curve")],
    "LaneSampleAssociation": [("width", 2, False, "double")],
    "Lane": [("id", 1, False, "Id"), ("central_curve", 2, False, "Curve"),
             ("left_boundary", 3, False, "LaneBoundary"), ("right_boundary", 4, False, "LaneBoundary"),
             ("predecessor_id", 8, True, "Id"), ("successor_id", 9, True, "Id"),
             ("left_neighbor_forward_lane_id", 10, True, "Id"), ("right_neighbor_forward_lane_id", 11, True, "Id"),
             ("type", 12, False, _LANE_TYPE), ("junction_id", 16, False, "Id"),
             ("left_sample", 17, True, "LaneSampleAssociation"), ("right_sample", 18, True, "LaneSampleAssociation")],
    "Junction": [("id", 1, False, "Id"), ("lane_id", 6, True, "Id")],
    "Signal": [("id", 1, False, "Id"), ("stop_line", 6, True, "Curve")],
    "Crosswalk": [("id", 1, False, "Id"), ("polygon", 2, False, "Polygon")],
    "LaneOverlapInfo": [("start_s", 1, False, "double"), ("end_s", 2, False, "double")],
    "ObjectOverlapInfo": [("id", 1, False, "Id"), ("lane_overlap_info", 3, False, "LaneOverlapInfo")],
    "Overlap": [("id", 1, False, "Id"), ("object", 2, True, "ObjectOverlapInfo")],
    "Projection": [("proj", 1, False, "string")],
    "Header": [("projection", 3, False, "Projection")],
    "Map": [("header", 1, False, "Header"), ("crosswalk", 2, True, "Crosswalk"), ("junction", 3, True, "Junction"),
            ("lane", 4, True, "Lane"), ("signal", 6, True, "Signal"), ("overlap", 8, True, "Overlap")],
}
_MAP_CLASS = None


def import_apollo(path: str | os.PathLike, city: str | None = None) -> HDMap:
    """Read an Apollo HD map, binary or text protobuf (city code ``LAV`` unless ``city`` is given)."""
    path = Path(path)
    msg = _parse(path)
    hd = HDMap(city=city or CITY, drives_on="right", source=f"apollo:{path.name}")
    try:
        _lanes(msg, hd)
        if not hd.lanes:
            raise CmtoolError(f"{path}: no driving lanes (an Apollo map of {len(msg.lane)} lanes of other types)")
        overlaps = _overlaps(msg, hd)
        _junctions(msg, hd, overlaps)
        _signals(msg, hd, overlaps)
        for cw in msg.crosswalk:
            polygon = _points(cw.polygon.point)
            if len(polygon) > 3 and np.array_equal(polygon[0], polygon[-1]):
                polygon = polygon[:-1]
            if len(polygon) >= 3:
                hd.crosswalks.append(Crosswalk(cw.id.id, polygon))
        proj = msg.header.projection.proj if msg.header.HasField("projection") else ""
        _localise(hd, proj)
    except (TypeError, ValueError) as e:
        raise CmtoolError(f"{path}: malformed Apollo map ({type(e).__name__}: {e})") from None
    return tidy_references(hd)


# ------------------------------------------------------------------ reading
def _map_class():
    """The ``apollo.hdmap.Map`` message class, built once from :data:`_MESSAGES`."""
    global _MAP_CLASS
    if _MAP_CLASS is None:
        descriptor_pb2, descriptor_pool, message_factory = _protobuf("descriptor_pb2", "descriptor_pool",
                                                                     "message_factory")

        F = descriptor_pb2.FieldDescriptorProto
        scalars = {"double": F.TYPE_DOUBLE, "string": F.TYPE_STRING}
        proto = descriptor_pb2.FileDescriptorProto(name="cmtool/apollo_map.proto", package="apollo.hdmap",
                                                   syntax="proto2")
        for name, fields in _MESSAGES.items():
            message = proto.message_type.add(name=name)
            for field, number, repeated, kind in fields:
                f = message.field.add(name=field, number=number,
                                      label=F.LABEL_REPEATED if repeated else F.LABEL_OPTIONAL)
                if isinstance(kind, tuple):  # an enum, declared inside the message
                    enum = message.enum_type.add(name=f"{field.title()}Enum")
                    for value, n in kind:
                        enum.value.add(name=value, number=n)
                    f.type, f.type_name = F.TYPE_ENUM, f".apollo.hdmap.{name}.{enum.name}"
                elif kind in scalars:
                    f.type = scalars[kind]
                    if name == "PointENU":
                        f.default_value = "nan"  # as Apollo declares x and y: a missing coordinate is no coordinate
                else:
                    f.type, f.type_name = F.TYPE_MESSAGE, f".apollo.hdmap.{kind}"
        pool = descriptor_pool.DescriptorPool()
        pool.Add(proto)
        descriptor = pool.FindMessageTypeByName("apollo.hdmap.Map")
        if hasattr(message_factory, "GetMessageClass"):
            _MAP_CLASS = message_factory.GetMessageClass(descriptor)
        else:  # protobuf < 4.22
            _MAP_CLASS = message_factory.MessageFactory(pool).GetPrototype(descriptor)
    return _MAP_CLASS


def _protobuf(*modules: str) -> list:
    """Modules of the ``protobuf`` package (a dependency of cmtool; a clear error where it is missing)."""
    import importlib

    try:
        return [importlib.import_module(f"google.protobuf.{m}") for m in modules]
    except ImportError:
        raise CmtoolError("reading Apollo maps needs the protobuf package: pip install 'protobuf>=4.21'") from None


def _parse(path: Path):
    """The map message of a binary or text protobuf file (told apart by content)."""
    text_format, message = _protobuf("text_format", "message")
    DecodeError = message.DecodeError
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise CmtoolError(f"{path}: no such file") from None
    except OSError as e:
        raise CmtoolError(f"{path}: cannot read ({e.strerror or e})") from None
    if not data.strip():
        raise CmtoolError(f"{path}: empty file, not an Apollo map")
    text = _as_text(data)
    cls = _map_class()
    try:
        if text is not None:
            msg = text_format.Parse(text, cls(), allow_unknown_field=True)
        else:
            msg = cls.FromString(data)
    except text_format.ParseError as e:
        detail = str(e).splitlines()[0].rsplit("': ", 1)[-1] if str(e) else "malformed"
        where = f"line {e.GetLine()}: " if e.GetLine() else ""
        raise CmtoolError(f"{path}: not an Apollo map (text protobuf, {where}{detail[:100]})") from None
    except (DecodeError, RecursionError, ValueError) as e:
        detail = str(e).splitlines()[0].rsplit(": ", 1)[-1] if str(e) else type(e).__name__
        raise CmtoolError(f"{path}: not an Apollo map (binary protobuf: {detail[:100]})") from None
    if not msg.lane:
        raise CmtoolError(f"{path}: not an Apollo map (no lanes)")
    return msg


def _as_text(data: bytes) -> str | None:
    """The file as text when it is printable UTF-8 (a text protobuf), else None (binary)."""
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError:
        return None
    control = sum(ord(c) < 32 and c not in "\t\n\r\f\v" for c in text[:65536])
    return text if control == 0 else None


# ------------------------------------------------------------------ coordinates
def _localise(hd: HDMap, proj: str) -> None:
    """Move every geometry of ``hd`` from the map's grid (UTM) to local metres, in one batch; records the origin."""
    shapes = ([lane.centerline for lane in hd.lanes.values()] + [sl.line for sl in hd.stop_lines]
              + [cw.polygon for cw in hd.crosswalks])
    grid = np.concatenate(shapes)
    lanes = np.concatenate(shapes[: len(hd.lanes)])
    centre = 0.5 * (lanes.min(axis=0) + lanes.max(axis=0))
    params = _tmerc(proj)
    if proj:
        hd.meta["projection"] = proj
    if params is None:
        hd.meta["offset"] = [round(float(v), 3) for v in centre]
        local = grid - centre
    else:
        lat_0, lon_0, k, x_0, y_0 = params
        latlon = LocalProjection(lat_0, lon_0).to_latlon((np.concatenate([centre[None], grid]) - (x_0, y_0)) / k)
        if not np.all(np.isfinite(latlon)) or np.abs(latlon[:, 0]).max() > 89.0:
            raise ValueError(f"coordinates that the projection {proj!r} does not place on the globe")
        lat0, lon0 = (float(v) for v in latlon[0])
        hd.meta.update(lat0=lat0, lon0=lon0)
        local = LocalProjection(lat0, lon0).to_metres(latlon[1:, 0], latlon[1:, 1])
    parts = np.split(local, np.cumsum([len(a) for a in shapes])[:-1])
    for lane, xy in zip(hd.lanes.values(), parts):
        lane.centerline = xy
    for sl, xy in zip(hd.stop_lines, parts[len(hd.lanes):]):
        sl.line = xy
    for cw, xy in zip(hd.crosswalks, parts[len(hd.lanes) + len(hd.stop_lines):]):
        cw.polygon = xy


def _tmerc(proj: str) -> tuple[float, float, float, float, float] | None:
    """(lat_0, lon_0, k, x_0, y_0) of a PROJ ``+proj=utm`` or ``+proj=tmerc`` string (None for any other)."""
    args = dict(re.findall(r"\+(\w+)(?:=(\S+))?", proj or ""))
    try:
        if args.get("proj") == "utm":
            zone = int(args["zone"])
            if not 1 <= zone <= 60:
                return None
            return 0.0, 6.0 * zone - 183.0, 0.9996, 500_000.0, 10_000_000.0 if "south" in args else 0.0
        if args.get("proj") == "tmerc":
            values = tuple(float(args.get(key) or default) for key, default in
                           (("lat_0", 0.0), ("lon_0", 0.0), ("k", args.get("k_0") or 1.0), ("x_0", 0.0), ("y_0", 0.0)))
            ok = all(math.isfinite(v) for v in values) and abs(values[0]) <= 90 and abs(values[1]) <= 180
            return values if ok and values[2] > 0 else None
    except (KeyError, ValueError):
        return None
    return None


def _points(points) -> np.ndarray:
    """Repeated PointENU as an (N, 2) array of grid metres, consecutive repeats dropped."""
    xy = np.array([(p.x, p.y) for p in points], np.float64).reshape(-1, 2)
    if not np.all(np.isfinite(xy)):
        raise ValueError("a point without finite x and y")
    if len(xy) > 1:
        xy = xy[np.concatenate([[True], np.any(np.diff(xy, axis=0) != 0.0, axis=1)])]
    return xy


def _curve(curve) -> np.ndarray:
    """The points of a curve's line segments, in order."""
    return _points([p for seg in curve.segment for p in seg.line_segment.point])


def _length(line: np.ndarray) -> float:
    return float(np.linalg.norm(np.diff(line, axis=0), axis=1).sum())


# ------------------------------------------------------------------ map objects
def _lanes(msg, hd: HDMap) -> None:
    type_names = {v.number: v.name for v in msg.DESCRIPTOR.fields_by_name["lane"].message_type
                  .fields_by_name["type"].enum_type.values}
    for lane in msg.lane:
        lane_type = LANE_TYPES.get(type_names.get(lane.type, "")) if lane.HasField("type") else "vehicle"
        if lane_type is None:
            continue
        lid = lane.id.id
        if not lid:
            raise ValueError("a lane without an id")
        try:
            centerline = _curve(lane.central_curve)
            left, right = _curve(lane.left_boundary.curve), _curve(lane.right_boundary.curve)
        except ValueError as e:
            raise ValueError(f"lane {lid!r}: {e}") from None
        width = None
        if len(left) >= 2 and len(right) >= 2:
            middle, width = centerline_and_width(left, right)
            if len(centerline) < 2:
                centerline = middle
        if len(centerline) < 2:
            continue  # a lane without geometry: nothing to draw or drive
        if lane.left_sample and lane.right_sample:
            half = [np.mean([s.width for s in samples]) for samples in (lane.left_sample, lane.right_sample)]
            width = float(np.clip(sum(half), MIN_WIDTH, MAX_WIDTH))
        if lid in hd.lanes:
            raise ValueError(f"lane {lid!r}: its id is the id of an earlier lane")
        hd.add_lane(Lane(
            id=lid, centerline=centerline, width=3.5 if width is None else width,
            successors=[i.id for i in lane.successor_id], predecessors=[i.id for i in lane.predecessor_id],
            left_neighbor=next((i.id for i in lane.left_neighbor_forward_lane_id if i.id), None),
            right_neighbor=next((i.id for i in lane.right_neighbor_forward_lane_id if i.id), None),
            intersection_id=lane.junction_id.id or None, lane_type=lane_type,
        ))


def _overlaps(msg, hd: HDMap) -> dict[str, list[tuple[str, float]]]:
    """For each object that overlaps lanes of ``hd``: (lane id, share of the lane's length in the overlap) pairs.

    Apollo overlaps are (mostly) pairs of objects; a lane's share comes from its ``lane_overlap_info`` s range."""
    out: dict[str, list[tuple[str, float]]] = {}
    for overlap in msg.overlap:
        lanes = [(o.id.id, o.lane_overlap_info) for o in overlap.object if o.id.id in hd.lanes]
        others = {o.id.id for o in overlap.object if o.id.id not in hd.lanes}
        for lid, info in lanes:
            length = max(_length(hd.lanes[lid].centerline), 1e-6)
            share = (info.end_s - info.start_s) / length
            for other in others:
                if (lid, share) not in out.get(other, []):
                    out.setdefault(other, []).append((lid, share))
    return out


def _junctions(msg, hd: HDMap, overlaps: dict) -> None:
    """Junction membership: named by the lane or the junction, or a lane-junction overlap over (nearly) all the lane."""
    for junction in msg.junction:
        jid = junction.id.id
        members = [i.id for i in junction.lane_id if i.id in hd.lanes]
        members += [lid for lid, share in overlaps.get(jid, []) if share >= JUNCTION_COVER]
        for lid in members:
            hd.lanes[lid].intersection_id = hd.lanes[lid].intersection_id or jid
    for lane in hd.lanes.values():
        lane.is_intersection = lane.intersection_id is not None


def _signals(msg, hd: HDMap, overlaps: dict) -> None:
    """A stop line per signal stop line, controlling the lanes the signal overlaps (each to its nearest stop line)."""
    for signal in msg.signal:
        sid = signal.id.id
        lines = [line for line in (_curve(c) for c in signal.stop_line) if len(line) >= 2]
        if not lines:
            continue
        groups: list[list[str]] = [[] for _ in lines]
        for lid, _ in overlaps.get(sid, []):
            group = groups[_nearest(lines, hd.lanes[lid].centerline)]
            if lid not in group:
                group.append(lid)
        for k, (line, lane_ids) in enumerate(zip(lines, groups)):
            hd.stop_lines.append(StopLine(sid if len(lines) == 1 else f"{sid}.{k}", line, "unknown", lane_ids))


def _nearest(lines: list[np.ndarray], centerline: np.ndarray) -> int:
    """The index of the stop line nearest to a lane (smallest distance between their vertices)."""
    if len(lines) == 1:
        return 0
    d = [np.min(np.linalg.norm(line[:, None, :] - centerline[None, :, :], axis=-1)) for line in lines]
    return int(np.argmin(d))
