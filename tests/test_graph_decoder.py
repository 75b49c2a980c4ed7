"""The RVAE's graph decoder: refined polyline queries, feature sampling, successor logits and losses."""

import numpy as np
import pytest
import torch

from cmtool.core.errors import CmtoolError
from cmtool.maps.lanegraph import join_successors
from cmtool.model.config import RVAEConfig, RVAELossConfig
from cmtool.model.graph import sample_points
from cmtool.model.rvae import RVAE, decoded_elements
from cmtool.model.rvae_loss import denoise_input, denoise_loss, direction_loss, rvae_loss, successor_loss
from cmtool.train.data import vector_targets

SMALL = dict(d_model=64, decoder_layers=2, heads=4, ffn=128, dropout=0.0, decoder="graph")


def test_outputs_every_layer_and_successor_logits():
    torch.manual_seed(0)
    model = RVAE(RVAEConfig(**SMALL))
    out, mean, _ = model(torch.rand(2, 6, 128, 128), aux=True)
    assert out["lines"].shape == (2, 50, 20, 2) and out["lines_logit"].shape == (2, 50)
    assert out["green"].shape == (2, 10, 20, 2) and out["succ_logit"].shape == (2, 50, 50)
    assert len(out["aux"]) == 1 and out["aux"][0]["succ_logit"].shape == (2, 50, 50)
    assert out["lines"].abs().max() <= 32.0
    # the offset heads start at zero: every layer begins from the same reference polylines
    assert torch.equal(out["lines"], out["aux"][0]["lines"])
    # the successor head starts out preferring lanes whose end touches the next one's start
    gap = torch.cdist(out["lines"][:, :, -1], out["lines"][:, :, 0])
    near, far = gap < 2.0, gap > 20.0
    assert out["succ_logit"][near].mean() > out["succ_logit"][far].mean() + 10.0
    assert mean.shape == (2, 64, 8, 8)


def test_features_are_sampled_where_the_raster_has_them():
    feat = torch.zeros(1, 1, 32, 32)
    feat[0, 0, 0, 31] = 1.0  # front edge (row 0), right edge (last column): x = +31, y = -31 m
    points = torch.tensor([[[[31.0, -31.0], [31.0, 31.0], [-31.0, -31.0], [0.0, 0.0]]]]) / 32.0
    values = sample_points(feat, points)[0, 0, :, 0]
    assert values[0] > 0.9 and values[1:].abs().max() < 1e-6


def test_graph_decoder_refuses_control_points():
    with pytest.raises(CmtoolError, match="control_points"):
        RVAE(RVAEConfig(**SMALL, control_points=4))
    with pytest.raises(CmtoolError, match="rvae.decoder"):
        RVAE(RVAEConfig(decoder="mlp"))


def test_points_stay_float32_under_bf16_autocast():
    """bf16's 8-bit mantissa made the refined points jagged (docs/rvae-decoders.md): they stay float32."""
    torch.manual_seed(0)
    model = RVAE(RVAEConfig(**SMALL))
    for head in model.graph.offsets:
        torch.nn.init.normal_(head[-1].weight, std=0.05)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        out, _, _ = model(torch.rand(1, 6, 128, 128), sample=False, aux=True)
    assert out["lines"].dtype == torch.float32 and out["aux"][0]["lines"].dtype == torch.float32
    for lines in (out["lines"], out["aux"][0]["lines"]):  # not rounded to what bf16 holds (0.06 m at 16 m)
        assert (lines.to(torch.bfloat16).float() != lines).float().mean() > 0.9


def test_successor_loss_on_matched_pairs():
    succ = torch.zeros(1, 3, 3, dtype=torch.bool)
    succ[0, 0, 1] = succ[0, 1, 2] = True  # targets: 0 -> 1 -> 2
    pairs = [(np.array([2, 0, 1]), np.array([0, 1, 2]))]  # query 2 is target 0, query 0 target 1, query 1 target 2
    right = torch.full((1, 3, 3), -20.0)
    right[0, 2, 0] = right[0, 0, 1] = 20.0  # query 2 -> query 0 -> query 1: the targets' chain
    assert successor_loss(right, succ, pairs) < 1e-6
    wrong = right.transpose(1, 2).clone()
    assert successor_loss(wrong, succ, pairs) > 5.0
    diagonal = right.clone()
    diagonal[0, range(3), range(3)] = 50.0  # a lane into itself is never scored
    assert successor_loss(diagonal, succ, pairs) == successor_loss(right, succ, pairs)
    assert successor_loss(right, succ, [(np.array([0]), np.array([1]))]) == 0.0  # one matched line: no pair


def test_direction_loss():
    line = torch.stack([torch.linspace(0, 10, 5), torch.zeros(5)], dim=-1)
    assert direction_loss(line, line * 2.0) < 1e-6  # same directions, any length
    assert direction_loss(line.flip(0), line) == pytest.approx(2.0)  # reversed


def test_successor_targets_from_the_scene_edges():
    arrays = {"lines": np.zeros((2, 4, 20, 2), np.float32), "line_mask": np.ones((2, 4), bool),
              "green": np.zeros((2, 1, 20, 2), np.float32), "green_mask": np.zeros((2, 1), bool),
              "red": np.zeros((2, 1, 20, 2), np.float32), "red_mask": np.zeros((2, 1), bool),
              "edges": np.array([[0, 1], [2, 3], [1, 3]], np.int32), "edge_offsets": np.array([0, 2, 3])}
    first, second = vector_targets(arrays, 0)["succ"], vector_targets(arrays, 1)["succ"]
    assert first.nonzero().tolist() == [[0, 1], [2, 3]] and second.nonzero().tolist() == [[1, 3]]


def _batch():
    """Two scenes of three lines along x (0 flows into 2), no lights."""
    lines = torch.zeros(2, 50, 20, 2)
    lines[:, :3] = torch.stack([torch.linspace(-30, 30, 20), torch.zeros(20)], dim=-1)
    lines[:, 1, :, 1] = 3.5
    mask = torch.zeros(2, 50, dtype=torch.bool)
    mask[:, :3] = True
    succ = torch.zeros(2, 50, 50, dtype=torch.bool)
    succ[:, 0, 2] = True
    return {"lines": lines, "line_mask": mask, "green": torch.zeros(2, 10, 20, 2), "red": torch.zeros(2, 10, 20, 2),
            "green_mask": torch.zeros(2, 10, dtype=torch.bool), "red_mask": torch.zeros(2, 10, dtype=torch.bool),
            "succ": succ}


def test_loss_has_every_term_and_trains_every_part():
    torch.manual_seed(0)
    model = RVAE(RVAEConfig(**SMALL))
    batch = _batch()
    config = RVAELossConfig(aux_weight=1.0, direction_weight=2.0, successor_weight=5.0, denoise_weight=1.0)
    decoded, mean, logvar = model(torch.rand(2, 6, 128, 128), aux=True, denoise=denoise_input(batch, config))
    total, parts = rvae_loss(decoded, mean, logvar, batch, config)
    assert {"l1/lines", "exist/lines", "dir/lines", "succ/lines", "aux", "denoise", "kl"} <= set(parts)
    assert all(np.isfinite(v) for v in parts.values()) and parts["succ/lines"] > 0 and parts["denoise"] > 0
    total.backward()
    unused = [k for k, p in model.named_parameters() if p.grad is None]
    assert unused == []


def test_denoising_queries_are_hidden_from_the_matched_ones():
    torch.manual_seed(0)
    model = RVAE(RVAEConfig(**SMALL)).eval()
    z = torch.randn(2, 64, 8, 8)
    batch = _batch()
    plain = model.decode(z, aux=True)
    with_dn = model.decode(z, aux=True, denoise=denoise_input(batch, RVAELossConfig(denoise_weight=1.0)))
    for key in ("lines", "lines_logit", "green", "succ_logit"):
        assert torch.allclose(plain[key], with_dn[key], atol=1e-5), key
    assert len(with_dn["denoise"]) == 2 and with_dn["denoise"][-1]["lines"].shape == (2, 50, 20, 2)
    assert with_dn["denoise"][-1]["succ_logit"].shape == (2, 50, 50)
    with pytest.raises(CmtoolError, match="denoise"):
        RVAE(RVAEConfig(d_model=64, decoder_layers=1, heads=4, ffn=128)).decode(z, denoise=batch["lines"])


def test_denoise_loss_is_zero_only_for_the_true_lines():
    batch = _batch()
    config = RVAELossConfig(direction_weight=2.0, successor_weight=5.0, denoise_weight=1.0)
    succ_logit = torch.where(batch["succ"], 30.0, -30.0)
    exact = [{"lines": batch["lines"].clone(), "succ_logit": succ_logit}]
    assert denoise_loss(exact, batch, config) < 1e-6
    shifted = [{"lines": batch["lines"] + torch.tensor([0.0, 1.0]), "succ_logit": succ_logit}]
    assert denoise_loss(shifted, batch, config) == pytest.approx(64.0 * 6 * (1.0 / 32.0) / 100, rel=1e-4)  # 6 lines, 1 m off, 100 slots
    # padded slots (mask False) are never scored, whatever they hold
    padded = [{"lines": torch.where(batch["line_mask"][..., None, None], batch["lines"], 99.0),
               "succ_logit": succ_logit}]
    assert denoise_loss(padded, batch, config) < 1e-6


def test_decoded_successors_are_pairs_of_kept_lines():
    lines = torch.zeros(1, 4, 20, 2)
    logit = torch.tensor([[5.0, -5.0, 5.0, 5.0]])  # line 1 is not kept
    succ = torch.full((1, 4, 4), -5.0)
    succ[0, 0, 2] = succ[0, 1, 3] = succ[0, 3, 3] = 5.0  # 1 -> 3 dropped with line 1, 3 -> 3 is no link
    green = torch.zeros(1, 1, 20, 2)
    decoded = {"lines": lines, "lines_logit": logit, "green": green, "green_logit": torch.full((1, 1), -5.0),
               "red": green, "red_logit": torch.full((1, 1), -5.0), "succ_logit": succ}
    (item,) = decoded_elements(decoded)
    assert len(item["lines"]) == 3 and item["successors"].tolist() == [[0, 1]]  # kept lines 0, 2, 3
    assert "successors" not in decoded_elements({k: v for k, v in decoded.items() if k != "succ_logit"})[0]


def test_join_successors_shares_joints_without_kinks():
    a = np.stack([np.linspace(-20, 0, 11), np.zeros(11)], 1)
    b = np.stack([np.linspace(1, 21, 11), np.full(11, 0.6)], 1)  # starts 1.2 m from a's end
    c = np.stack([np.linspace(1, 15, 11), np.linspace(0.6, 14, 11)], 1)  # a fork from the same point
    joined = join_successors([a, b, c], [(0, 1), (0, 2)])
    assert np.allclose(joined[0][-1], joined[1][0]) and np.allclose(joined[1][0], joined[2][0])
    assert np.allclose(joined[0][-1], np.mean([a[-1], b[0], c[0]], axis=0))
    assert np.allclose(joined[0][0], a[0]) and np.allclose(joined[1][-1], b[-1])  # far ends stay
    steps = np.diff(joined[1], axis=0)
    assert np.allclose(steps, steps[0])  # the move fades linearly: still a straight line
    assert [np.array_equal(x, y) for x, y in zip(join_successors([a, b], []), [a, b])] == [True, True]


def test_successor_counts_match_lanes_before_links():
    from cmtool.maps.lanegraph import LaneGraph
    from cmtool.train.reconstruction import successor_counts

    def lane(x0, y):
        return np.stack([np.linspace(x0, x0 + 19, 20), np.full(20, y)], 1)

    truth = np.stack([lane(-20, 0.0), lane(0, 0.0), lane(0, 3.5)])
    edges = np.array([[0, 1], [0, 2]])
    # the prediction lists the same lanes in another order, one shifted 0.4 m, plus a lane far off
    pred = LaneGraph(lanes=[lane(0, 3.5), lane(-20, 0.4), lane(0, 0.0), lane(0, 20.0)],
                     successors=[(1, 2), (1, 0), (2, 0), (1, 3)])
    correct, predicted, true = successor_counts(pred, truth, edges, tol=1.0)
    assert (correct, predicted, true) == (2, 4, 2)  # 1->2 and 1->0 are true; 2->0 reversed; 3 matches nothing
    assert successor_counts(pred, truth, edges, tol=0.1)[0] == 0  # the shifted lane, in both links, no longer matches
