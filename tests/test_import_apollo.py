"""Apollo importer against the raw protobuf of the two shared Apollo maps (walked here independently, from the wire
format: field numbers of Apollo's map.proto / map_lane.proto / map_geometry.proto), text protobuf, errors, a picture."""

import struct
from pathlib import Path

import numpy as np
import pytest

from cmtool.core.errors import CmtoolError
from cmtool.core.geometry import CV_SHIFT, ego_to_pixel
from cmtool.formats.importers import import_hd_map
from cmtool.maps.hdmap import HDMap

DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "real" / "apollo"
SAN_MATEO, BORREGAS = DATA / "san_mateo_sim_map.bin", DATA / "borregas_ave_base_map.bin"
needs_data = pytest.mark.skipif(not DATA.is_dir(), reason="shared Apollo maps not available")
CITY_DRIVING, PARKING = 2, 5  # apollo.hdmap.Lane.LaneType

# The shared data README's figures (all lanes), and what cmtool imports: the driving lanes (San Mateo's 199 parking
# lanes along the kerbs are not lanes to drive in).
EXPECTED = {
    "san_mateo_sim_map.bin": dict(raw_lanes=1305, raw_km=23.6, raw_successors=1427, junctions=67,
                                  lanes=1106, km=20.1, successors=1285, signals=130, stop_lines=187, crosswalks=52),
    "borregas_ave_base_map.bin": dict(raw_lanes=60, raw_km=2.7, raw_successors=62, junctions=2,
                                      lanes=60, km=2.7, successors=62, signals=15, stop_lines=15, crosswalks=6),
}


# ------------------------------------------------------------------ an independent wire-format walker
def _fields(buf: bytes):
    """(field number, value) of a protobuf message: ints for varints, bytes for length-delimited fields, floats for
    64-bit fields (doubles)."""
    i = 0
    while i < len(buf):
        key, i = _varint(buf, i)
        number, wire = key >> 3, key & 7
        if wire == 0:
            value, i = _varint(buf, i)
        elif wire == 1:
            value, i = struct.unpack_from("<d", buf, i)[0], i + 8
        elif wire == 2:
            n, i = _varint(buf, i)
            value, i = buf[i:i + n], i + n
        elif wire == 5:
            value, i = buf[i:i + 4], i + 4
        else:
            raise ValueError(f"wire type {wire}")
        yield number, value


def _varint(buf: bytes, i: int) -> tuple[int, int]:
    value = shift = 0
    while True:
        b = buf[i]
        value |= (b & 0x7F) << shift
        i, shift = i + 1, shift + 7
        if b < 0x80:
            return value, i


def _get(buf: bytes, number: int) -> list:
    return [v for n, v in _fields(buf) if n == number]


def _raw(path: Path) -> dict:
    """Lanes (id, type, successor ids, central curve points in UTM) and top-level counts, from the wire."""
    top = list(_fields(path.read_bytes()))
    lanes = {}
    for buf in (v for n, v in top if n == 4):  # Map.lane
        points = [(_get(p, 1)[0], _get(p, 2)[0]) for seg in _get((_get(buf, 2) or [b""])[0], 1)  # Curve.segment
                  for line in _get(seg, 1) for p in _get(line, 1)]  # CurveSegment.line_segment, LineSegment.point
        lanes[_get(_get(buf, 1)[0], 1)[0].decode()] = dict(
            type=(_get(buf, 12) or [None])[0], points=np.array(points),
            successors=[_get(s, 1)[0].decode() for s in _get(buf, 9)])
    counts = {name: sum(n == k for n, _ in top) for name, k in (("crosswalks", 2), ("junctions", 3), ("signals", 6))}
    return dict(lanes=lanes, **counts)


def _km(lines) -> float:
    return sum(float(np.linalg.norm(np.diff(l, axis=0), axis=1).sum()) for l in lines) / 1000.0


@pytest.fixture(scope="module", params=[SAN_MATEO, BORREGAS], ids=lambda p: p.stem)
def case(request):
    if not DATA.is_dir():
        pytest.skip("shared Apollo maps not available")
    return request.param, _raw(request.param), import_hd_map("apollo", request.param)


# ------------------------------------------------------------------ the real maps
def test_counts_match_raw_and_readme(case):
    path, raw, hd = case
    want = EXPECTED[path.name]
    lanes = raw["lanes"]
    assert len(lanes) == want["raw_lanes"]
    assert _km(l["points"] for l in lanes.values()) == pytest.approx(want["raw_km"], rel=0.03)
    assert sum(len(l["successors"]) for l in lanes.values()) == want["raw_successors"]
    assert (raw["junctions"], raw["signals"], raw["crosswalks"]) == (want["junctions"], want["signals"],
                                                                     want["crosswalks"])
    driving = {k for k, l in lanes.items() if l["type"] == CITY_DRIVING}
    assert {l["type"] for k, l in lanes.items() if k not in driving} <= {PARKING}
    assert set(hd.lanes) == driving and len(hd.lanes) == want["lanes"]
    edges = {(a, b) for a, lane in hd.lanes.items() for b in lane.successors}
    assert edges == {(a, b) for a in driving for b in lanes[a]["successors"] if b in driving}
    assert len(edges) == want["successors"]
    assert _km(lane.centerline for lane in hd.lanes.values()) == pytest.approx(want["km"], rel=0.03)
    # UTM metres (scale 0.9996 on the central meridian) to true metres: lengths agree to well within a per cent
    assert _km(lane.centerline for lane in hd.lanes.values()) == pytest.approx(
        _km(lanes[k]["points"] for k in driving), rel=0.005)
    assert len({lane.intersection_id for lane in hd.lanes.values()} - {None}) == want["junctions"]
    assert len(hd.stop_lines) == want["stop_lines"] and len(hd.crosswalks) == want["crosswalks"]
    assert hd.reference_errors() == []
    assert hd.city == "LAV" and hd.drives_on == "right" and hd.source == f"apollo:{path.name}"
    assert set(HDMap.from_json(hd.to_json()).lanes) == set(hd.lanes)


def test_geometry_is_local_metres_on_the_globe(case):
    path, raw, hd = case
    xmin, ymin, xmax, ymax = hd.bounds()
    assert max(abs(xmin), abs(xmax), abs(ymin), abs(ymax)) < 1000  # near the origin, not at UTM's 4,000 km
    assert abs(xmin + xmax) < 10 and abs(ymin + ymax) < 10
    # the README: San Mateo about 37.557-37.568 N, 122.321-122.331 W; Borregas Ave (Sunnyvale) about 37.41 N, 122.02 W
    lat0, lon0 = hd.meta["lat0"], hd.meta["lon0"]
    assert (37.557 < lat0 < 37.568 and -122.331 < lon0 < -122.321) if "mateo" in path.name else \
        (37.40 < lat0 < 37.43 and -122.03 < lon0 < -122.00)
    assert "+proj=utm +zone=10" in hd.meta["projection"]
    # the shape is kept: every lane's point-to-point distances as in UTM (to 0.1 %)
    for k, lane in list(hd.lanes.items())[:200]:
        utm = raw["lanes"][k]["points"]
        np.testing.assert_allclose(np.linalg.norm(lane.centerline - lane.centerline[0], axis=1),
                                   np.linalg.norm(utm - utm[0], axis=1) / 0.9996, rtol=1e-3, atol=0.02)


def test_links_junctions_lights_and_widths(case):
    _, _, hd = case
    for a, lane in hd.lanes.items():
        for b in lane.successors:
            assert np.linalg.norm(lane.centerline[-1] - hd.lanes[b].centerline[0]) < 1.0, (a, b)
        for side in ("left_neighbor", "right_neighbor"):
            n = getattr(lane, side)
            if n is not None:  # forward neighbours: same direction, side by side
                c, o = lane.centerline, hd.lanes[n].centerline
                assert np.dot(c[-1] - c[0], o[-1] - o[0]) > 0
                assert np.min(np.linalg.norm(c[:, None] - o[None], axis=2)) < 8.0
    inside = [lane for lane in hd.lanes.values() if lane.is_intersection]
    assert inside and all(lane.intersection_id for lane in inside)
    assert 0.2 < len(inside) / len(hd.lanes) < 0.8
    assert sum(len(s.lane_ids) for s in hd.stop_lines) > len(hd.stop_lines)
    for sl in hd.stop_lines:  # a light's stop line lies across or next to the lanes it controls
        for lid in sl.lane_ids:
            gap = np.min(np.linalg.norm(sl.line[:, None] - hd.lanes[lid].centerline[None], axis=2))
            assert gap < 25.0, (sl.id, lid)
        assert sl.state == "unknown"
    widths = np.array([lane.width for lane in hd.lanes.values()])
    assert 3.0 < np.median(widths) < 4.0 and widths.min() >= 0.5
    for cw in hd.crosswalks:
        assert len(cw.polygon) >= 3 and not np.allclose(cw.polygon[0], cw.polygon[-1])


def test_city_override(tmp_path):
    if not DATA.is_dir():
        pytest.skip("shared Apollo maps not available")
    hd = import_hd_map("apollo", BORREGAS, city="PIT")
    assert hd.city == "PIT" and hd.drives_on == "right"


# ------------------------------------------------------------------ text protobuf
@needs_data
def test_text_protobuf_round_trip(tmp_path):
    """The binary map written as text protobuf imports to the same map, whatever the suffix says."""
    from google.protobuf import text_format

    from cmtool.formats.importers.apollo import _map_class

    msg = _map_class().FromString(BORREGAS.read_bytes())
    text = text_format.MessageToString(msg)
    assert text.startswith("header {") and "lane {" in text
    binary = import_hd_map("apollo", BORREGAS)
    for name in ("base_map.txt", "text_named.bin"):  # detected by content, not by suffix
        (tmp_path / name).write_text(text)
        hd = import_hd_map("apollo", tmp_path / name)
        assert set(hd.lanes) == set(binary.lanes)
        for k, lane in hd.lanes.items():
            np.testing.assert_allclose(lane.centerline, binary.lanes[k].centerline, atol=1e-6)
            assert lane.successors == binary.lanes[k].successors and lane.width == binary.lanes[k].width
        assert [s.lane_ids for s in hd.stop_lines] == [s.lane_ids for s in binary.stop_lines]
        assert len(hd.crosswalks) == len(binary.crosswalks) and hd.meta == binary.meta
    (tmp_path / "binary_named.txt").write_bytes(BORREGAS.read_bytes())
    assert set(import_hd_map("apollo", tmp_path / "binary_named.txt").lanes) == set(binary.lanes)


def _point(x, y):
    return f"point {{ x: {x} y: {y} }}"


def test_text_protobuf_with_fields_cmtool_does_not_read(tmp_path):
    """A hand-written text map with Apollo fields cmtool does not declare (speed limits, turn types, stop signs ...)
    and no projection: read, only shifted to the origin."""
    lane = ('lane {{ id {{ id: "{i}" }} central_curve {{ segment {{ line_segment {{ {a} {b} }} s: 0 '
            'start_position {{ x: 1 y: 2 z: 0 }} heading: 0.1 length: 50 }} }} speed_limit: 13.4 turn: NO_TURN '
            'type: CITY_DRIVING direction: FORWARD {succ} left_sample {{ s: 0 width: 1.6 }} '
            'right_sample {{ s: 0 width: 1.6 }} }}\n')
    text = ('header { version: "1" date: "2020" district: "x" vendor: "someone" }\n'
            + lane.format(i="a", a=_point(500000, 4e6), b=_point(500050, 4e6), succ='successor_id { id: "b" }')
            + lane.format(i="b", a=_point(500050, 4e6), b=_point(500100, 4e6), succ='predecessor_id { id: "a" }')
            + 'stop_sign { id { id: "s" } stop_line { segment { line_segment { '
            + _point(500040, 3999998) + _point(500040, 4000002.0) + ' } } } type: ONE_WAY }\n')
    path = tmp_path / "hand.txt"
    path.write_text(text)
    hd = import_hd_map("apollo", path)
    assert set(hd.lanes) == {"a", "b"} and hd.lanes["a"].successors == ["b"] and hd.lanes["b"].predecessors == ["a"]
    np.testing.assert_allclose(hd.lanes["a"].centerline, [[-50, 0], [0, 0]])
    assert hd.lanes["a"].width == pytest.approx(3.2) and hd.meta == {"offset": [500050.0, 4000000.0]}
    assert hd.reference_errors() == []


# ------------------------------------------------------------------ errors
def test_errors(tmp_path):
    with pytest.raises(CmtoolError, match=r"missing\.bin: no such file"):
        import_hd_map("apollo", tmp_path / "missing.bin")
    garbage = tmp_path / "garbage.bin"
    garbage.write_bytes(np.random.default_rng(0).bytes(4000))
    with pytest.raises(CmtoolError, match=r"garbage\.bin: not an Apollo map \(binary protobuf") as e:
        import_hd_map("apollo", garbage)
    assert "\n" not in str(e.value) and len(str(e.value)) < 200
    empty = tmp_path / "empty.bin"
    empty.write_bytes(b"")
    with pytest.raises(CmtoolError, match=r"empty\.bin: empty file"):
        import_hd_map("apollo", empty)
    av2 = tmp_path / "log_map.json"
    av2.write_text('{"lane_segments": {}, "pedestrian_crossings": {}}')
    with pytest.raises(CmtoolError, match=r"log_map\.json: not an Apollo map \(text protobuf, line 1: ") as e:
        import_hd_map("apollo", av2)
    assert "\n" not in str(e.value)
    osm = tmp_path / "map.osm"
    osm.write_text("<?xml version='1.0'?>\n<osm><node id='1' lat='49' lon='8'/></osm>\n")
    with pytest.raises(CmtoolError, match=r"map\.osm: not an Apollo map"):
        import_hd_map("apollo", osm)
    other = tmp_path / "other.txt"  # well-formed text protobuf of some other message: nothing Apollo in it
    other.write_text('name: "x" items { value: 3 }\n')
    with pytest.raises(CmtoolError, match=r"other\.txt: not an Apollo map \(no lanes\)"):
        import_hd_map("apollo", other)
    bad = tmp_path / "bad.txt"
    bad.write_text('lane {\n  id { id: "a" }\n  central_curve { segment { line_segment { point { x: oops } } } }\n}\n')
    with pytest.raises(CmtoolError, match=r"bad\.txt: not an Apollo map \(text protobuf, line 3: "):
        import_hd_map("apollo", bad)
    no_y = tmp_path / "no_y.txt"  # Apollo's coordinates default to NaN: a point without y is no point
    no_y.write_text('lane { id { id: "a" } central_curve { segment { line_segment { point { x: 1 } '
                    + _point(3, 4) + " } } } }\n")
    with pytest.raises(CmtoolError, match=r"no_y\.txt: malformed Apollo map \(ValueError: lane 'a': a point without"):
        import_hd_map("apollo", no_y)
    parking = tmp_path / "parking.txt"
    parking.write_text('lane { id { id: "p" } type: PARKING central_curve { segment { line_segment { '
                       + _point(0, 0) + _point(5, 0) + " } } } }\n")
    with pytest.raises(CmtoolError, match=r"parking\.txt: no driving lanes"):
        import_hd_map("apollo", parking)
    if DATA.is_dir():  # an Apollo map is not a file of the other formats either
        with pytest.raises(CmtoolError, match=r"borregas_ave_base_map\.bin: malformed XML"):
            import_hd_map("lanelet2", BORREGAS)


# ------------------------------------------------------------------ a picture
@needs_data
def test_picture_of_the_map_shows_its_lanes():
    """cmtool's own lane drawing (cmtool.viz.draw.lanes_image) of the whole San Mateo map, north up: the pixels it
    draws are where the imported lanes run, and the map sits in the middle of the picture."""
    from cmtool.viz.draw import BACKGROUND, lanes_image

    hd = import_hd_map("apollo", SAN_MATEO)
    size, frame_m = 600, 1300.0  # about 2.2 m a pixel: the whole map (about 860 x 1180 m) fits
    lines = [np.stack([lane.centerline[:, 1], -lane.centerline[:, 0]], axis=1) for lane in hd.lanes.values()]
    img = lanes_image(lines, [], [], [], frame_m=frame_m, size=size, ego=False)
    drawn = np.any(img != np.array(BACKGROUND, np.uint8), axis=2)
    # where the lanes run, densely sampled, in whole pixels
    dense = [np.stack([np.interp(np.linspace(0, 1, 200), np.linspace(0, 1, len(l)), l[:, k]) for k in (0, 1)], 1)
             for l in lines]
    pix = np.round(ego_to_pixel(np.concatenate(dense), frame_m / size, frame_m) / (1 << CV_SHIFT)).astype(int)
    assert pix.min() >= 0 and pix.max() < size  # nothing falls off the picture
    truth = np.zeros((size, size), bool)
    truth[pix[:, 1], pix[:, 0]] = True
    near = _dilate(truth, 2)
    assert drawn[truth].mean() > 0.95 or _dilate(drawn, 1)[truth].mean() > 0.99  # every lane shows
    assert near[drawn].mean() > 0.97  # and nothing else does
    rows, cols = np.nonzero(drawn)
    assert abs(rows.mean() - size / 2) < 40 and abs(cols.mean() - size / 2) < 40
    assert 0.02 < drawn.mean() < 0.5


def _dilate(mask: np.ndarray, r: int) -> np.ndarray:
    out = mask.copy()
    for dr in range(-r, r + 1):
        for dc in range(-r, r + 1):
            out |= np.roll(np.roll(mask, dr, axis=0), dc, axis=1)
    return out
