"""The rule-based lane layout (cmtool.data.rules) and `cmtool baseline rules`."""

import json

import numpy as np
import pytest

from cmtool.core.geometry import unit
from cmtool.data.rules import LANE_WIDTH_M, LANES, lane_counts, rule_layout
from cmtool.maps.sdmap import Road, SDMap
from cmtool.metrics.validity import check
from tests.conftest import REPO, in_process


def road(rid, points, **kw):
    return Road(rid, np.asarray(points, np.float64), **kw)


def side_of(lane, line) -> float:
    """Mean signed distance of a lane to the left of a straight reference line (first to last point)."""
    a, b = np.asarray(line[0], float), np.asarray(line[-1], float)
    d = unit(b - a)
    rel = lane.centerline - a
    return float(np.mean(d[0] * rel[:, 1] - d[1] * rel[:, 0]))


def heading(lane) -> np.ndarray:
    return unit(lane.centerline[-1] - lane.centerline[0])


def test_lane_counts_from_tags_and_class_defaults():
    assert lane_counts(road("a", [[0, 0], [1, 0]], lanes=4)) == (2, 2)
    assert lane_counts(road("a", [[0, 0], [1, 0]], lanes=3)) == (2, 1)
    assert lane_counts(road("a", [[0, 0], [1, 0]], lanes=1)) == (1, 1)  # an unmarked two-way street
    assert lane_counts(road("a", [[0, 0], [1, 0]], lanes=3, oneway=1)) == (3, 0)
    assert lane_counts(road("a", [[0, 0], [1, 0]], road_class="primary")) == (LANES["primary"][0] // 2,) * 2
    assert lane_counts(road("a", [[0, 0], [1, 0]], road_class="residential", oneway=-1)) == (1, 0)


@pytest.mark.parametrize("side", ["right", "left"])
def test_a_two_way_road_drives_on_its_side(side):
    line = [[0, 0], [100, 0]]
    hd = rule_layout(SDMap(roads=[road("r", line, lanes=4, road_class="secondary")]), side)
    assert len(hd.lanes) == 4
    for lane in hd.lanes.values():
        along = heading(lane)[0] > 0
        offset = side_of(lane, line)
        # right-hand traffic: lanes along the polyline lie to its right (negative), the others to its left
        assert (offset < 0) == (along == (side == "right"))
        assert 0.4 * LANE_WIDTH_M["secondary"] < abs(offset) < 2.1 * LANE_WIDTH_M["secondary"]
    # neighbours: lane changes between the two lanes of each direction, none across the centreline
    pairs = {(l.id, l.left_neighbor) for l in hd.lanes.values() if l.left_neighbor}
    assert len(pairs) == 2 and all(hd.lanes[a].id[:-1] == hd.lanes[b].id[:-1] for a, b in pairs)


def test_one_way_roads_run_their_way_and_a_divided_road_is_two():
    hd = rule_layout(SDMap(roads=[road("a", [[0, 0], [100, 0]], oneway=-1, lanes=2),
                                  road("b", [[0, 20], [100, 20]], oneway=1, lanes=2)]))
    by_side = {}
    for lane in hd.lanes.values():
        by_side.setdefault(lane.centerline[0][1] > 10, []).append(heading(lane)[0])
    assert sorted(by_side) == [False, True]
    assert all(h < -0.99 for h in by_side[False]) and all(h > 0.99 for h in by_side[True])
    assert all(abs(side_of(l, [[0, 0], [100, 0]])) < LANE_WIDTH_M["residential"] for l in hd.lanes.values()
               if l.centerline[0][1] < 10)  # centred on a one-way road


def test_the_layout_channels_draw_each_lane_with_its_heading():
    from cmtool.data.layouts import LAYOUT_CHANNELS, control_raster, cropped_layouts, layout_raster
    from cmtool.data.scene import Pose

    sd = SDMap(roads=[road("a", [[-100, 0], [100, 0]], oneway=-1, lanes=2)])  # two lanes running towards -x
    (scene,) = cropped_layouts([(sd, Pose(0.0, 0.0, 0.0), "right")], "rules")
    raster = layout_raster(scene)
    assert raster.shape == (128, 128, LAYOUT_CHANNELS) and raster.dtype == np.uint8
    drawn = raster.any(-1)
    rows, cols = np.nonzero(drawn)
    assert set(rows) == set(range(128))  # the lanes cross the whole frame, front to back (x is up)
    assert np.all(np.abs(cols - 63.5) < 4.0 / 0.5)  # within 4 m of the road, which runs through the centre
    assert np.all(raster[drawn] == [0, 128])  # heading pi: cos -1 -> 0, sin 0 -> 128 (of 255)
    assert len(np.unique(cols)) >= 4  # two lanes side by side, 2 px (1 m) each
    image = control_raster(np.full((128, 128, 3), 7, np.uint8), None)  # no layout (an SD picture): zeros
    assert image.shape == (128, 128, 5) and not image[..., 3:].any() and (image[..., :3] == 7).all()


def test_a_crossing_gets_connectors_and_no_u_turns():
    sd = SDMap(roads=[road("ew", [[-100, 0], [0, 0], [100, 0]], lanes=2),
                      road("ns", [[0, -100], [0, 0], [0, 100]], lanes=4, road_class="secondary")])
    hd = rule_layout(sd)
    connectors = [l for l in hd.lanes.values() if l.is_intersection]
    roads = [l for l in hd.lanes.values() if not l.is_intersection]
    assert len(roads) == 2 * 2 + 4 * 2
    # ns: 2 lanes each way straight on (2 pairs per arm), turns from its near (right) and far (left) lane;
    # ew: 1 lane each way, straight + right + left
    assert len(connectors) == 2 * (2 + 1 + 1) + 2 * (1 + 1 + 1)
    for c in connectors:
        (a,), (b,) = c.predecessors, c.successors
        assert np.linalg.norm(hd.lanes[a].centerline[-1] - c.centerline[0]) < 1e-9
        assert np.linalg.norm(hd.lanes[b].centerline[0] - c.centerline[-1]) < 1e-9
        assert float(heading(hd.lanes[a]) @ heading(hd.lanes[b])) > -0.5  # no U-turn
        assert np.linalg.norm(c.centerline[0]) > 4.0  # lanes stop short of the junction
    # right turns leave from the rightmost lane: from the northbound ns lanes into eastbound ew
    north = [l for l in roads if l.road_id and heading(l)[1] > 0.99 and l.centerline[-1][1] < 0]
    rightmost = max(north, key=lambda l: l.centerline[0][0])
    turns_east = [hd.lanes[s] for s in rightmost.successors if heading(hd.lanes[hd.lanes[s].successors[0]])[0] > 0.99]
    assert len(turns_east) == 1
    assert check(_graph(hd)).score > 0.9


def test_ends_near_a_road_meet_it_and_bridges_do_not():
    t = rule_layout(SDMap(roads=[road("main", [[-80, 0], [80, 0]]), road("side", [[0, 2.0], [0, 80]])]))
    assert any(l.is_intersection for l in t.lanes.values())  # the side road stopped 2 m short: a T-junction
    bridge = rule_layout(SDMap(roads=[road("under", [[-80, 0], [80, 0]]),
                                      road("over", [[0, -80], [0, 80]], layer=1)]))
    assert not any(l.is_intersection for l in bridge.lanes.values()) and len(bridge.lanes) == 4


def test_a_road_split_into_two_ways_runs_on():
    hd = rule_layout(SDMap(roads=[road("a", [[0, 0], [50, 0]], lanes=2), road("b", [[50, 0], [100, 5]], lanes=2)]))
    assert not any(l.is_intersection for l in hd.lanes.values())
    linked = [(a.id, s) for a in hd.lanes.values() for s in a.successors]
    assert len(linked) == 2 and all(a[:a.index("_")] != b[:b.index("_")] for a, b in linked)


def _graph(hd):
    from cmtool.data.scene import Pose, SceneCropper

    return SceneCropper(hd).extract(Pose(0.0, 0.0, 0.0)).to_lanegraph()


def test_baseline_rules_cli_frames_and_whole_map(tmp_path, capsys):
    from cmtool.data.synth import generate_city

    city = tmp_path / "lav.json"
    generate_city("LAV", seed=1, extent=400.0).save(city)
    code, out, err = in_process(capsys, "baseline", "rules", "--from-hd", city, "--whole", tmp_path / "whole.json")
    assert code == 0, err
    whole = json.loads((tmp_path / "whole.json").read_text())
    assert whole["format"] == "cmtool.hdmap" and len(whole["lanes"]) > 20 and whole["source"].startswith("rules:")
    assert "SD roads" in out and not (tmp_path / "rules").exists()  # no frame asked for: the whole map alone
    code, out, err = in_process(capsys, "baseline", "rules", "--from-hd", city, "--out", tmp_path / "rules")
    assert code == 0, err
    (name,) = [p.stem for p in (tmp_path / "rules").glob("*.json") if not p.name.endswith(".gt.json")]
    graph = json.loads((tmp_path / "rules" / f"{name}.json").read_text())
    assert graph["meta"]["method"] == "rules" and graph["lanes"] and graph["meta"]["validity"] > 0.5
    assert (tmp_path / "rules" / f"{name}.gt.json").is_file() and (tmp_path / "rules" / f"{name}.png").is_file()
    assert "validity" in out and "rules lane graph" in out
    code, _, err = in_process(capsys, "baseline", "rules", "--osm", tmp_path / "x.osm")
    assert code == 1 and "--center" in err
    code, _, err = in_process(capsys, "baseline", "rules", "--from-hd", city, "--osm", city)
    assert code == 1 and "one SD input" in err


NET = """<net version="1.20">
  <location netOffset="0.00,0.00" convBoundary="0,0,100,10" origBoundary="0,0,1,1" projParameter="!"/>
  <edge id=":J_0" function="internal">
    <lane id=":J_0_0" index="0" speed="10" length="9" shape="45,-1.6 54,-1.6"/>
  </edge>
  <edge id="a" from="S" to="J" priority="1">
    <lane id="a_0" index="0" speed="10" length="45" shape="0,-1.6 45,-1.6"/>
    <lane id="a_1" index="1" speed="10" length="45" allow="pedestrian" shape="0,-4 45,-4"/>
  </edge>
  <edge id="b" from="J" to="E" priority="1">
    <lane id="b_0" index="0" speed="10" length="46" shape="54,-1.6 100,-1.6"/>
  </edge>
  <connection from="a" to="b" fromLane="0" toLane="0" via=":J_0_0" dir="s" state="M"/>
  <connection from=":J_0" to="b" fromLane="0" toLane="0" dir="s" state="M"/>
</net>
"""


def test_a_sumo_network_reads_as_an_hd_map(tmp_path):
    from cmtool.formats.sumo import read_sumo_net

    (tmp_path / "n.net.xml").write_text(NET)
    hd = read_sumo_net(tmp_path / "n.net.xml")
    assert sorted(hd.lanes) == [":J_0_0", "a_0", "b_0"]  # the footway is no car lane
    assert hd.lanes["a_0"].successors == [":J_0_0"] and hd.lanes[":J_0_0"].successors == ["b_0"]
    assert hd.lanes[":J_0_0"].is_intersection and hd.lanes[":J_0_0"].intersection_id == "J"
    np.testing.assert_allclose(hd.lanes["b_0"].centerline, [[54, -1.6], [100, -1.6]])


def test_netconvert_lays_out_the_same_roads():
    from cmtool.formats.sumo import netconvert_layout, netconvert_path

    if netconvert_path() is None:
        pytest.skip("SUMO's netconvert is not installed (pip install eclipse-sumo)")
    sd = SDMap(roads=[road("ew", [[-100, 0], [0, 0], [100, 0]], lanes=2),
                      road("ns", [[0, -100], [0, 0], [0, 100]], lanes=2, oneway=1)])
    hd = netconvert_layout(sd)
    roads = [l for l in hd.lanes.values() if not l.is_intersection]
    assert len(roads) == 4 + 4 and any(l.is_intersection for l in hd.lanes.values())  # split at the junction
    north = [l for l in roads if abs(l.centerline[:, 0]).max() < 5]
    assert north and all(heading(l)[1] > 0.99 for l in north)  # the one-way road runs one way, in our metres
    east = [l for l in roads if heading(l)[0] > 0.99]
    assert east and all(side_of(l, [[-100, 0], [100, 0]]) < 0 for l in east)  # right-hand traffic


def test_sample_starts_from_the_rule_layout(sampling_ckpt, tmp_path, capsys):
    from cmtool.data.synth import generate_city

    city = tmp_path / "pit.json"
    generate_city("PIT", seed=2, extent=400.0).save(city)
    args = ("sample", "--from-hd", city, "--steps", 4, "--no-log", "--quiet")
    code, out, err = in_process(capsys, *args, "--ckpt", sampling_ckpt["controlmap"], "--init", "rules",
                                "--strength", 0.3, "--out", tmp_path / "sde")
    assert code == 0, err
    (name,) = [p for p in (tmp_path / "sde").glob("*.json") if not p.name.endswith(".gt.json")]
    meta = json.loads(name.read_text())["meta"]
    assert meta["init"] == "rules" and meta["strength"] == 0.3
    code, _, err = in_process(capsys, *args, "--init", "rules", "--out", tmp_path / "x")  # the shipped weights encode
    assert code == 0, err
    (name,) = [p for p in (tmp_path / "x").glob("*.json") if not p.name.endswith(".gt.json")]
    assert json.loads(name.read_text())["meta"]["init"] == "rules"
    code, _, err = in_process(capsys, *args, "--encoder", sampling_ckpt["rvae"], "--out", tmp_path / "y")
    assert code == 1 and "--encoder goes with --init" in err
    code, _, err = in_process(capsys, "sample", "--sd", REPO / "sample_data" / "sd_sgp.png", "--init", "rules",
                              "--ckpt", sampling_ckpt["controlmap"], "--no-log", "--out", tmp_path / "z")
    assert code == 0, err  # a picture's roads are traced: the rules lay lanes out on them
    assert json.loads((tmp_path / "z" / "sd_sgp.json").read_text())["meta"]["init"] == "rules"


def test_sample_reports_the_models_own_maps_beside_the_guaranteed_ones(sampling_ckpt, tmp_path, capsys):
    from cmtool.data.synth import generate_city

    city = tmp_path / "sgp.json"
    generate_city("SGP", seed=3, extent=400.0).save(city)
    args = ("sample", "--ckpt", sampling_ckpt["controlmap"], "--from-hd", city, "--steps", 3, "--no-log", "--quiet")
    code, out, err = in_process(capsys, *args, "--out", tmp_path / "final")
    assert code == 0, err
    (name,) = [p for p in (tmp_path / "final").glob("*.json") if not p.name.endswith(".gt.json")]
    meta = json.loads(name.read_text())["meta"]
    assert set(meta["composed"]) == {"lanes_from", "movements", "dropped"} and 0 <= meta["raw"]["validity"] <= 1
    code, out, err = in_process(capsys, *args, "--raw", "--out", tmp_path / "raw")
    assert code == 0, err
    meta = json.loads((tmp_path / "raw" / name.name).read_text())["meta"]
    assert "composed" not in meta and "raw" not in meta
