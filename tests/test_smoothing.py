"""Decoded polylines smoothed into least-squares Bézier curves: what the fit keeps and what it removes,
and that `cmtool sample --smooth K` applies exactly that fit to the decoder's points."""

import json

import numpy as np
import pytest

from cmtool.core.geometry import bezier_fit_matrix
from cmtool.maps.lanegraph import LaneGraph, infer_successors
from cmtool.metrics.validity import check
from tests.conftest import REPO, in_process

SD_PNG = REPO / "sample_data" / "sd_lav.png"


def test_fit_is_a_projection_that_keeps_low_degree_curves():
    fit = bezier_fit_matrix(20, 6)
    assert np.allclose(fit @ fit, fit, atol=1e-9)
    t = np.linspace(0.0, 1.0, 20)
    curve = np.stack([30 * t - 15, 4 * t**3 - 6 * t**2 + 1], axis=-1)  # a cubic: degree below 6 control points
    assert np.allclose(fit @ curve, curve, atol=1e-9)
    assert np.allclose(bezier_fit_matrix(20, 20), np.eye(20), atol=1e-6)
    with pytest.raises(ValueError):
        bezier_fit_matrix(20, 1)


def test_fit_removes_point_jitter_and_the_kinks_it_makes():
    rng = np.random.default_rng(0)
    x = np.linspace(-20.0, 20.0, 20)
    truth = np.stack([x, 0.01 * x**2], axis=-1)
    jagged = truth + rng.normal(0.0, 0.4, truth.shape)
    smooth = bezier_fit_matrix(20, 6) @ jagged
    rms_smooth, rms_jagged = (np.sqrt(np.mean((line - truth) ** 2)) for line in (smooth, jagged))
    assert rms_smooth < 0.7 * rms_jagged  # noise keeps a share of 6 / 20 of its variance
    counts = [check(LaneGraph(lanes=[lane], successors=infer_successors([lane]))).counts() for lane in (jagged, smooth)]
    assert counts[0].get("kink", 0) > 0 and counts[1].get("kink", 0) == 0


def test_sample_smooths_the_decoded_points(sampling_ckpt, tmp_path, capsys):
    common = ("sample", "--ckpt", sampling_ckpt["controlmap"], "--sd", SD_PNG, "--steps", 3, "--city", "LAV", "--raw",
              "--no-log", "--quiet")
    for name, k in (("raw", 0), ("smooth", 4)):
        code, _, err = in_process(capsys, *common, "--smooth", k, "--out", tmp_path / name)
        assert code == 0, err
    raw, smooth = (json.loads((tmp_path / name / "sd_lav.json").read_text()) for name in ("raw", "smooth"))
    assert raw["meta"]["smooth"] == 0 and smooth["meta"]["smooth"] == 4
    fit = bezier_fit_matrix(20, 4)
    for key in ("lanes", "green_lights", "red_lights"):
        assert len(raw[key]) == len(smooth[key])
        for r, s in zip(raw[key], smooth[key]):
            assert np.allclose(fit @ np.asarray(r), np.asarray(s), atol=1e-3)
    assert raw["lanes"] and raw["lanes"] != smooth["lanes"]
