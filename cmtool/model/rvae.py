"""The raster-to-vector autoencoder (RVAE, stage 1), after SLEDGE.

The encoder is a torchvision ResNet trunk (random init, GroupNorm instead of BatchNorm) that maps the
HD raster (docs/data.md: "Frames and rasters") to a Gaussian posterior over a ``latent_channels x latent_size x latent_size``
latent. The decoder is DETR-style: one learned query per output slot (lines, green-light lines,
red-light lines) attends to the latent tokens through a pre-norm transformer decoder; per element type
an MLP head regresses the polyline points (ego-frame metres, tanh-bounded to the frame) and a linear
layer its existence logit. The same heads can read every decoder layer (DETR's auxiliary outputs,
used by the training loss only). With ``rvae.decoder = "graph"`` the decoder is
:class:`cmtool.model.graph.GraphDecoder` instead (polyline queries refined layer by layer, and
successor logits between lines).
"""

from __future__ import annotations

import math
from functools import partial

import numpy as np
import torch
from torch import Tensor, nn

from cmtool.core.errors import CmtoolError
from cmtool.core.geometry import bernstein_basis
from cmtool.model.config import RVAE_LIMITS, RVAEConfig, check_sizes
from cmtool.model.graph import GraphDecoder

ELEMENTS = ("lines", "green", "red")
BACKBONES = ("resnet18", "resnet34", "resnet50")
DECODERS = ("detr", "graph")
ENCODER_PREFIXES = ("trunk.", "to_latent.")  # state-dict keys of the encoder (raster -> posterior)
_STAGES = ("layer1", "layer2", "layer3", "layer4")  # the trunk through layer k has stride 2 ** (k + 1)


def encoder_trunk(backbone: str, in_channels: int, raster_px: int, latent_size: int,
                  stages: int = 4) -> tuple[nn.Sequential, int]:
    """A ResNet trunk of its first ``stages`` stages reducing ``raster_px`` to ``latent_size``; returns it and
    its output channels.

    Strides of the last stages kept are set to 1 until the total stride is ``raster_px / latent_size``.
    """
    if backbone not in BACKBONES:
        raise CmtoolError(f"rvae.backbone: must be one of {', '.join(BACKBONES)}, got {backbone!r}")
    if stages not in (2, 3, 4):
        raise CmtoolError(f"rvae.encoder_stages: must be 2, 3 or 4, got {stages}")
    full = 2 ** (stages + 1)  # the stride of the trunk with every stride kept
    stride = raster_px / latent_size
    drop = math.log2(full / stride) if stride > 0 else -1.0
    if raster_px % latent_size or drop != int(drop) or not 0 <= drop <= stages - 1:
        strides = ", ".join(str(full >> k) for k in range(stages - 1, -1, -1))
        raise CmtoolError(f"rvae.raster_px: {raster_px} cannot be reduced to latent_size {latent_size} by "
                          f"{stages} encoder stages: raster_px / latent_size must be {strides}")
    import torchvision  # here: 2-3 s to import, and a sampler's RVAE often holds no encoder

    net = getattr(torchvision.models, backbone)(weights=None, norm_layer=partial(nn.GroupNorm, 32))
    net.conv1 = nn.Conv2d(in_channels, 64, kernel_size=7, stride=2, padding=3, bias=False)
    kept = _STAGES[:stages]
    for name in kept[::-1][:int(drop)]:
        for m in getattr(net, name)[0].modules():
            if isinstance(m, nn.Conv2d) and m.stride == (2, 2):
                m.stride = (1, 1)
    trunk = nn.Sequential(net.conv1, net.bn1, net.relu, net.maxpool, *(getattr(net, name) for name in kept))
    return trunk, net.fc.in_features >> (4 - stages)


def sine_position_encoding(size: int, dim: int, temperature: float = 10000.0) -> Tensor:
    """Fixed 2D sine/cosine encoding (DETR) of a ``size x size`` grid -> (size * size, dim), row-major, on the CPU
    (as :func:`cmtool.model.dit.sincos_pos_embed_2d`)."""
    if dim % 4:
        raise CmtoolError(f"rvae.d_model: must be divisible by 4 for the 2D sine encoding, got {dim}")
    quarter = dim // 4
    freq = temperature ** (-torch.arange(quarter, dtype=torch.float64, device="cpu") / quarter)
    pos = torch.arange(size, dtype=torch.float64, device="cpu")[:, None] * freq  # (size, quarter)
    enc = torch.cat([pos.sin(), pos.cos()], dim=1)  # (size, dim / 2)
    rows = enc[:, None].expand(size, size, dim // 2)
    cols = enc[None, :].expand(size, size, dim // 2)
    return torch.cat([rows, cols], dim=-1).reshape(size * size, dim).float()


class LineHead(nn.Module):
    """Queries -> polylines (B, Q, P, 2) in metres and existence logits (B, Q).

    With ``control_points = 0`` the MLP regresses every point (tanh * frame / 2); with K >= 2 it
    regresses K Bézier control points the same way and the P points are sampled from that curve, so
    lines are smooth by construction (and stay in the frame, inside their control points' hull)."""

    def __init__(self, d_model: int, num_points: int, frame_m: float, control_points: int = 0):
        super().__init__()
        if control_points:
            if not 2 <= control_points <= num_points:
                raise CmtoolError(f"rvae.control_points: 0 or 2..{num_points}, got {control_points}")
            self.register_buffer("basis", torch.from_numpy(bernstein_basis(num_points, control_points)).float(),
                                 persistent=False)
        else:
            self.basis = None
        outputs = control_points or num_points
        self.points = nn.Sequential(nn.Linear(d_model, d_model), nn.ReLU(), nn.Linear(d_model, outputs * 2))
        self.logit = nn.Linear(d_model, 1)
        self.outputs = outputs
        self.half_frame = frame_m / 2.0

    def forward(self, h: Tensor) -> tuple[Tensor, Tensor]:
        b, q = h.shape[:2]
        points = self.points(h).tanh().reshape(b, q, self.outputs, 2) * self.half_frame
        if self.basis is not None:
            points = torch.einsum("pk,bqkd->bqpd", self.basis.to(points.dtype), points)
        return points, self.logit(h).squeeze(-1)


class RVAE(nn.Module):
    """HD raster (B, C, H, W) -> latent posterior (B, 64, 8, 8) -> scene vectors."""

    def __init__(self, config: RVAEConfig, encoder: bool = True):
        super().__init__()
        check_sizes(config, "rvae", RVAE_LIMITS)
        self.config = config
        self.trunk = self.to_latent = None  # without an encoder (the released decoder-only weights)
        if encoder:
            self.trunk, trunk_channels = encoder_trunk(config.backbone, config.in_channels, config.raster_px,
                                                       config.latent_size, config.encoder_stages)
            self.to_latent = nn.Conv2d(trunk_channels, 2 * config.latent_channels, kernel_size=3, padding=1)
        if config.decoder not in DECODERS:
            raise CmtoolError(f"rvae.decoder: must be one of {', '.join(DECODERS)}, got {config.decoder!r}")
        if config.decoder == "graph":
            if config.control_points:
                raise CmtoolError("rvae.control_points: the graph decoder refines free points; set it to 0")
            self.graph = GraphDecoder(config, sine_position_encoding(config.latent_size, config.d_model), ELEMENTS)
            return
        self.graph = None
        self.token_proj = nn.Linear(config.latent_channels, config.d_model)
        self.register_buffer("pos", sine_position_encoding(config.latent_size, config.d_model), persistent=False)
        self.query = nn.Embedding(sum(config.queries.values()), config.d_model)
        layer = nn.TransformerDecoderLayer(config.d_model, config.heads, config.ffn, config.dropout, batch_first=True,
                                           norm_first=True)
        self.decoder = nn.TransformerDecoder(layer, config.decoder_layers, norm=nn.LayerNorm(config.d_model))
        self.heads = nn.ModuleDict({name: LineHead(config.d_model, config.num_points, config.frame_m,
                                                   config.control_points)
                                    for name in ELEMENTS})

    def encode(self, raster: Tensor) -> tuple[Tensor, Tensor]:
        """Raster (B, C, H, W) -> posterior mean and log-variance, each (B, latent_channels, S, S)."""
        if self.trunk is None:
            raise CmtoolError("this RVAE holds its decoder only (a packed decoder); encoding HD rasters needs a full "
                              "RVAE checkpoint (`cmtool train rvae`, `cmtool train encoder`, or weights packed with "
                              "--encoder, as the shipped ones are)")
        if tuple(raster.shape[1:]) != (self.config.in_channels, self.config.raster_px, self.config.raster_px):
            raise ValueError(f"expected rasters of shape (B, {self.config.in_channels}, {self.config.raster_px}, "
                             f"{self.config.raster_px}), got {tuple(raster.shape)}")
        mean, logvar = self.to_latent(self.trunk(raster)).chunk(2, dim=1)
        return mean, logvar

    def decode(self, z: Tensor, aux: bool = False, denoise: Tensor | None = None) -> dict[str, Tensor]:
        """Latent (B, latent_channels, S, S) -> {"lines", "lines_logit", "green", "green_logit", "red", "red_logit"}.

        With ``aux``, also ``"aux"``: such dicts read from each earlier decoder layer, first to last. The
        graph decoder adds ``"succ_logit"`` (B, L, L): line i flows into line j, and with ``denoise``
        (noised true lines, training only) the denoising queries' outputs (:class:`GraphDecoder`)."""
        if self.graph is not None:
            return self.graph(z, aux, denoise)
        if denoise is not None:
            raise CmtoolError("rvae_loss.denoise_weight: denoising queries need rvae.decoder = \"graph\"")
        b = z.shape[0]
        memory = self.token_proj(z.flatten(2).transpose(1, 2)) + self.pos
        h = self.query.weight.expand(b, -1, -1)
        earlier = []
        for i, layer in enumerate(self.decoder.layers):
            h = layer(h, memory)
            if aux and i < len(self.decoder.layers) - 1:
                earlier.append(self._read(self.decoder.norm(h)))
        out = self._read(self.decoder.norm(h))
        if aux:
            out["aux"] = earlier
        return out

    def _read(self, h: Tensor) -> dict[str, Tensor]:
        """Decoder states (B, Q, d_model) -> the heads' polylines and logits per element type."""
        out = {}
        for name, part in zip(ELEMENTS, h.split(list(self.config.queries.values()), dim=1)):
            out[name], out[f"{name}_logit"] = self.heads[name](part)
        return out

    def forward(self, raster: Tensor | None, sample: bool = True,
                posterior: tuple[Tensor, Tensor] | None = None,
                aux: bool = False, denoise: Tensor | None = None) -> tuple[dict[str, Tensor], Tensor, Tensor]:
        """Encode, take z (reparameterised sample, or the mean when ``sample`` is False), decode.

        ``posterior``: a (mean, logvar) pair to decode instead of encoding ``raster`` (decoder
        fine-tuning on a latent cache); ``aux``, ``denoise``: see :meth:`decode`."""
        mean, logvar = posterior if posterior is not None else self.encode(raster)
        z = mean + torch.exp(0.5 * logvar) * torch.randn_like(mean) if sample else mean
        return self.decode(z, aux, denoise), mean, logvar


def same_encoder(a: dict[str, Tensor], b: dict[str, Tensor]) -> bool:
    """Whether two RVAE state dicts hold the same encoder (and so encode to the same latent space)."""
    enc_a, enc_b = ({k: v for k, v in t.items() if k.startswith(ENCODER_PREFIXES)} for t in (a, b))
    return enc_a.keys() == enc_b.keys() and all(torch.equal(v.cpu(), enc_b[k].cpu()) for k, v in enc_a.items())


def decoded_elements(decoded: dict[str, Tensor], threshold: float = 0.5) -> list[dict[str, np.ndarray]]:
    """Per batch item, the polylines whose existence probability exceeds ``threshold``:
    ``{"lines": (n, P, 2) float32, "green": ..., "red": ...}``; from the graph decoder also
    ``"successors"`` (E, 2) int64, pairs of kept lines (indices into ``"lines"``) whose successor
    probability exceeds 0.5."""
    keep = {name: (torch.sigmoid(decoded[f"{name}_logit"]) > threshold).cpu().numpy() for name in ELEMENTS}
    points = {name: decoded[name].detach().float().cpu().numpy() for name in ELEMENTS}
    out = [{name: points[name][i][keep[name][i]] for name in ELEMENTS} for i in range(len(points["lines"]))]
    if "succ_logit" in decoded:
        linked = (decoded["succ_logit"].detach().float() > 0).cpu().numpy()
        for item, kept, links in zip(out, keep["lines"], linked):
            idx = np.flatnonzero(kept)
            pairs = np.argwhere(links[np.ix_(idx, idx)])
            item["successors"] = pairs[pairs[:, 0] != pairs[:, 1]].astype(np.int64).reshape(-1, 2)
    return out
