"""Improved precision/recall, Control / GT recall with binomial p-values, and the feature rasters."""

import math

import numpy as np
import pytest
import torch

from cmtool.core.errors import CmtoolError
from cmtool.data.sd_raster import rasterize_sd
from cmtool.maps.sdmap import Road, SDMap
from cmtool.metrics.features import FeatureExtractor, imagenet_weights, lanes_image, sd_image
from cmtool.metrics.retrieval import batch_recall, improved_precision_recall

pytestmark = pytest.mark.usefixtures("one_thread")


def direct_tail(m: int, n: int, p: float) -> float:
    """P(M' >= m) for M' ~ Binomial(n, p), summed term by term."""
    return sum(math.comb(n, j) * p**j * (1 - p) ** (n - j) for j in range(m, n + 1))


def test_precision_recall_of_a_set_with_itself_and_with_a_far_set():
    x = np.random.default_rng(0).normal(size=(50, 8))
    assert improved_precision_recall(x, x) == {"precision": 1.0, "recall": 1.0, "k": 3}
    far = improved_precision_recall(x, x + 100.0)
    assert far["precision"] == 0.0 and far["recall"] == 0.0
    # a generator that covers only half of the real modes: full precision, half recall
    real = np.concatenate([np.random.default_rng(1).normal(size=(40, 2)) + c for c in ([0, 0], [50, 0])])
    fake = np.random.default_rng(2).normal(size=(40, 2))
    half = improved_precision_recall(real, fake)
    assert half["precision"] > 0.9 and half["recall"] == pytest.approx(0.5, abs=0.05)


def test_batch_recall_hits_and_p_values():
    rng = np.random.default_rng(0)
    feats = rng.normal(size=(128, 16))
    perfect = batch_recall(feats, feats, batch=64, k=3)
    assert perfect["recall"] == 1.0 and perfect["hits"] == perfect["n"] == 128
    assert perfect["p_value"] == pytest.approx(direct_tail(128, 128, 3 / 64), rel=1e-9)
    noise = batch_recall(rng.normal(size=(130, 16)), rng.normal(size=(130, 16)), batch=16, k=3)
    assert noise["n"] == 128  # the incomplete last batch is left out
    assert noise["p_value"] == pytest.approx(direct_tail(noise["hits"], 128, 3 / 16), rel=1e-9)
    # hand-made batch of 4, k = 1: rows 0 and 1 find their own target first, rows 2 and 3 do not
    gen = np.array([[1, 0], [0, 1], [1, 0.1], [0.1, 1]], float)
    tgt = np.array([[1, 0], [0, 1], [-1, 0], [0, -1]], float)
    r = batch_recall(gen, tgt, batch=4, k=1)
    assert r["hits"] == 2 and r["p_value"] == pytest.approx(direct_tail(2, 4, 0.25))
    with pytest.raises(ValueError):
        batch_recall(gen, tgt[:3], batch=4)


def test_feature_rasters_share_one_style():
    lanes = [np.array([[0.0, -1.75], [20.0, -1.75]]), np.array([[20.0, 1.75], [0.0, 1.75]])]
    img = lanes_image(lanes)
    assert img.shape == (128, 128, 3)
    fwd, back = img[40, 67], img[40, 60]  # x = 11.75 m; y = -1.75 (right) and +1.75 (left)
    assert fwd.tolist() == [255, 255, 128] and back.tolist() == [255, 0, 128]
    sd = rasterize_sd(SDMap(roads=[Road("r", np.array([[-40.0, 0.0], [40.0, 0.0]]))]), 0.0, 0.0, 0.0)
    two_way = sd_image(sd)
    assert two_way[64, 64].tolist() == [255, 128, 128] and two_way[10, 10].tolist() == [0, 0, 0]
    one_way = sd_image(rasterize_sd(SDMap(roads=[Road("r", np.array([[-40.0, 0.0], [40.0, 0.0]]), oneway=1)]),
                                    0.0, 0.0, 0.0))
    assert one_way[64, 64].tolist() == [255, 255, 128]  # heading 0: cos 1, sin 0, as for the lane


def test_seeded_backbone_is_deterministic_and_imagenet_needs_weights(tmp_path, monkeypatch):
    images = np.stack([lanes_image([np.array([[-30.0, y], [30.0, y]])]) for y in (-10.0, 10.0)])
    a = FeatureExtractor("resnet50-seeded")(images)
    b = FeatureExtractor("resnet50-seeded")(images)
    assert a.shape == (2, 2048) and np.array_equal(a, b) and not np.array_equal(a[0], a[1])
    monkeypatch.setenv("TORCH_HOME", str(tmp_path))
    with pytest.raises(CmtoolError, match="no ImageNet weights found"):
        imagenet_weights()
    bad = tmp_path / "w.pth"
    torch.save({"conv1.weight": torch.zeros(1)}, bad)
    with pytest.raises(CmtoolError, match="not ResNet-50 weights"):
        FeatureExtractor("resnet50-imagenet", weights=bad)
    with pytest.raises(CmtoolError, match="unknown feature backbone"):
        FeatureExtractor("vgg")


def test_bf16_features_stay_close_to_fp32():
    images = np.stack([lanes_image([np.array([[-30.0, y], [30.0, y + k]]) for y in (-10.0, 0.0, 10.0)])
                       for k in range(-6, 6)])
    fp32 = FeatureExtractor("resnet50-seeded")(images)
    bf16 = FeatureExtractor("resnet50-seeded", precision="bf16")(images)
    assert bf16.dtype == np.float32 and bf16.shape == fp32.shape and not np.array_equal(bf16, fp32)
    cosine = (fp32 * bf16).sum(1) / np.linalg.norm(fp32, axis=1) / np.linalg.norm(bf16, axis=1)
    assert cosine.min() > 0.99
    # what the recall metrics use: each image's nearest other image is the same
    def nearest(f):
        d = ((f[:, None] - f[None]) ** 2).sum(-1)
        np.fill_diagonal(d, np.inf)
        return d.argmin(1)

    assert (nearest(fp32) == nearest(bf16)).mean() >= 0.9
    with pytest.raises(CmtoolError, match="feature precision"):
        FeatureExtractor(precision="fp16")
