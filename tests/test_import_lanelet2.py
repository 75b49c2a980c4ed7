"""Lanelet2 importer against the raw Karlsruhe example (parsed here independently with xml.etree)."""

import xml.etree.ElementTree as ET
from itertools import combinations
from pathlib import Path

import numpy as np
import pytest
import shapely
from shapely.geometry import LineString

from cmtool.core.errors import CmtoolError
from cmtool.formats.importers import import_hd_map
from cmtool.maps.hdmap import HDMap

MAP = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "lanelet2" / "mapping_example.osm"
ROAD = ("road", "highway", "play_street", "emergency_lane", "bus_lane")


@pytest.fixture(scope="module")
def raw():
    if not MAP.is_file():
        pytest.skip("shared Lanelet2 data not available")
    root = ET.parse(MAP).getroot()
    live = [e for e in root if e.get("action") != "delete"]
    nodes = {e.get("id"): (float(e.get("lat")), float(e.get("lon"))) for e in live if e.tag == "node"}
    ways = {e.get("id"): [n.get("ref") for n in e.iter("nd")] for e in live if e.tag == "way"}
    rels = {}
    for e in live:
        if e.tag == "relation":
            tags = {t.get("k"): t.get("v") for t in e.iter("tag")}
            members = [(m.get("type"), m.get("ref"), m.get("role")) for m in e.iter("member")]
            rels[e.get("id")] = (tags, members)
    return nodes, ways, rels


@pytest.fixture(scope="module")
def hd(raw):
    return import_hd_map("lanelet2", MAP)


def _lanelets(rels, subtypes):
    return {k: v for k, v in rels.items() if v[0].get("type") == "lanelet" and v[0].get("subtype") in subtypes}


def _metres(nodes):
    """Independent local east/north metres around the mean lat/lon, from the WGS84 ellipsoid's radii of
    curvature (good to a few centimetres over this map)."""
    ll = np.array(list(nodes.values()))
    lat0, lon0 = ll.mean(axis=0)
    a, e2 = 6378137.0, 0.00669437999014
    s2 = np.sin(np.radians(lat0)) ** 2
    north = np.radians(1.0) * a * (1 - e2) / (1 - e2 * s2) ** 1.5  # metres per degree of latitude
    east = np.radians(1.0) * a / np.sqrt(1 - e2 * s2)  # times cos(lat): metres per degree of longitude

    def f(lat, lon):
        return np.array([(lon - lon0) * east * np.cos(np.radians(lat)), (lat - lat0) * north])

    return f


def test_lane_crosswalk_and_light_counts(raw, hd):
    _, _, rels = raw
    roads = _lanelets(rels, ROAD)
    two_way = [k for k, (tags, _) in roads.items() if tags.get("one_way") == "no"]
    assert len(hd.lanes) == len(roads) + len(two_way)
    assert set(hd.lanes) == set(roads) | {f"{k}-rev" for k in two_way}
    assert len(hd.crosswalks) == len(_lanelets(rels, ("crosswalk",)))
    light = ("regulatory_element", "traffic_light")
    lights = {k for k, (tags, _) in rels.items() if (tags.get("type"), tags.get("subtype")) == light}
    assert {s.id for s in hd.stop_lines} == lights and len(lights) == 6
    for s in hd.stop_lines:
        users = {k for k, (_, members) in roads.items() if ("relation", s.id, "regulatory_element") in members}
        assert set(s.lane_ids) == users and users
        assert s.state == "unknown"
    assert hd.city == "KAR" and hd.source == "lanelet2:mapping_example.osm"
    assert hd.reference_errors() == []
    assert set(HDMap.from_json(hd.to_json()).lanes) == set(hd.lanes)


def test_projection_is_metric(raw, hd):
    nodes, ways, rels = raw
    to_m = _metres(nodes)
    for s in hd.stop_lines:
        ref = next(r for t, r, role in rels[s.id][1] if role == "ref_line")
        expected = np.array([to_m(*nodes[n]) for n in ways[ref]])
        np.testing.assert_allclose(s.line, expected, atol=0.3)
        length = np.linalg.norm(expected[-1] - expected[0])
        assert np.linalg.norm(s.line[-1] - s.line[0]) == pytest.approx(length, abs=0.05)
    xmin, ymin, xmax, ymax = hd.bounds()
    assert 500 < xmax - xmin < 10000 and 200 < ymax - ymin < 10000


def test_successors_connect_and_are_complete(raw, hd):
    _, ways, rels = raw
    edges = [(a, b) for a, lane in hd.lanes.items() for b in lane.successors]
    assert len(edges) > 300
    for a, b in edges:
        assert np.linalg.norm(hd.lanes[a].centerline[-1] - hd.lanes[b].centerline[0]) < 0.5
    # Lanelets whose bound ways share a cross-section (one end node of each bound) either follow
    # each other (in some direction) or are diverging/merging siblings, flagged as intersection.
    # A cross-section is (left way end node, nearer right way end node); B touches A when they share
    # one with the same roles, or with swapped roles when one of them is two-way (then it has a reversed lane).
    nodes = raw[0]
    to_m = _metres(nodes)
    roads = _lanelets(rels, ROAD)
    ends, two_way = {}, {k for k, (tags, _) in roads.items() if tags.get("one_way") == "no"}
    for k, (_, members) in roads.items():
        b = {role: ways[ref] for t, ref, role in members if role in ("left", "right")}
        p = {role: [to_m(*nodes[b[role][0]]), to_m(*nodes[b[role][-1]])] for role in b}
        d = {(i, j): np.linalg.norm(p["left"][i] - p["right"][j]) for i in (0, -1) for j in (0, -1)}
        j0 = 0 if d[0, 0] + d[-1, -1] <= d[0, -1] + d[-1, 0] else -1
        ends[k] = {(b["left"][0], b["right"][j0]), (b["left"][-1], b["right"][-1 - j0])}
    linked = {frozenset({a.removesuffix("-rev"), b.removesuffix("-rev")}) for a, b in edges}
    touching = 0
    for a, b in combinations(sorted(roads), 2):
        swapped = {(r, l) for l, r in ends[b]} if {a, b} & two_way else set()
        if ends[a] & (ends[b] | swapped):
            touching += 1
            assert frozenset({a, b}) in linked or (hd.lanes[a].is_intersection and hd.lanes[b].is_intersection), (a, b)
    assert touching >= len(edges) // 2
    assert 10 < sum(lane.is_intersection for lane in hd.lanes.values()) < len(hd.lanes) // 2


def test_centerline_between_bounds(raw, hd):
    nodes, ways, rels = raw
    to_m = _metres(nodes)
    off = []
    for k, (_, members) in _lanelets(rels, ROAD).items():
        lane = hd.lanes[k]
        bounds = {role: LineString([to_m(*nodes[n]) for n in ways[ref]])
                  for t, ref, role in members if role in ("left", "right")}
        pts = shapely.points(lane.centerline)
        dl, dr = shapely.distance(pts, bounds["left"]), shapely.distance(pts, bounds["right"])
        off.append(max(np.abs(dl - lane.width / 2).mean(), np.abs(dr - lane.width / 2).mean()))
        # driving direction: the left bound's vertices lie left of the centerline's local tangent
        c, left = lane.centerline, np.asarray(bounds["left"].coords)
        k_near = np.argmin(np.linalg.norm(left[:, None] - c[None], axis=2), axis=1)
        tangent = c[np.minimum(k_near + 1, len(c) - 1)] - c[np.maximum(k_near - 1, 0)]
        rel = left - c[k_near]
        side = tangent[:, 0] * rel[:, 1] - tangent[:, 1] * rel[:, 0] > 0
        assert side.mean() > 0.5, k
    assert np.median(off) < 0.3 and np.percentile(off, 90) < 1.0


def test_neighbours_share_a_bound(raw, hd):
    _, _, rels = raw
    pairs = [(k, lane.left_neighbor) for k, lane in hd.lanes.items() if lane.left_neighbor]
    assert len(pairs) > 20
    for k, n in pairs:
        assert hd.lanes[n].right_neighbor == k
        mine = {r for t, r, role in rels[k.removesuffix("-rev")][1] if role in ("left", "right")}
        theirs = {r for t, r, role in rels[n.removesuffix("-rev")][1] if role in ("left", "right")}
        assert mine & theirs
        a, b = hd.lanes[k].centerline, hd.lanes[n].centerline
        assert np.dot(a[-1] - a[0], b[-1] - b[0]) > 0


def test_errors(tmp_path):
    with pytest.raises(CmtoolError, match="no such file"):
        import_hd_map("lanelet2", tmp_path / "missing.osm")
    bad = tmp_path / "bad.osm"
    bad.write_text("<osm><node id='1' lat='1' lon='2'></osm>")
    with pytest.raises(CmtoolError, match=r"bad\.osm: malformed XML"):
        import_hd_map("lanelet2", bad)
    av2 = tmp_path / "log_map.json"
    av2.write_text('{"lane_segments": {}, "pedestrian_crossings": {}}')
    with pytest.raises(CmtoolError, match=r"log_map\.json: malformed XML"):
        import_hd_map("lanelet2", av2)
    plain = tmp_path / "plain.osm"
    plain.write_text("<osm><node id='1' lat='49' lon='8'/><way id='2'><nd ref='1'/></way></osm>")
    with pytest.raises(CmtoolError, match=r"plain\.osm: not a Lanelet2 map"):
        import_hd_map("lanelet2", plain)
    dangling = tmp_path / "dangling.osm"
    dangling.write_text(
        "<osm><node id='1' lat='49' lon='8'/><relation id='5'><member type='way' ref='9' role='left'/>"
        "<member type='way' ref='8' role='right'/><tag k='type' v='lanelet'/><tag k='subtype' v='road'/>"
        "</relation></osm>"
    )
    with pytest.raises(CmtoolError, match=r"dangling\.osm: lanelet 5: way 9 does not exist"):
        import_hd_map("lanelet2", dangling)


LOCAL_MAPS = MAP.parents[1] / "real" / "lanelet2"  # INTERACTION and SinD: local coordinates near lat/lon 0
LOCAL_FILES = sorted(LOCAL_MAPS.glob("*/*.osm")) if LOCAL_MAPS.is_dir() else []


@pytest.mark.skipif(not LOCAL_FILES, reason="shared real Lanelet2 maps not available")
@pytest.mark.parametrize("path", LOCAL_FILES, ids=lambda p: f"{p.parent.name}/{p.stem}")
def test_real_maps_local_coordinates_and_untyped_lanelets(path):
    """Every real Lanelet2 map imports at its true size in metres, also those placed near lat/lon 0, and every road
    lanelet becomes a lane: SinD's without a subtype (its connectors) and Changchun's ``main_road`` ones too."""
    root = ET.parse(path).getroot()
    nodes = {e.get("id"): (float(e.get("lat")), float(e.get("lon"))) for e in root if e.tag == "node"}
    roads = []
    for e in root:
        tags = {t.get("k"): t.get("v") for t in e.iter("tag")}
        road = tags.get("subtype", "road") in (*ROAD, "main_road")
        if e.tag == "relation" and tags.get("type") == "lanelet" and road:
            roads.append(e.get("id") if tags.get("one_way") != "no" else None)
    hd = import_hd_map("lanelet2", path)
    assert len(hd.lanes) >= len(roads) >= 10 and {r for r in roads if r} <= set(hd.lanes)
    assert hd.reference_errors() == []
    assert sum(len(lane.successors) for lane in hd.lanes.values()) > len(hd.lanes) / 2
    to_m = _metres(nodes)
    xy = np.array([to_m(*ll) for ll in nodes.values()])
    span = xy.max(axis=0) - xy.min(axis=0)  # independent: the extent of all nodes, in metres
    assert 50 < span.max() < 2000
    xmin, ymin, xmax, ymax = hd.bounds()
    assert xmax - xmin <= span[0] * 1.01 + 1 and ymax - ymin <= span[1] * 1.01 + 1
    assert max(xmax - xmin, ymax - ymin) > 0.3 * span.max()
    assert 2.5 < np.median([lane.width for lane in hd.lanes.values()]) < 10.0
