"""HD raster orientation and direction encoding."""

import numpy as np

from cmtool.data.hd_raster import rasterize_scene


def raster(lines, green=(), red=(), **kw):
    def pad(ls):
        arr = np.zeros((max(len(ls), 1), 20, 2), np.float32)
        for i, l in enumerate(ls):
            arr[i] = l
        return arr, np.arange(len(arr)) < len(ls)

    (l, lm), (g, gm), (r, rm) = pad(lines), pad(green), pad(red)
    return rasterize_scene(l, lm, g, gm, r, rm, **kw)


def seg(a, b):
    return np.linspace(a, b, 20)


def test_shape_and_background():
    out = raster([])
    assert out.shape == (6, 128, 128) and out.dtype == np.float32
    assert not out.any()
    assert raster([], px_m=0.25).shape == (6, 256, 256)


def test_line_ahead_lands_in_top_rows_with_plus_x_encoding():
    out = raster([seg([20, -2], [30, -2])])  # ahead, heading +x, slightly right
    rows, cols = np.nonzero(out[0])
    assert rows.max() < 32 and rows.min() >= 2  # x in [20, 30] -> rows 4..24
    assert cols.min() > 64  # right of centre
    np.testing.assert_allclose(out[0][out[0] > 0], 1.0)
    np.testing.assert_allclose(out[1][out[0] > 0], 0.5)
    assert not out[2:].any()


def test_line_to_the_left_lands_in_left_columns_heading_encoded():
    out = raster([seg([-5, 25], [5, 25])])  # to the left, heading +x
    rows, cols = np.nonzero(out[0])
    assert cols.max() < 32 and rows.min() > 40 and rows.max() < 90
    out = raster([seg([0, 20], [0, 30])])  # heading +y (pointing left)
    on = out[0] > 0
    np.testing.assert_allclose(out[0][on], 0.5, atol=1e-6)
    np.testing.assert_allclose(out[1][on], 1.0, atol=1e-6)


def test_light_channels_and_pixel_centres():
    out = raster([], green=[seg([0, 0], [10, 0])], red=[seg([0, 0], [-10, 0])], width_m=0.5)
    assert not out[:2].any()
    g_rows, g_cols = np.nonzero(out[2])
    r_rows, r_cols = np.nonzero(out[5])  # heading pi encodes as (0, 0.5): find it by the sin channel
    assert g_rows.max() <= 64 and r_rows.min() >= 63  # green ahead, red behind
    np.testing.assert_allclose(out[4][out[5] > 0], 0.0)
    np.testing.assert_allclose(out[5][out[5] > 0], 0.5)
    assert set(g_cols) <= {63, 64} and set(r_cols) <= {63, 64}

