import numpy as np

from cmtool.core.geo import LocalProjection
from cmtool.core.geometry import from_frame, offset, resample, to_frame


def test_projection_distances_match_geodesy():
    proj = LocalProjection(49.0, 8.4)
    pts = proj.to_metres([49.0, 49.001, 49.0], [8.4, 8.4, 8.401])
    np.testing.assert_allclose(pts[0], [0.0, 0.0], atol=1e-9)
    # Meridian arc of 0.001 deg at 49 N is 111.21 m; a parallel arc is N(phi) cos(phi) dlon = 73.17 m.
    assert abs(pts[1, 1] - 111.21) < 0.02 and abs(pts[1, 0]) < 1e-6
    assert abs(pts[2, 0] - 73.17) < 0.02 and abs(pts[2, 1]) < 0.01


def test_frames_roundtrip_and_orientation():
    pose = (100.0, 50.0, np.pi / 2)  # facing north
    world = np.array([[100.0, 60.0], [90.0, 50.0]])  # 10 m ahead, 10 m to the left (west)
    ego = to_frame(world, *pose)
    np.testing.assert_allclose(ego, [[10.0, 0.0], [0.0, 10.0]], atol=1e-9)
    np.testing.assert_allclose(from_frame(ego, *pose), world, atol=1e-9)


def test_resample_and_offset():
    line = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0]])
    r = resample(line, 5)
    np.testing.assert_allclose(r, [[0, 0], [5, 0], [10, 0], [10, 5], [10, 10]])
    np.testing.assert_allclose(offset(np.array([[0.0, 0.0], [10.0, 0.0]]), 2.0), [[0, 2], [10, 2]])


def test_inverse_projection_round_trips():
    proj = LocalProjection(-33.9, 151.2)
    xy = np.random.default_rng(0).uniform(-20000.0, 20000.0, size=(500, 2))
    latlon = proj.to_latlon(xy)
    np.testing.assert_allclose(proj.to_metres(latlon[:, 0], latlon[:, 1]), xy, atol=1e-6)
    np.testing.assert_allclose(proj.to_latlon([0.0, 0.0]), [-33.9, 151.2], atol=1e-12)
