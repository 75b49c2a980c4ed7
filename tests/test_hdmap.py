import json

import numpy as np
import pytest

from cmtool.core.errors import CmtoolError
from cmtool.maps.hdmap import Crosswalk, HDMap, Lane, StopLine
from cmtool.maps.sdmap import Road, SDMap


def small_map() -> HDMap:
    hd = HDMap(city="PIT", source="test")
    hd.add_lane(Lane("a", np.array([[0.0, 0.0], [10.0, 0.0]]), width=3.2, road_id="r1"))
    hd.add_lane(Lane("b", np.array([[10.0, 0.0], [15.0, 5.0]]), is_intersection=True, intersection_id="i1"))
    hd.add_lane(Lane("c", np.array([[15.0, 5.0], [15.0, 20.0]]), road_id="r2"))
    hd.link("a", "b")
    hd.link("b", "c")
    hd.stop_lines.append(StopLine("s", np.array([[10.0, -1.6], [10.0, 1.6]]), "red", ["b"]))
    hd.crosswalks.append(Crosswalk("x", np.array([[11.0, -2.0], [13.0, -2.0], [13.0, 2.0], [11.0, 2.0]])))
    return hd


def test_hdmap_roundtrip(tmp_path):
    hd = small_map()
    assert hd.reference_errors() == []
    hd.save(tmp_path / "m.json")
    back = HDMap.load(tmp_path / "m.json")
    assert list(back.lanes) == ["a", "b", "c"]
    assert back.lanes["a"].successors == ["b"] and back.lanes["c"].predecessors == ["b"]
    assert back.lanes["b"].is_intersection and back.lanes["b"].intersection_id == "i1"
    np.testing.assert_allclose(back.lanes["b"].centerline, hd.lanes["b"].centerline)
    assert back.stop_lines[0].state == "red" and back.stop_lines[0].lane_ids == ["b"]
    assert back.crosswalks[0].polygon.shape == (4, 2)
    assert back.bounds() == (0.0, 0.0, 15.0, 20.0)


def test_reference_errors_name_the_lane():
    hd = small_map()
    hd.lanes["a"].successors.append("zzz")
    hd.lanes["c"].predecessors.remove("b")
    errors = hd.reference_errors()
    assert any("successor 'zzz' does not exist" in e for e in errors)
    assert any("lane b: successor c does not list it as predecessor" in e for e in errors)


@pytest.mark.parametrize(
    "mutate, message",
    [
        (lambda o: o["lanes"][1].update(width="wide"), "lanes[1].width: expected a number"),
        (lambda o: o["lanes"][0].update(centerline=[[0, 0]]), "lanes[0].centerline: expected at least 2 points"),
        (lambda o: o["lanes"][0]["centerline"].__setitem__(0, [float("nan"), 0]), "lanes[0].centerline: polyline has NaN"),
        (lambda o: o["lanes"][2].update(lane_type="tram"), "lanes[2].lane_type: expected one of"),
        (lambda o: o["lanes"][0].pop("id"), "lanes[0].id: missing"),
        (lambda o: o["lanes"][0].update(successors=["nope"]), "successor 'nope' does not exist"),
        (lambda o: o["stop_lines"][0].update(state="blue"), "stop_lines[0].state"),
        (lambda o: o.update(format="cmtool.sdmap"), "format: expected 'cmtool.hdmap'"),
        (lambda o: o.update(drives_on="middle"), "drives_on"),
    ],
)
def test_hdmap_validation_names_field(mutate, message):
    obj = json.loads(json.dumps(small_map().to_json()))
    mutate(obj)
    with pytest.raises(CmtoolError, match="m.json: .*" + message.replace("[", r"\[").replace("]", r"\]").replace(".", r"\.")):
        HDMap.from_json(obj, where="m.json")


def test_load_errors(tmp_path):
    with pytest.raises(CmtoolError, match="no such file"):
        HDMap.load(tmp_path / "missing.json")
    bad = tmp_path / "bad.json"
    bad.write_text('{"format": "cmtool.hdmap",\n "lanes": [}')
    with pytest.raises(CmtoolError, match="malformed JSON at line 2"):
        HDMap.load(bad)


def test_sdmap_roundtrip_and_validation(tmp_path):
    sd = SDMap(city="BOS", roads=[Road("r1", np.array([[0.0, 0.0], [50.0, 0.0], [80.0, 10.0]]), "primary", 4, 0),
                                 Road("r2", np.array([[0.0, 0.0], [0.0, -40.0]]), "residential", None, -1)])
    sd.save(tmp_path / "sd.json")
    back = SDMap.load(tmp_path / "sd.json")
    assert [r.id for r in back.roads] == ["r1", "r2"]
    assert back.roads[0].lanes == 4 and back.roads[1].lanes is None
    np.testing.assert_allclose(back.roads[1].travel_polyline()[0], [0.0, -40.0])
    obj = sd.to_json()
    obj["roads"][1]["oneway"] = 2
    with pytest.raises(CmtoolError, match=r"roads\[1\]\.oneway"):
        SDMap.from_json(obj)
    obj["roads"][1]["oneway"] = 0
    obj["roads"][0]["road_class"] = "footway"
    with pytest.raises(CmtoolError, match=r"roads\[0\]\.road_class"):
        SDMap.from_json(obj)
