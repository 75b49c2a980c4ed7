"""Diffusion Transformer over the RVAE latent (stage 2), after Peebles & Xie's DiT as SLEDGE uses it.

The latent ``(B, 64, 8, 8)`` is cut into patches of size 1, i.e. 64 tokens of 64 channels, with
fixed 2D sine-cosine positions. Timestep and city label are summed into one conditioning vector
``c`` that drives adaLN-Zero modulation in every block; modulation layers and the final projection
start at zero, so a fresh model predicts ``eps = 0``. Label ``num_classes`` is the null label used
for label dropout (done by the training code) and for city-free sampling. The model predicts
epsilon only (no learned variance).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from cmtool.model.config import DiTConfig

FREQ_DIM = 256


def sincos_pos_embed_2d(dim: int, grid: int) -> Tensor:
    """Fixed 2D sine-cosine embedding ``(grid * grid, dim)``, tokens in row-major order, on the CPU (also inside a
    meta-device block, where torch's ``arange`` imports its compiler: 2-3 s of every checkpoint load).

    The first half of the channels encodes the row, the second half the column.
    """
    omega = 1.0 / 10000 ** (torch.arange(dim // 4, dtype=torch.float64, device="cpu") / (dim // 4))
    pos = torch.arange(grid, dtype=torch.float64, device="cpu")
    rows, cols = torch.meshgrid(pos, pos, indexing="ij")

    def embed(p: Tensor) -> Tensor:
        angles = p.reshape(-1, 1) * omega
        return torch.cat([angles.sin(), angles.cos()], dim=1)

    return torch.cat([embed(rows), embed(cols)], dim=1).float()


def timestep_embedding(t: Tensor, dim: int = FREQ_DIM, max_period: float = 10000.0) -> Tensor:
    """Sinusoidal embedding ``(B, dim)`` of (possibly fractional) timesteps ``t`` (B,)."""
    half = dim // 2
    freqs = torch.exp(-math.log(max_period) * torch.arange(half, dtype=torch.float32, device=t.device) / half)
    args = t.float()[:, None] * freqs[None]
    return torch.cat([args.cos(), args.sin()], dim=1)


def modulate(x: Tensor, shift: Tensor, scale: Tensor) -> Tensor:
    """adaLN modulation of tokens ``x`` (B, T, D) by per-sample ``shift``/``scale`` (B, D)."""
    return x * (1 + scale[:, None]) + shift[:, None]


class Attention(nn.Module):
    """Multi-head self-attention with fused qkv, via ``scaled_dot_product_attention``."""

    def __init__(self, hidden: int, heads: int):
        super().__init__()
        self.heads = heads
        self.qkv = nn.Linear(hidden, 3 * hidden)
        self.proj = nn.Linear(hidden, hidden)

    def forward(self, x: Tensor) -> Tensor:
        b, n, d = x.shape
        q, k, v = self.qkv(x).reshape(b, n, 3, self.heads, d // self.heads).permute(2, 0, 3, 1, 4)
        return self.proj(F.scaled_dot_product_attention(q, k, v).transpose(1, 2).reshape(b, n, d))


class Mlp(nn.Module):
    """Two-layer feed-forward network with tanh-GELU."""

    def __init__(self, hidden: int, inner: int):
        super().__init__()
        self.fc1 = nn.Linear(hidden, inner)
        self.fc2 = nn.Linear(inner, hidden)

    def forward(self, x: Tensor) -> Tensor:
        return self.fc2(F.gelu(self.fc1(x), approximate="tanh"))


class DiTBlock(nn.Module):
    """Transformer block with adaLN-Zero: shift, scale and gate of both branches come from ``c``."""

    def __init__(self, hidden: int, heads: int, mlp_ratio: float):
        super().__init__()
        self.norm1 = nn.LayerNorm(hidden, elementwise_affine=False, eps=1e-6)
        self.attn = Attention(hidden, heads)
        self.norm2 = nn.LayerNorm(hidden, elementwise_affine=False, eps=1e-6)
        self.mlp = Mlp(hidden, int(hidden * mlp_ratio))
        self.ada = nn.Sequential(nn.SiLU(), nn.Linear(hidden, 6 * hidden))

    def forward(self, x: Tensor, c: Tensor) -> Tensor:
        shift1, scale1, gate1, shift2, scale2, gate2 = self.ada(c).chunk(6, dim=1)
        x = x + gate1[:, None] * self.attn(modulate(self.norm1(x), shift1, scale1))
        return x + gate2[:, None] * self.mlp(modulate(self.norm2(x), shift2, scale2))


class FinalLayer(nn.Module):
    """adaLN-modulated LayerNorm and a linear map from tokens back to latent channels."""

    def __init__(self, hidden: int, out_channels: int):
        super().__init__()
        self.norm = nn.LayerNorm(hidden, elementwise_affine=False, eps=1e-6)
        self.linear = nn.Linear(hidden, out_channels)
        self.ada = nn.Sequential(nn.SiLU(), nn.Linear(hidden, 2 * hidden))

    def forward(self, x: Tensor, c: Tensor) -> Tensor:
        shift, scale = self.ada(c).chunk(2, dim=1)
        return self.linear(modulate(self.norm(x), shift, scale))


class DiT(nn.Module):
    """Epsilon-predicting DiT: ``forward(x, t, y)`` maps a noisy latent to its noise estimate."""

    def __init__(self, config: DiTConfig):
        super().__init__()
        self.config = config = config.resolved()
        h = config.hidden
        self.patch = nn.Linear(config.latent_channels, h)
        self.register_buffer("pos", sincos_pos_embed_2d(h, config.latent_size), persistent=False)
        self.t_mlp = nn.Sequential(nn.Linear(FREQ_DIM, h), nn.SiLU(), nn.Linear(h, h))
        self.labels = nn.Embedding(config.num_classes + 1, h)
        self.blocks = nn.ModuleList(DiTBlock(h, config.heads, config.mlp_ratio) for _ in range(config.depth))
        self.final_layer = FinalLayer(h, config.latent_channels)
        self._init_weights()

    def _init_weights(self) -> None:
        for m in self.modules():
            if isinstance(m, nn.Linear):
                nn.init.xavier_uniform_(m.weight)
                nn.init.zeros_(m.bias)
        nn.init.normal_(self.labels.weight, std=0.02)
        for layer in (self.t_mlp[0], self.t_mlp[2]):
            nn.init.normal_(layer.weight, std=0.02)
        for block in self.blocks:
            nn.init.zeros_(block.ada[-1].weight)
            nn.init.zeros_(block.ada[-1].bias)
        for layer in (self.final_layer.ada[-1], self.final_layer.linear):
            nn.init.zeros_(layer.weight)
            nn.init.zeros_(layer.bias)

    @property
    def latent_shape(self) -> tuple[int, int, int]:
        """Shape ``(C, H, W)`` of one latent."""
        return self.config.latent_channels, self.config.latent_size, self.config.latent_size

    @property
    def null_label(self) -> int:
        """The label index meaning "no city"."""
        return self.config.num_classes

    def embed_tokens(self, x: Tensor) -> Tensor:
        """Latent ``(B, C, H, W)`` -> tokens ``(B, H*W, hidden)`` with positions added."""
        return self.patch(x.flatten(2).transpose(1, 2)) + self.pos

    def condition(self, t: Tensor, y: Tensor) -> Tensor:
        """Conditioning vector ``(B, hidden)`` from timesteps ``t`` (B,) and labels ``y`` (B,)."""
        return self.t_mlp(timestep_embedding(t)) + self.labels(y)

    def final(self, h: Tensor, c: Tensor) -> Tensor:
        """Tokens ``(B, T, hidden)`` -> epsilon ``(B, C, H, W)``."""
        out = self.final_layer(h, c)
        return out.transpose(1, 2).reshape(out.shape[0], *self.latent_shape)

    def forward(self, x: Tensor, t: Tensor, y: Tensor) -> Tensor:
        c = self.condition(t, y)
        h = self.embed_tokens(x)
        for block in self.blocks:
            h = block(h, c)
        return self.final(h, c)
