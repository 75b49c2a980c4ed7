import cv2
import numpy as np
import pytest

from cmtool.core.errors import CmtoolError
from cmtool.data.sd_raster import (
    ENCODINGS, SDRasterizer, as_encoding, convert_sd_image, decode_sd, direction_value, is_sd_raster, rasterize_sd,
    sd_raster_from_image,
)
from cmtool.maps.sdmap import Road, SDMap


def road(points, lanes=None, oneway=0, road_class="residential", link=False):
    return Road("r", np.asarray(points, dtype=float), road_class, lanes, oneway, link)


def test_road_straight_ahead():
    # ego at (10, 5) heading north; the road runs north through the ego position
    sd = SDMap(roads=[road([[10, -100], [10, 100]], lanes=3)])
    r = rasterize_sd(sd, 10.0, 5.0, np.pi / 2)
    assert r.shape == (128, 128, 3) and r.dtype == np.uint8
    cols = np.flatnonzero(r[..., 0].any(axis=0))
    assert set(cols) >= {63, 64} and cols.min() >= 61 and cols.max() <= 66  # centre columns
    assert r[:, 63, 0].all() and r[:, 64, 0].all()  # over the whole height
    assert set(np.unique(r[..., 0])) == {0, 144}  # R: a residential road
    assert set(np.unique(r[r[..., 0] > 0][:, 1])) == {96}  # G = 32 * lanes
    assert not r[..., 2].any()  # two-way: no direction


def test_oneway_forward_direction_and_lane_cap():
    sd = SDMap(roads=[road([[0, 0], [0, 1], [0, 50]], lanes=9, oneway=1)])
    r = rasterize_sd(sd, 0.0, 0.0, np.pi / 2)  # travel heading = ego heading -> theta 0
    on = r[..., 0] > 0
    assert set(np.unique(r[on][:, 2])) <= {127, 128}
    assert set(np.unique(r[on][:, 1])) == {224}  # 32 * min(lanes, 7)
    assert on[:64].sum() > 100 and on[70:].sum() == 0  # only ahead of ego (top half)
    reverse = rasterize_sd(SDMap(roads=[road([[0, 0], [0, 50]], oneway=-1)]), 0.0, 0.0, np.pi / 2)
    assert set(np.unique(reverse[reverse[..., 0] > 0][:, 2])) <= {1, 255}  # travelling backwards
    assert not reverse[..., 1].any()  # lane count unknown


def test_orientation_left_and_ahead():
    # ego at the origin heading east (+x world), so world +y is the ego's left
    left = rasterize_sd(SDMap(roads=[road([[-40, 20], [40, 20]])]), 0.0, 0.0, 0.0)
    cols = np.flatnonzero(left[..., 0].any(axis=0))
    assert cols.max() < 64 and abs(cols.mean() - 23.5) < 1.0  # y = +20 -> column (32 - 20) / 0.5 - 0.5
    assert left[..., 0].any(axis=1).all()  # parallel to travel: a vertical band over all rows
    ahead = rasterize_sd(SDMap(roads=[road([[20, -40], [20, 40]])]), 0.0, 0.0, 0.0)
    rows = np.flatnonzero(ahead[..., 0].any(axis=1))
    assert rows.max() < 64 and abs(rows.mean() - 23.5) < 1.0  # x = +20 -> top half
    assert ahead[..., 0].any(axis=0).all()


def test_the_road_class_is_in_r_and_weights_of_encoding_1_see_road_presence():
    """A primary and a residential road without lane tags give different rasters (R by class, links 8 less); weights
    of encoding 1 see both as the plain road presence they were trained on, and a drawn road reads as unknown."""
    line = [[0, -50], [0, 50]]
    primary, residential = (rasterize_sd(SDMap(roads=[road(line, road_class=c)]), 0.0, 0.0, np.pi / 2)
                            for c in ("primary", "residential"))
    assert not np.array_equal(primary, residential)
    assert set(np.unique(primary[..., 0])) == {0, 208} and set(np.unique(residential[..., 0])) == {0, 144}
    ramp = rasterize_sd(SDMap(roads=[road(line, road_class="motorway", link=True, oneway=1)]), 0.0, 0.0, np.pi / 2)
    assert set(np.unique(ramp[..., 0])) == {0, 232}
    dec = decode_sd(ramp)
    assert set(dec["road_class"][dec["road"]]) == {"motorway"} and dec["link"][dec["road"]].all()
    assert set(dec["road_class"][~dec["road"]]) == {""}
    old = as_encoding(np.stack([primary, residential]), 1)
    assert np.array_equal(old[0], old[1]) and set(np.unique(old[..., 0])) == {0, 255}
    assert np.array_equal(as_encoding(primary, 2), primary) and set(ENCODINGS) == {1, 2}
    assert is_sd_raster(primary)  # a class alone makes an SD raster (no tags: G and B 0); R alone is a drawing
    drawn = sd_raster_from_image(np.where(residential[..., 0] > 0, 255, 0).astype(np.uint8))
    assert set(np.unique(drawn[..., 0])) == {0, 255} and set(decode_sd(drawn)["road_class"].ravel()) == {""}
    with pytest.raises(CmtoolError, match="encoding 3"):
        as_encoding(primary, 3)


def test_direction_encoding_values():
    assert direction_value(0.0) in (127, 128)
    assert direction_value(-np.pi) == 1 and direction_value(np.pi - 1e-9) == 255
    assert direction_value(np.pi / 2) == 191  # to the left
    # a one-way road heading to the ego's left: B encodes +pi/2
    r = rasterize_sd(SDMap(roads=[road([[10, -30], [10, 30]], oneway=1)]), 0.0, 0.0, 0.0)
    assert set(np.unique(r[r[..., 0] > 0][:, 2])) == {191}
    dec = decode_sd(r)
    assert np.nanmax(np.abs(dec["heading"] - np.pi / 2)) < 0.02


def test_oneway_drawn_over_twoway():
    sd = SDMap(roads=[road([[0, -50], [0, 50]], oneway=1, lanes=1), road([[-50, 0], [50, 0]], lanes=4)])
    r = rasterize_sd(sd, 0.0, 0.0, np.pi / 2)
    assert r[64, 64, 2] > 0 and r[64, 64, 1] == 32  # the crossing keeps the one-way road's values
    assert r[64, 10, 1] == 128 and r[64, 10, 2] == 0


def test_one_rasterizer_draws_every_pose_as_rasterize_sd():
    curve = [[50 * np.cos(t), 50 * np.sin(t)] for t in np.linspace(0, np.pi, 40)]
    sd = SDMap(roads=[road(curve, oneway=1, lanes=2), road([[-60, 10], [60, 10]], lanes=4),
                      road([[0, -60], [0, 60]], oneway=-1), road([[500, 500], [600, 500]])])
    draw = SDRasterizer(sd)
    for x, y, yaw in ((0.0, 0.0, 0.0), (40.0, 20.0, 1.0), (-30.0, 5.0, -2.5), (300.0, 300.0, 0.0)):
        assert np.array_equal(draw(x, y, yaw), rasterize_sd(sd, x, y, yaw))
    assert np.array_equal(draw(0.0, 0.0, 0.3, frame_m=200.0, size=512), rasterize_sd(sd, 0.0, 0.0, 0.3, 200.0, 512))


def test_far_roads_and_frame_size():
    sd = SDMap(roads=[road([[500, 500], [600, 500]])])
    assert not rasterize_sd(sd, 0.0, 0.0, 0.0).any()
    big = rasterize_sd(SDMap(roads=[road([[0, -50], [0, 50]])]), 0.0, 0.0, 0.0, frame_m=32.0, size=64)
    assert big.shape == (64, 64, 3) and big[..., 0].any()


def test_image_from_black_white_png(tmp_path):
    drawing = np.zeros((400, 300), np.uint8)
    cv2.line(drawing, (150, 0), (150, 399), 255, 20)  # a vertical road in the middle
    cv2.line(drawing, (0, 40), (299, 40), 255, 20)  # a crossing road near the top
    path = tmp_path / "roads.png"
    cv2.imwrite(str(path), drawing)
    r = sd_raster_from_image(path)
    assert r.shape == (128, 128, 3) and r.dtype == np.uint8
    assert set(np.unique(r[..., 0])) == {0, 255} and not r[..., 1:].any()
    assert r[64, 64, 0] == 255 and r[100, 10, 0] == 0 and r[13, 20, 0] == 255
    jpg = tmp_path / "roads.jpg"
    cv2.imwrite(str(jpg), cv2.cvtColor(drawing, cv2.COLOR_GRAY2BGR))
    assert (sd_raster_from_image(jpg)[..., 0] != r[..., 0]).mean() < 0.01
    assert np.array_equal(sd_raster_from_image(drawing), r)  # arrays work too


def test_image_dark_roads_on_light_paper_with_thin_strokes():
    paper = np.full((1024, 1024), 255, np.uint8)
    cv2.line(paper, (512, 0), (512, 1023), 0, 3)  # a thin dark road, 3 px of 1024
    r = sd_raster_from_image(paper)
    assert r[64, 64, 0] == 255 and r[64, 20, 0] == 0
    assert 1 <= (r[64, :, 0] > 0).sum() <= 2  # one road column, not the paper
    assert not sd_raster_from_image(np.full((50, 50), 200, np.uint8)).any()  # blank page: no roads


def test_sd_raster_passes_through(tmp_path):
    raster = rasterize_sd(SDMap(roads=[road([[0, -50], [0, 50]], lanes=2, oneway=1)]), 0.0, 0.0, 0.3)
    assert np.array_equal(sd_raster_from_image(raster), raster)
    path = tmp_path / "sd.png"
    cv2.imwrite(str(path), cv2.cvtColor(raster, cv2.COLOR_RGB2BGR))  # saved the cv2 way (BGR)
    assert np.array_equal(sd_raster_from_image(path), raster)


def test_unreadable_images(tmp_path):
    bad = tmp_path / "bad.png"
    bad.write_bytes(b"not a png")
    for path in (bad, tmp_path / "missing.png"):
        with pytest.raises(CmtoolError, match=path.name):
            sd_raster_from_image(path)
    with pytest.raises(CmtoolError, match="shape"):
        sd_raster_from_image(np.zeros((10, 10, 2), np.uint8))


def test_transparent_sixteen_bit_and_array_pictures(tmp_path):
    rgba = np.zeros((200, 200, 4), np.uint8)
    cv2.line(rgba, (100, 0), (100, 199), (0, 0, 0, 255), 10)  # black strokes on a transparent page
    cv2.imwrite(str(tmp_path / "t.png"), rgba)
    r = sd_raster_from_image(tmp_path / "t.png")
    assert r[64, 64, 0] == 255 and r[64, 10, 0] == 0
    deep = rgba[..., 3].astype(np.uint16) * 257  # the same strokes, white on black in 16 bits
    cv2.imwrite(str(tmp_path / "d.png"), deep)
    assert np.array_equal(sd_raster_from_image(tmp_path / "d.png"), r)
    np.save(tmp_path / "a.npy", deep > 0)
    assert np.array_equal(sd_raster_from_image(tmp_path / "a.npy"), r)


def test_sd_rasters_of_other_sizes_are_resampled_with_a_note():
    raster = rasterize_sd(SDMap(roads=[road([[0, -50], [0, 50]], lanes=2, oneway=1)]), 0.0, 0.0, 0.3)
    big = cv2.resize(raster, (256, 256), interpolation=cv2.INTER_NEAREST)
    out, note = convert_sd_image(big)
    assert np.array_equal(out, raster) and "resampled the 256 x 256 SD raster" in note
    assert convert_sd_image(raster)[1] is None


def test_mirror_sd_flips_columns_and_one_way_headings():
    from cmtool.data.sd_raster import decode_direction, direction_value, mirror_sd

    sd = np.zeros((4, 4, 3), np.uint8)
    sd[1, 0] = (255, 64, direction_value(0.3))  # one-way road heading 0.3 rad at the left edge
    sd[2, 1] = (255, 96, 0)                     # two-way road
    m = mirror_sd(sd)
    assert tuple(m[1, 3, :2]) == (255, 64) and abs(decode_direction(m[1, 3, 2]) + 0.3) < 0.02
    assert tuple(m[2, 2]) == (255, 96, 0) and m[..., 2].sum() == m[1, 3, 2]
    assert np.array_equal(mirror_sd(m), sd)
