"""ControlMap (stage 3): exact base behaviour at init, frozen base under training, batched CFG pass."""

import pytest
import torch

from cmtool.core.errors import CmtoolError
from cmtool.model.config import PAPER_CONTROL_WIDTHS, ControlConfig, DiTConfig
from cmtool.model.controlmap import ControlMap
from cmtool.model.dit import DiT
from tests.conftest import perturb

pytestmark = pytest.mark.usefixtures("one_thread")  # tiny models run fastest single-threaded

SMALL = ControlConfig(num_blocks=2, widths=(16, 16, 32, 32), groups=8)


def small_dit() -> DiT:
    torch.manual_seed(0)
    dit = DiT(DiTConfig(depth=3, hidden=64, heads=4))
    perturb(dit)
    return dit


def inputs(b: int = 3):
    g = torch.Generator().manual_seed(1)
    return (torch.randn(b, 64, 8, 8, generator=g), torch.randint(0, 1000, (b,), generator=g),
            torch.randint(0, 4, (b,), generator=g), torch.rand(b, 3, 128, 128, generator=g))


def count(model: torch.nn.Module) -> int:
    return sum(p.numel() for p in model.parameters())


@pytest.mark.parametrize("perturbed", [False, True])
def test_fresh_controlmap_equals_base_exactly(perturbed):
    torch.manual_seed(0)
    dit = DiT(DiTConfig(depth=3, hidden=64, heads=4))
    if perturbed:
        perturb(dit)
    cm = ControlMap(dit, SMALL)
    x, t, y, ctrl = inputs()
    base = dit(x, t, y)
    assert torch.equal(cm(x, t, y, ctrl), base)
    assert torch.equal(cm(x, t, y), base)
    assert perturbed == bool(base.abs().sum() > 0)


def test_copies_start_as_independent_copies_of_the_first_blocks():
    dit = small_dit().requires_grad_(False)
    cm = ControlMap(dit, SMALL)
    assert len(cm.copies) == 2 and len(cm.zero) == 2
    assert all(p.requires_grad for p in cm.branch_parameters())
    for copy, block in zip(cm.copies, dit.blocks):
        for (name, p), q in zip(copy.named_parameters(), block.parameters()):
            assert torch.equal(p, q) and p.data_ptr() != q.data_ptr(), name


def test_training_the_branch_leaves_the_base_untouched():
    dit = small_dit()
    cm = ControlMap(dit, SMALL)
    cm.freeze_base()
    assert not dit.training and not any(p.requires_grad for p in dit.parameters())
    base_before = {k: v.clone() for k, v in dit.state_dict().items()}
    branch = cm.branch_parameters()
    assert count(cm) == count(dit) + sum(p.numel() for p in branch)
    branch_before = [p.detach().clone() for p in branch]
    x, t, y, ctrl = inputs(4)
    target = torch.randn_like(x)
    opt = torch.optim.AdamW(branch, lr=1e-3, weight_decay=0.0)
    for _ in range(3):
        opt.zero_grad()
        ((cm(x, t, y, ctrl) - target) ** 2).mean().backward()
        opt.step()
    for k, v in dit.state_dict().items():
        assert torch.equal(v, base_before[k]), k
    assert all(p.grad is None for p in dit.parameters())
    assert all(not torch.equal(p, q) for p, q in zip(branch, branch_before))
    with torch.no_grad():
        assert not torch.allclose(cm(x, t, y, ctrl), dit(x, t, y))
        assert torch.equal(cm(x, t, y), dit(x, t, y))


def test_forward_cfg_halves_match_separate_passes():
    dit = small_dit()
    cm = ControlMap(dit, SMALL)
    perturb(cm)
    x, t, y, ctrl = inputs()
    with torch.no_grad():
        eps_cond, eps_uncond, residuals = cm.forward_cfg(x, t, y, ctrl)
        assert torch.allclose(eps_cond, cm(x, t, y, ctrl), atol=1e-5)
        assert torch.allclose(eps_uncond, cm.base(x, t, y), atol=1e-5)
        assert not torch.allclose(eps_cond, eps_uncond, atol=1e-3)
    assert len(residuals) == 2
    assert all(r.shape == (3, 64, 64) and r.abs().sum() > 0 for r in residuals)


def test_paper_controlmap_count():
    with torch.device("meta"):
        cm = ControlMap(DiT(DiTConfig(size="B")), ControlConfig(widths=PAPER_CONTROL_WIDTHS))
    assert abs(count(cm) - 230e6) / 230e6 < 0.10
    assert len(cm.copies) == 6


def test_default_config_fits_the_tiny_dit():
    with torch.device("meta"):
        dit = DiT(DiTConfig())
        cm = ControlMap(dit, ControlConfig())
    assert count(cm) > count(dit)
    assert ControlConfig(widths=[32, 64, 128, 192]).widths == (32, 64, 128, 192)
    assert cm.config.num_blocks <= dit.config.depth


@pytest.mark.parametrize("config, field", [
    (ControlConfig(num_blocks=4), "control.num_blocks"),
    (ControlConfig(num_blocks=1, widths=(16, 24, 32, 48)), "control.widths"),
    (ControlConfig(num_blocks=1, widths=(32, 64, 128)), "control.widths"),
    (ControlConfig(num_blocks=1, image_px=64), "control.image_px"),
])
def test_bad_configs_raise(config, field):
    with pytest.raises(CmtoolError, match=field):
        ControlMap(small_dit(), config)


def test_weights_of_the_old_sd_encoding_see_no_road_class_and_a_resume_across_encodings_is_refused(tmp_path):
    """The shipped branch (trained on encoding 1, its config without sd_encoding) reads a primary and a residential
    road alike, as it was trained; a branch of encoding 2 reads them apart. Resuming an old-encoding run with a
    recipe of encoding 2 is refused with a message naming both encodings."""
    import shutil

    import numpy as np

    from cmtool.data.sd_raster import rasterize_sd
    from cmtool.maps.sdmap import Road, SDMap
    from cmtool.model import checkpoint as ckpt
    from cmtool.model.controlmap import control_images, sd_tensor
    from cmtool.model.release import bundled_checkpoint
    from cmtool.train.loop import _resume_point

    line = np.array([[0.0, -50.0], [0.0, 50.0]])
    rasters = np.stack([rasterize_sd(SDMap(roads=[Road("r", line, c)]), 0.0, 0.0, np.pi / 2)
                        for c in ("primary", "residential")])
    model, config = ckpt.load_model(bundled_checkpoint())
    assert config["control"]["sd_encoding"] == 1 and model.config.sd_encoding == 1
    with torch.no_grad():
        old = [model.encoder(sd_tensor(c)[None]) for c in control_images(model.config, rasters)]
    assert torch.equal(old[0], old[1])
    new = ControlConfig(**{**config["control"], "sd_encoding": 2})
    torch.manual_seed(0)
    with torch.no_grad():
        branch = ControlMap(DiT(DiTConfig(**config["model"])), new)
        seen = [branch.encoder(sd_tensor(c)[None]) for c in control_images(new, rasters)]
    assert not torch.equal(seen[0], seen[1])
    run = tmp_path / "run"
    shutil.copytree(bundled_checkpoint(), ckpt.step_dir(run, 4000))
    wanted = {"kind": "controlmap", "model": config["model"], "control": {**config["control"], "sd_encoding": 2}}
    with pytest.raises(CmtoolError, match=r"encoding 1 \(R road presence.*encoding 2 \(R road class.*branch_from"):
        _resume_point(run, True, "controlmap", wanted)
