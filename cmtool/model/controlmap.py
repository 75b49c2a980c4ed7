"""ControlMap (stage 3): an SD-map ControlNet branch on a frozen, pretrained DiT.

A convolutional control encoder turns the ``(B, 3, 128, 128)`` SD raster (with ``control.layout``, followed by
the two channels of the rule layout's lanes: :mod:`cmtool.data.layouts`) into a ``(B, 64, 8, 8)``
map, adds 2D sine-cosine positions and flattens it to 64 tokens. Trainable copies of the first
``M`` DiT blocks (initialised from the base) run on ``base tokens + proj(control tokens)``; the
output of copy ``m`` passes a zero-initialised linear layer and is added to the output of base block
``m``. Both projections start at zero, so a fresh ControlMap computes exactly the base DiT.
"""

from __future__ import annotations

import copy

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from cmtool.core.errors import CmtoolError
from cmtool.data.layouts import LAYOUT_CHANNELS, LAYOUTS, control_raster
from cmtool.data.sd_raster import as_encoding
from cmtool.model.config import ControlConfig
from cmtool.model.dit import DiT, sincos_pos_embed_2d

SD_CHANNELS = 3
NO_LAYOUT = "none"


def sd_tensor(sd: np.ndarray) -> Tensor:
    """(H, W, C) uint8 control image (an SD raster, maybe with layout channels) -> (C, H, W) float32 in [0, 1]."""
    return torch.from_numpy(np.ascontiguousarray(sd.transpose(2, 0, 1))).float().div_(255.0)


def control_images(config: ControlConfig, sd: np.ndarray, layouts: list | None = None) -> np.ndarray:
    """The control images (B, H, W, in_channels) uint8 that a branch of ``config`` reads, from SD rasters ``sd``
    (B, H, W, 3) of today's encoding, in the branch's own encoding, and, when it reads a layout, each scene's layout
    raster (None, or None entries: no layout)."""
    sd = as_encoding(np.asarray(sd), config.sd_encoding)
    if config.layout == NO_LAYOUT:
        return sd
    layouts = layouts if layouts is not None else [None] * len(sd)
    return np.stack([control_raster(s, lay) for s, lay in zip(sd, layouts)])


class EncoderStage(nn.Module):
    """Strided 3x3 conv -> GroupNorm -> GELU, then a residual 3x3 conv -> GroupNorm -> GELU."""

    def __init__(self, cin: int, cout: int, groups: int):
        super().__init__()
        self.down = nn.Conv2d(cin, cout, 3, stride=2, padding=1)
        self.norm1 = nn.GroupNorm(groups, cout)
        self.conv = nn.Conv2d(cout, cout, 3, padding=1)
        self.norm2 = nn.GroupNorm(groups, cout)

    def forward(self, x: Tensor) -> Tensor:
        x = F.gelu(self.norm1(self.down(x)))
        return x + F.gelu(self.norm2(self.conv(x)))


class ControlEncoder(nn.Module):
    """Control image ``(B, C, px, px)`` in [0, 1] -> control tokens ``(B, (px/16)**2, out_channels)``."""

    def __init__(self, config: ControlConfig, out_channels: int):
        super().__init__()
        chans = (config.in_channels, *config.widths)
        self.stages = nn.Sequential(*(EncoderStage(a, b, config.groups) for a, b in zip(chans, chans[1:])))
        self.out = nn.Conv2d(config.widths[-1], out_channels, 1)
        self.register_buffer("pos", sincos_pos_embed_2d(out_channels, config.image_px // 16), persistent=False)

    def forward(self, image: Tensor) -> Tensor:
        return self.out(self.stages(image)).flatten(2).transpose(1, 2) + self.pos


class ControlMap(nn.Module):
    """A frozen-able base DiT (``self.base``) plus the trainable SD-map control branch."""

    def __init__(self, dit: DiT, config: ControlConfig):
        super().__init__()
        _validate(config, dit)
        self.config = config
        self.base = dit
        hidden = dit.config.hidden
        self.encoder = ControlEncoder(config, dit.config.latent_channels)
        self.proj = nn.Linear(dit.config.latent_channels, hidden)
        self.copies = copy.deepcopy(dit.blocks[: config.num_blocks]).requires_grad_(True)
        self.zero = nn.ModuleList(nn.Linear(hidden, hidden) for _ in range(config.num_blocks))
        for layer in (self.proj, *self.zero):
            nn.init.zeros_(layer.weight)
            nn.init.zeros_(layer.bias)

    @property
    def latent_shape(self) -> tuple[int, int, int]:
        """Shape ``(C, H, W)`` of one latent."""
        return self.base.latent_shape

    def freeze_base(self) -> None:
        """Stop gradients into the base DiT and put it in eval mode."""
        self.base.requires_grad_(False)
        self.base.eval()

    def branch_parameters(self) -> list[nn.Parameter]:
        """Every parameter outside the base DiT (what stage 3 trains)."""
        return [p for name, p in self.named_parameters() if not name.startswith("base.")]

    def encode_control(self, control: Tensor) -> Tensor:
        """Control images ``(B, C, px, px)`` -> control tokens ``(B, T, hidden)`` (fixed over a sampling run)."""
        return self.proj(self.encoder(control))

    def forward(self, x: Tensor, t: Tensor, y: Tensor, control: Tensor | None = None) -> Tensor:
        """Epsilon for ``x`` (B, C, H, W); ``control`` None runs exactly the base DiT."""
        if control is None:
            return self.base(x, t, y)
        return self._run(x, t, y, self.encode_control(control))[0]

    def forward_cfg(self, x: Tensor, t: Tensor, y: Tensor, control: Tensor | None = None, *,
                    tokens: Tensor | None = None) -> tuple[Tensor, Tensor, list[Tensor]]:
        """One batched pass for guidance: ``(eps_cond, eps_uncond, residuals)``.

        The first B of the 2B rows get the control residuals, the last B take the plain base path;
        the control branch only runs on the B conditioned rows. Give the SD raster ``control`` or its
        precomputed :meth:`encode_control` ``tokens``. ``residuals`` holds the M tensors
        ``(B, T, hidden)`` added to the base blocks' outputs.
        """
        if tokens is None:
            tokens = self.encode_control(control)
        b = x.shape[0]
        eps, residuals = self._run(torch.cat([x, x]), torch.cat([t, t]), torch.cat([y, y]), tokens)
        return eps[:b], eps[b:], residuals

    def forward_cond(self, x: Tensor, t: Tensor, y: Tensor, *, tokens: Tensor) -> tuple[Tensor, list[Tensor]]:
        """The conditioned rows of :meth:`forward_cfg` alone, ``(eps_cond, residuals)``: all that guidance at
        w = 1 needs (``eps_uncond + 1 (eps_cond - eps_uncond) = eps_cond``), at the cost of one pass."""
        return self._run(x, t, y, tokens)

    def _run(self, x: Tensor, t: Tensor, y: Tensor, tokens: Tensor) -> tuple[Tensor, list[Tensor]]:
        """Base pass over all rows; the first ``len(tokens)`` rows get the control residuals."""
        n = tokens.shape[0]
        c = self.base.condition(t, y)
        h = self.base.embed_tokens(x)
        hc = h[:n] + tokens
        residuals = []
        for i, block in enumerate(self.base.blocks):
            h = block(h, c)
            if i < len(self.copies):
                hc = self.copies[i](hc, c[:n])
                residuals.append(self.zero[i](hc))
                h = torch.cat([h[:n] + residuals[-1], h[n:]])
        return self.base.final(h, c), residuals


def _validate(config: ControlConfig, dit: DiT) -> None:
    """Raise CmtoolError for a control config that does not fit ``dit``."""
    if not 1 <= config.num_blocks <= dit.config.depth:
        raise CmtoolError(f"control.num_blocks: must be in 1..{dit.config.depth} (the DiT depth), "
                          f"got {config.num_blocks}")
    if config.groups <= 0 or len(config.widths) != 4 or any(w <= 0 or w % config.groups for w in config.widths):
        raise CmtoolError(f"control.widths: need 4 positive multiples of groups ({config.groups}), "
                          f"got {list(config.widths)}")
    if config.image_px != 16 * dit.config.latent_size:
        raise CmtoolError(f"control.image_px: must be 16 x latent_size = {16 * dit.config.latent_size}, "
                          f"got {config.image_px}")
    if dit.config.latent_channels % 4:
        raise CmtoolError(f"dit.latent_channels: must be divisible by 4 for the control tokens, got "
                          f"{dit.config.latent_channels}")
    if config.layout not in (NO_LAYOUT, *LAYOUTS):
        raise CmtoolError(f"control.layout: choose {NO_LAYOUT}, {', '.join(LAYOUTS)}, got {config.layout!r}")
    wanted = SD_CHANNELS + (LAYOUT_CHANNELS if config.layout != NO_LAYOUT else 0)
    if config.in_channels != wanted:
        raise CmtoolError(f"control.in_channels: must be {wanted} with control.layout = {config.layout!r} "
                          f"({SD_CHANNELS} SD channels{f', {LAYOUT_CHANNELS} layout channels' if wanted > 3 else ''}), "
                          f"got {config.in_channels}")
