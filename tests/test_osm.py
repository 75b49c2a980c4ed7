from pathlib import Path

import numpy as np
import pytest

from cmtool.core.errors import CmtoolError
from cmtool.formats.osm import parse_lanes, parse_oneway, read_osm, road_class_of

FIXTURE = Path(__file__).resolve().parent / "fixtures" / "small.osm"


def check_small(sd):
    roads = {r.id: r for r in sd.roads}
    assert sorted(roads) == ["w10", "w11", "w13", "w14"]  # footway 12 and building 15 skipped
    main = roads["w10"]
    assert (main.road_class, main.lanes, main.oneway) == ("primary", 4, 0)
    # 0.001 degrees of latitude is about 111 m, northwards (+y); same longitude, so x does not move
    steps = np.diff(main.polyline, axis=0)
    np.testing.assert_allclose(steps[:, 1], 111.0, atol=0.5)
    np.testing.assert_allclose(steps[:, 0], 0.0, atol=0.05)
    res = roads["w11"]
    assert (res.road_class, res.lanes, res.oneway) == ("residential", None, -1)
    # travel runs against the way: from node 4 (east) to node 3 (west)
    assert res.travel_polyline()[0, 0] > res.travel_polyline()[-1, 0]
    # 0.001 degrees of longitude at 40.44 N is about 111 km * cos(40.44) = 84.8 m
    assert abs(res.polyline[1, 0] - res.polyline[0, 0]) == pytest.approx(84.8, abs=0.5)
    link = roads["w13"]  # node 99 is missing: the way keeps nodes 6, 7 (node 4 alone is dropped)
    assert (link.road_class, link.lanes, link.oneway) == ("secondary", None, 0)
    assert len(link.polyline) == 2
    assert roads["w14"].oneway == 1 and roads["w14"].lanes == 3  # motorways are one-way by default
    centre = np.concatenate([r.polyline for r in sd.roads]).mean(axis=0)
    assert np.all(np.abs(centre) < 150.0)  # projected around the data
    assert sd.meta["lat0"] == pytest.approx(40.4418, abs=1e-3)


def test_read_osm_xml():
    check_small(read_osm(FIXTURE))


def test_read_osm_pbf(tmp_path):
    osmium = pytest.importorskip("osmium")
    pbf = tmp_path / "small.osm.pbf"
    with osmium.SimpleWriter(str(pbf)) as writer:
        for obj in osmium.FileProcessor(str(FIXTURE)):
            writer.add(obj)
    check_small(read_osm(pbf))


def test_pbf_without_osmium_gives_install_hint(tmp_path, monkeypatch):
    import builtins

    real_import = builtins.__import__

    def no_osmium(name, *args, **kwargs):
        if name == "osmium":
            raise ImportError("no osmium")
        return real_import(name, *args, **kwargs)

    pbf = tmp_path / "x.osm.pbf"
    pbf.write_bytes(b"\0")
    monkeypatch.setattr(builtins, "__import__", no_osmium)
    with pytest.raises(CmtoolError, match=r"pip install osmium"):
        read_osm(pbf)


def test_malicious_xml_is_refused(tmp_path):
    bomb = tmp_path / "bomb.osm"
    bomb.write_text('<?xml version="1.0"?>\n<!DOCTYPE osm [<!ENTITY a "aaaaaaaaaa"><!ENTITY b "&a;&a;&a;&a;">]>\n'
                    '<osm><node id="1" lat="0" lon="0"><tag k="name" v="&b;"/></node></osm>\n')
    with pytest.raises(CmtoolError, match="bomb.osm"):
        read_osm(bomb)


@pytest.mark.parametrize("content, message", [
    (None, "no such file"),
    ("<osm><node id='1' lat='north' lon='0'/></osm>", "lacks a valid id"),
    ("<osm><way id='1'>", "malformed XML"),
])
def test_bad_files_raise_cmtool_error(tmp_path, content, message):
    path = tmp_path / "bad.osm"
    if content is not None:
        path.write_text(content)
    with pytest.raises(CmtoolError, match=message):
        read_osm(path)


def test_bad_pbf_and_wrong_suffix(tmp_path):
    pytest.importorskip("osmium")
    junk = tmp_path / "junk.osm.pbf"
    junk.write_bytes(b"this is not a pbf file at all")
    with pytest.raises(CmtoolError, match="junk.osm.pbf"):
        read_osm(junk)
    other = tmp_path / "map.geojson"
    other.write_text("{}")
    with pytest.raises(CmtoolError, match="expected an OpenStreetMap"):
        read_osm(other)


def test_file_without_roads_is_refused(tmp_path):
    path = tmp_path / "empty.osm"
    path.write_text("<osm version='0.6'><node id='1' lat='1' lon='2'/></osm>")
    with pytest.raises(CmtoolError, match="no drivable roads"):
        read_osm(path)
    lanelet2 = tmp_path / "lanelets.osm"
    lanelet2.write_text("<osm version='0.6'><node id='1' lat='1' lon='2'/><node id='2' lat='1' lon='2.001'/>"
                        "<way id='3'><nd ref='1'/><nd ref='2'/><tag k='type' v='line_thin'/></way></osm>")
    with pytest.raises(CmtoolError, match="Lanelet2 map"):
        read_osm(lanelet2)


def test_tag_parsing():
    assert [road_class_of(h) for h in ("motorway_link", "footway", "living_street", None, "trunk")] == [
        "motorway", None, "residential", None, "trunk"]
    values = ("3", " 2 ", "2;3", "many", None, "0", "40")
    assert [parse_lanes(v) for v in values] == [3, 2, None, None, None, None, None]
    assert [parse_oneway({"oneway": v}) for v in ("yes", "True", "1", "-1", "reverse", "no", "maybe")] == [
        1, 1, 1, -1, -1, 0, 0]
    assert parse_oneway({"highway": "motorway"}) == 1
    assert parse_oneway({"highway": "motorway", "oneway": "no"}) == 0
    assert parse_oneway({"highway": "primary", "junction": "roundabout"}) == 1


def test_written_osm_reads_back_as_the_same_roads(tmp_path):
    from cmtool.data.sd_derive import derive_sd
    from cmtool.data.synth import generate_city
    from cmtool.formats.osm import write_osm

    sd = derive_sd(generate_city("BOS", seed=3, extent=300.0))
    write_osm(sd, tmp_path / "town.osm", 42.355, -71.065)
    back = read_osm(tmp_path / "town.osm")
    assert len(back.roads) == len(sd.roads)
    for a, b in zip(sd.roads, back.roads):
        assert (a.road_class, a.lanes, a.oneway) == (b.road_class, b.lanes, b.oneway)
        assert len(a.polyline) == len(b.polyline)
    # the same shapes up to the origin: read_osm centres its projection on the nodes' mean
    pa, pb = np.concatenate([r.polyline for r in sd.roads]), np.concatenate([r.polyline for r in back.roads])
    np.testing.assert_allclose(pb - pb[0], pa - pa[0], atol=0.01)
    # roads that met at one point share a node in the file, so the road graph stays connected
    text = (tmp_path / "town.osm").read_text()
    assert text.count("<node ") < sum(len(r.polyline) for r in sd.roads)


def test_a_file_of_another_kind_is_named(tmp_path):
    """Issue 58: a picture or an HD map given where an OpenStreetMap file is expected is named as what it is."""
    from cmtool.data.synth import generate_city

    (tmp_path / "sd.png").write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(32))
    generate_city("LAV", seed=0, extent=200.0).save(tmp_path / "city.json")
    with pytest.raises(CmtoolError, match=r"sd.png is a picture \(PNG\); expected an OpenStreetMap"):
        read_osm(tmp_path / "sd.png")
    with pytest.raises(CmtoolError, match=r"city.json is an HD map \(JSON\); expected an OpenStreetMap"):
        read_osm(tmp_path / "city.json")
