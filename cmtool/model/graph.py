"""The RVAE's graph decoder (``rvae.decoder = "graph"``): polyline queries refined layer by layer, and a
successor head, so that it learns in fewer steps and outputs a lane graph.

Ideas taken from MapTR (polyline queries, point and edge-direction losses) and Deformable DETR
(reference points refined layer by layer, each layer a prediction trained on its own), shaped for a
64-token latent:

- a small convolutional decoder upsamples the latent to a feature map of 4 x its size, aligned with
  the raster (row 0 is the front edge, column 0 the left edge);
- every query (lines, then green- and red-light lines) holds a reference polyline of P points in
  half-frame units; each layer samples the feature map at those points (bilinear), adds what it
  read to the query, runs self-attention among the queries and cross-attention to the latent tokens,
  and moves the points by a predicted offset (in atanh space; as in Deformable DETR, the points a
  layer starts from are detached from the layer before); the offset heads start at zero; the query
  also gets an embedding of where its points are (DAB-DETR's positional queries);
- in training, denoising queries (DN-DETR) start from noised copies of the true lines and learn to
  return to them without matching, which gives every step a positive example per true line; the
  queries that are matched cannot attend to them;
- the successor head scores "lane i flows into lane j" from the two lanes' states and the gap
  between i's last and j's first point; it starts out linking lanes whose ends touch.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from cmtool.model.config import RVAEConfig

FEATURES = 32  # channels of the upsampled feature map the queries sample
_GAP_SCALE = -1.0  # initial successor logit per metre of gap between a lane's end and the next lane's start
_GAP_BIAS = 2.0  # initial successor logit of touching lanes


class GraphDecoder(nn.Module):
    """Latent (B, C, S, S) -> per element type polylines (B, Q, P, 2) in metres and existence logits
    (B, Q), and ``succ_logit`` (B, L, L) over the line queries."""

    def __init__(self, config: RVAEConfig, positions: Tensor, elements: tuple[str, ...]):
        super().__init__()
        d, c, p = config.d_model, config.latent_channels, config.num_points
        self.config, self.elements, self.sizes = config, elements, [config.queries[e] for e in elements]
        self.token_proj = nn.Linear(c, d)
        self.register_buffer("pos", positions, persistent=False)
        self.features = nn.Sequential(
            nn.Conv2d(c, d, 3, padding=1), nn.GroupNorm(8, d), nn.GELU(),
            nn.Upsample(scale_factor=2, mode="bilinear"), nn.Conv2d(d, d, 3, padding=1), nn.GroupNorm(8, d), nn.GELU(),
            nn.Upsample(scale_factor=2, mode="bilinear"), nn.Conv2d(d, FEATURES, 3, padding=1))
        self.query = nn.Embedding(sum(self.sizes), d)
        self.dn_query = nn.Parameter(torch.zeros(d))
        self.where = nn.Sequential(nn.Linear(p * 2, d), nn.ReLU(), nn.Linear(d, d))
        self.first_points = nn.Linear(d, p * 2)
        self.read_points = nn.ModuleList(nn.Linear(p * FEATURES, d) for _ in range(config.decoder_layers))
        self.layers = nn.ModuleList(
            nn.TransformerDecoderLayer(d, config.heads, config.ffn, config.dropout, batch_first=True, norm_first=True)
            for _ in range(config.decoder_layers))
        self.norm = nn.LayerNorm(d)
        self.offsets = nn.ModuleList(nn.Sequential(nn.Linear(d, d), nn.ReLU(), nn.Linear(d, p * 2))
                                     for _ in range(config.decoder_layers))
        for head in self.offsets:
            nn.init.zeros_(head[-1].weight)
            nn.init.zeros_(head[-1].bias)
        self.logits = nn.ModuleDict({name: nn.Linear(d, 1) for name in elements})
        self.succ_out, self.succ_in = nn.Linear(d, d), nn.Linear(d, d)
        self.succ_gap = nn.Parameter(torch.tensor(_GAP_SCALE))
        self.succ_bias = nn.Parameter(torch.tensor(_GAP_BIAS))

    def forward(self, z: Tensor, aux: bool = False, denoise: Tensor | None = None) -> dict:
        """``denoise``: noised true lines (B, N, P, 2) in metres to start denoising queries from; their
        outputs, one dict ``{"lines", "succ_logit"}`` per layer, come back under ``"denoise"``."""
        b, p, q = z.shape[0], self.config.num_points, sum(self.sizes)
        half = self.config.frame_m / 2.0
        memory = self.token_proj(z.flatten(2).transpose(1, 2)) + self.pos
        # channels-last: on a CPU, bilinear upsampling of a (B, C, H, W)-contiguous map is about 9x slower
        feat = self.features(z.contiguous(memory_format=torch.channels_last))
        h = self.query.weight.expand(b, -1, -1)
        # the points stay float32 under bf16 autocast: bf16's 8-bit mantissa makes the refinement jagged
        ref = torch.tanh(self.first_points(self.query.weight).float()).reshape(1, -1, p, 2).expand(b, -1, -1, -1)
        mask = None
        if denoise is not None:
            n = denoise.shape[1]
            h = torch.cat([h, self.dn_query.expand(b, n, -1)], dim=1)
            ref = torch.cat([ref, (denoise.float() / half).clamp(-0.98, 0.98)], dim=1)
            mask = torch.zeros(q + n, q + n, dtype=torch.bool, device=z.device)
            mask[:q, q:] = True  # the matched queries do not see the denoising ones (they hold the answer)
        outputs = []
        for layer, read, offset in zip(self.layers, self.read_points, self.offsets):
            h = h + read(sample_points(feat, ref).flatten(2)) + self.where(ref.flatten(2))
            h = layer(h, memory, tgt_mask=mask)
            state = self.norm(h)
            moved = torch.tanh(torch.atanh(ref.clamp(-0.999, 0.999)) + offset(state).float().reshape(b, -1, p, 2))
            outputs.append((state, moved))
            ref = moved.detach()  # the next layer refines these points without back-propagating into them
        out = self._read(*(t[:, :q] for t in outputs[-1]))
        if aux:
            out["aux"] = [self._read(state[:, :q], points[:, :q]) for state, points in outputs[:-1]]
        if denoise is not None:
            out["denoise"] = [{"lines": points[:, q:] * half,
                               "succ_logit": self.successor_logits(state[:, q:], points[:, q:] * half)}
                              for state, points in outputs]
        return out

    def _read(self, state: Tensor, ref: Tensor) -> dict[str, Tensor]:
        """States (B, Q, d) and reference polylines (B, Q, P, 2) -> the element dict of one layer."""
        out = {}
        half = self.config.frame_m / 2.0
        for name, h, points in zip(self.elements, state.split(self.sizes, dim=1), ref.split(self.sizes, dim=1)):
            out[name], out[f"{name}_logit"] = points * half, self.logits[name](h).squeeze(-1)
        out["succ_logit"] = self.successor_logits(state[:, :self.sizes[0]], out[self.elements[0]])
        return out

    def successor_logits(self, h: Tensor, lines: Tensor) -> Tensor:
        """Logit (B, L, L) that line i flows into line j: state affinity plus a (learned) penalty on the
        gap in metres between i's last and j's first point (detached: the link does not pull lanes)."""
        affinity = self.succ_out(h) @ self.succ_in(h).transpose(1, 2) / math.sqrt(h.shape[-1])
        gap = torch.cdist(lines[:, :, -1].detach().float(), lines[:, :, 0].detach().float()).to(h.dtype)
        return affinity + self.succ_gap * gap + self.succ_bias


def sample_points(feat: Tensor, points: Tensor) -> Tensor:
    """Bilinear samples (B, Q, P, F) of a raster-aligned feature map (B, F, H, W) at ego-frame points
    (B, Q, P, 2) in half-frame units (x forward = up, y left = left)."""
    grid = torch.stack([-points[..., 1], -points[..., 0]], dim=-1).float()  # (column, row) in [-1, 1]
    return F.grid_sample(feat.float(), grid, align_corners=False).permute(0, 2, 3, 1)


def noised_lines(lines: Tensor, sigma_m: float) -> Tensor:
    """Denoising-query starts: each polyline (B, L, P, 2) moved as a whole by N(0, sigma_m) per axis and
    each point by N(0, sigma_m / 2) more."""
    shift = torch.randn_like(lines[:, :, :1]) * sigma_m
    return lines + shift + torch.randn_like(lines) * (sigma_m / 2.0)
