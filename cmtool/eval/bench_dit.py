"""``cmtool bench dit``: this project's DiT forward pass against diffusers' ``DiTTransformer2DModel`` (SLEDGE's
backbone) of the same shape and batch, in the same process, float32 and bf16 autocast, interleaved.

diffusers is an optional benchmark extra (``pip install 'cmtool[bench]'``), never a runtime dependency.
Weights are random (perturbed from the zero initialisation of adaLN-Zero, so outputs are not all zero);
timings are per forward pass under ``torch.inference_mode``.
"""

from __future__ import annotations

import statistics
import time

import torch

from cmtool.core.errors import CmtoolError
from cmtool.model.config import SIZES, DiTConfig
from cmtool.model.dit import DiT

SETTINGS = (("cmtool", False), ("cmtool", True), ("diffusers", False), ("diffusers", True))  # (model, bf16)


def diffusers_dit(config: DiTConfig) -> torch.nn.Module:
    """diffusers' DiT with ``config``'s shape: patch size 1 over the latent, adaLN-Zero blocks, class labels."""
    try:
        from diffusers import DiTTransformer2DModel
    except ImportError:
        raise CmtoolError("bench dit compares with diffusers' DiT: pip install 'cmtool[bench]'") from None
    return DiTTransformer2DModel(num_attention_heads=config.heads, attention_head_dim=config.hidden // config.heads,
                                 in_channels=config.latent_channels, out_channels=config.latent_channels,
                                 num_layers=config.depth, patch_size=1, sample_size=config.latent_size,
                                 num_embeds_ada_norm=config.num_classes + 1)


def bench_dit(size: str = "B", batch: int = 32, repeats: int = 5, report=print) -> dict:
    """Seconds per forward pass (minimum and median of ``repeats``) of each of :data:`SETTINGS`, the speed-up of
    this project's DiT over diffusers' float32 one, and the relative difference of bf16 outputs from float32."""
    if size not in SIZES:
        raise CmtoolError(f"--size: {size!r} (choose {', '.join(SIZES)})")
    config = DiTConfig(size=size, latent_channels=64, latent_size=8, num_classes=4).resolved()
    generator = torch.Generator().manual_seed(0)
    models = {"cmtool": DiT(config).eval(), "diffusers": diffusers_dit(config).eval()}
    with torch.no_grad():
        for model in models.values():
            for p in model.parameters():
                p.add_(0.02 * torch.randn(p.shape, generator=generator))
    x = torch.randn(batch, config.latent_channels, config.latent_size, config.latent_size, generator=generator)
    t = torch.randint(0, 1000, (batch,), generator=generator)
    y = torch.randint(0, config.num_classes, (batch,), generator=generator)

    def forward(name: str, bf16: bool) -> torch.Tensor:
        with torch.inference_mode(), torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16):
            out = models[name](x, t, y) if name == "cmtool" else models[name](x, timestep=t, class_labels=y).sample
        return out.float()

    params = {name: sum(p.numel() for p in m.parameters()) for name, m in models.items()}
    report(f"DiT-{size}: cmtool {params['cmtool'] / 1e6:.1f}M, diffusers {params['diffusers'] / 1e6:.1f}M "
           f"parameters; batch {batch}, {torch.get_num_threads()} threads")
    outputs = {s: forward(*s) for s in SETTINGS}  # warm-up, and the outputs compared below
    times = {s: [] for s in SETTINGS}
    for _ in range(repeats):  # interleaved, so load from other work spreads over all settings
        for s in SETTINGS:
            began = time.perf_counter()
            forward(*s)
            times[s].append(time.perf_counter() - began)
    result = {}
    for (name, bf16), runs in times.items():
        key = f"{name} {'bf16' if bf16 else 'fp32'}"
        result[key] = {"min": min(runs), "median": statistics.median(runs)}
        report(f"  {key:<16} min {min(runs):.3f} s, median {statistics.median(runs):.3f} s per forward pass")
    base = result["diffusers fp32"]["min"]
    for key in ("cmtool fp32", "cmtool bf16"):
        result[f"{key} speed-up"] = base / result[key]["min"]
    result["cmtool bf16 / diffusers bf16"] = result["diffusers bf16"]["min"] / result["cmtool bf16"]["min"]
    for name in ("cmtool", "diffusers"):
        ref = outputs[(name, False)]
        result[f"{name} bf16 difference"] = float((outputs[(name, True)] - ref).norm() / ref.norm())
    report(f"speed-up over diffusers fp32 (minimum times): cmtool fp32 {result['cmtool fp32 speed-up']:.2f}x, "
           f"cmtool bf16 {result['cmtool bf16 speed-up']:.2f}x; cmtool bf16 over diffusers bf16 "
           f"{result['cmtool bf16 / diffusers bf16']:.2f}x")
    report(f"bf16 outputs against fp32 (relative norm): cmtool {result['cmtool bf16 difference']:.4f}, diffusers "
           f"{result['diffusers bf16 difference']:.4f}")
    return result
