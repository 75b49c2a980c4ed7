"""DiT (stage 2): shapes, parameter counts, adaLN-Zero init, null label, gradients."""

import pytest
import torch

from cmtool.core.errors import CmtoolError
from cmtool.model.config import SIZES, DiTConfig
from cmtool.model.dit import DiT, sincos_pos_embed_2d
from tests.conftest import perturb

pytestmark = pytest.mark.usefixtures("one_thread")  # tiny models run fastest single-threaded


def tiny(**kw) -> DiT:
    torch.manual_seed(0)
    return DiT(DiTConfig(depth=2, hidden=64, heads=4, **kw))


def inputs(b: int = 3, num_classes: int = 3):
    g = torch.Generator().manual_seed(1)
    return (torch.randn(b, 64, 8, 8, generator=g), torch.randint(0, 1000, (b,), generator=g),
            torch.randint(0, num_classes + 1, (b,), generator=g))


def expected_params(depth: int, h: int, mlp_ratio: float = 4.0, c: int = 64, classes: int = 3) -> int:
    m = int(h * mlp_ratio)
    block = (3 * h * h + 3 * h) + (h * h + h) + (h * m + m) + (m * h + h) + (6 * h * h + 6 * h)
    stem = (c * h + h) + (256 * h + h) + (h * h + h) + (classes + 1) * h
    final = (2 * h * h + 2 * h) + (h * c + c)
    return depth * block + stem + final


def test_shapes_for_long_and_float_timesteps():
    model = tiny()
    perturb(model)
    x, t, y = inputs()
    assert model(x, t, y).shape == (3, 64, 8, 8)
    assert model(x, t.float() + 0.5, y).shape == (3, 64, 8, 8)
    assert model.embed_tokens(x).shape == (3, 64, 64)
    assert model.condition(t, y).shape == (3, 64)
    assert model.latent_shape == (64, 8, 8)


@pytest.mark.parametrize("size", list(SIZES))
def test_parameter_counts(size):
    with torch.device("meta"):
        model = DiT(DiTConfig(size=size))
    depth, hidden, heads = SIZES[size]
    assert (model.config.depth, model.config.hidden, model.config.heads) == (depth, hidden, heads)
    assert sum(p.numel() for p in model.parameters()) == expected_params(depth, hidden)


def test_dit_b_matches_sledge_count():
    with torch.device("meta"):
        model = DiT(DiTConfig(size="B"))
    count = sum(p.numel() for p in model.parameters())
    assert abs(count - 138e6) / 138e6 < 0.10


def test_fresh_model_predicts_zero_noise():
    model = tiny()
    x, t, y = inputs()
    assert torch.equal(model(x, t, y), torch.zeros_like(x))


def test_null_label_is_the_extra_row():
    model = tiny()
    perturb(model)
    x, t, _ = inputs()
    null = torch.full((3,), model.null_label)
    out_null = model(x, t, null)
    assert torch.isfinite(out_null).all()
    assert not torch.allclose(out_null, model(x, t, torch.zeros(3, dtype=torch.long)))
    with pytest.raises(IndexError):
        model(x, t, null + 1)


def test_gradients_reach_every_parameter():
    model = tiny()
    perturb(model)
    x, t, y = inputs(b=8)
    y = torch.arange(8) % 4
    ((model(x, t, y) - x) ** 2).mean().backward()
    for name, p in model.named_parameters():
        assert p.grad is not None and torch.isfinite(p.grad).all(), name
        assert p.grad.abs().sum() > 0, name


def test_same_seed_same_weights_and_output():
    a, b = tiny(), tiny()
    assert all(torch.equal(p, q) for p, q in zip(a.state_dict().values(), b.state_dict().values()))
    for model in (a, b):
        torch.manual_seed(3)
        perturb(model)
    x, t, y = inputs()
    assert torch.equal(a(x, t, y), b(x, t, y))


def test_config_overrides_and_errors():
    config = DiTConfig(size="S", depth=3).resolved()
    assert (config.depth, config.hidden, config.heads) == (3, 384, 6)
    with pytest.raises(CmtoolError, match="dit.size"):
        DiTConfig(size="huge").resolved()
    with pytest.raises(CmtoolError, match="dit.hidden"):
        DiTConfig(hidden=100, heads=3).resolved()


def test_sincos_positions_are_distinct():
    pos = sincos_pos_embed_2d(64, 8)
    assert pos.shape == (64, 64)
    assert torch.cdist(pos, pos).add(torch.eye(64)).min() > 0.1


def test_bench_dit_compares_with_diffusers_of_the_same_shape(capsys):
    """`cmtool bench dit`: both DiTs of one size timed in fp32 and bf16, bf16 outputs close to fp32's."""
    pytest.importorskip("diffusers")
    from tests.conftest import in_process

    code, out, err = in_process(capsys, "bench", "dit", "--size", "tiny", "--batch", 2, "--repeats", 1)
    assert code == 0, err
    assert "cmtool 5.5M, diffusers" in out and "speed-up over diffusers fp32" in out
    for setting in ("cmtool fp32", "cmtool bf16", "diffusers fp32", "diffusers bf16"):
        assert setting in out
    from cmtool.eval.bench_dit import bench_dit

    result = bench_dit("tiny", 2, 1, report=lambda line: None)
    assert 0 < result["cmtool bf16 difference"] < 0.05 and 0 < result["diffusers bf16 difference"] < 0.05
