"""Model and schedule configurations: plain dataclasses, built from recipe TOML tables and stored
in checkpoint configs. No torch here, so reading a recipe stays cheap."""

from __future__ import annotations

from dataclasses import dataclass, replace

from cmtool.core.errors import CmtoolError
from cmtool.data.sd_raster import ENCODING, ENCODINGS


def check_sizes(config, section: str, limits: dict[str, int]) -> None:
    """Refuse a model size beyond ``limits`` (field -> largest value): far past any model cmtool trains, and a
    number that would take hours to build or more memory than a machine has."""
    for key, most in limits.items():
        values = getattr(config, key)
        for value in values if isinstance(values, tuple) else (values,):
            if value > most:
                raise CmtoolError(f"{section}.{key}: {value} is more than cmtool builds (at most {most})")


RVAE_LIMITS = {"in_channels": 64, "raster_px": 4096, "latent_channels": 4096, "latent_size": 256, "d_model": 16384,
               "decoder_layers": 64, "heads": 1024, "ffn": 65536, "num_lines": 10_000, "num_lights": 10_000,
               "num_points": 10_000}
DIT_LIMITS = {"depth": 256, "hidden": 16384, "heads": 1024, "latent_channels": 4096, "latent_size": 256,
              "num_classes": 100_000}
CONTROL_LIMITS = {"num_blocks": 256, "in_channels": 64, "image_px": 4096, "widths": 16384}


@dataclass
class RVAEConfig:
    """RVAE hyper-parameters (plain fields: built from a TOML table)."""

    backbone: str = "resnet18"
    encoder_stages: int = 4  # ResNet stages the encoder keeps: 3 drops layer4 (about half the compute)
    in_channels: int = 6
    raster_px: int = 128
    latent_channels: int = 64
    latent_size: int = 8
    d_model: int = 256
    decoder_layers: int = 4
    heads: int = 8
    ffn: int = 1024
    dropout: float = 0.1
    num_lines: int = 50  # line queries: at least the dataset's num_lines (training refuses fewer)
    num_lights: int = 10
    num_points: int = 20
    control_points: int = 0  # 0: the heads regress every point; K >= 2: K Bézier control points per line
    decoder: str = "detr"  # detr: SLEDGE's (learned queries regress points); graph: reference polylines refined
    #                        layer by layer on an upsampled feature map, plus a successor head (cmtool.model.graph)
    frame_m: float = 64.0

    @property
    def queries(self) -> dict[str, int]:
        """Number of decoder queries per element type."""
        return {"lines": self.num_lines, "green": self.num_lights, "red": self.num_lights}


@dataclass
class RVAELossConfig:
    """Loss and matching-cost weights (SLEDGE's, see cmtool.model.rvae_loss) and the frame size."""

    l1_weight: float = 64.0
    existence_weight: float = 5.0
    kl_weight: float = 0.1
    aux_weight: float = 0.0  # weight of the same loss on each earlier decoder layer (0: final layer only)
    direction_weight: float = 0.0  # matched lines' segment directions, 1 - cosine (MapTR's edge-direction loss)
    successor_weight: float = 0.0  # successor BCE between matched lines (graph decoder)
    denoise_weight: float = 0.0  # graph decoder: weight of the denoising queries' loss (0: none)
    denoise_m: float = 2.0  # noise of the denoising queries' starts: line shift sigma (points: half of it)
    frame_m: float = 64.0


# DiT sizes (depth, hidden, heads). XL uses hidden 1024 (about 532M parameters, the
# paper reports about 487M); B lands at about 130M (SLEDGE reports about 138M).
SIZES = {"tiny": (8, 192, 4), "S": (12, 384, 6), "B": (12, 768, 12), "L": (24, 1024, 16), "XL": (28, 1024, 16)}


@dataclass
class DiTConfig:
    """DiT hyper-parameters; ``depth``/``hidden``/``heads`` override ``SIZES[size]`` when > 0."""

    size: str = "tiny"
    depth: int = 0
    hidden: int = 0
    heads: int = 0
    mlp_ratio: float = 4.0
    latent_channels: int = 64
    latent_size: int = 8
    num_classes: int = 3

    def resolved(self) -> DiTConfig:
        """A copy with depth/hidden/heads filled from ``SIZES``, validated."""
        if self.size not in SIZES:
            raise CmtoolError(f"dit.size: unknown size {self.size!r} (choose from {', '.join(SIZES)})")
        depth, hidden, heads = SIZES[self.size]
        config = replace(self, depth=self.depth or depth, hidden=self.hidden or hidden, heads=self.heads or heads)
        if min(config.depth, config.hidden, config.heads, config.latent_channels, config.latent_size,
               config.num_classes) <= 0:
            raise CmtoolError("dit: depth, hidden, heads, latent_channels, latent_size, num_classes must be > 0")
        if config.hidden % config.heads or config.hidden % 4:
            raise CmtoolError(f"dit.hidden: {config.hidden} must be divisible by 4 and by heads ({config.heads})")
        if config.mlp_ratio <= 0:
            raise CmtoolError(f"dit.mlp_ratio: must be > 0, got {config.mlp_ratio}")
        check_sizes(config, "dit", DIT_LIMITS | {"mlp_ratio": 64})
        return config


@dataclass
class ScheduleConfig:
    """Forward-process schedule: ``kind`` is "linear" (betas beta_start..beta_end) or "cosine"."""

    kind: str = "linear"
    train_steps: int = 1000
    beta_start: float = 1e-4
    beta_end: float = 0.02


PAPER_CONTROL_WIDTHS = (256, 512, 1024, 1024)


@dataclass
class ControlConfig:
    """Control branch hyper-parameters; the defaults suit the tiny DiT.

    The paper-sized branch on DiT-B uses ``widths=PAPER_CONTROL_WIDTHS`` (about 234M parameters in
    total, base included).
    """

    num_blocks: int = 6
    in_channels: int = 3  # 3 SD raster channels, + 2 with a layout
    image_px: int = 128
    widths: tuple[int, ...] = (32, 64, 128, 192)
    groups: int = 32
    layout: str = "none"  # "rules": the control image carries the rule layout's lanes too (cmtool.data.layouts)
    sd_encoding: int = ENCODING  # the SD raster encoding the branch reads (cmtool.data.sd_raster; 1: no road class)

    def __post_init__(self) -> None:
        self.widths = tuple(self.widths)
        check_sizes(self, "control", CONTROL_LIMITS)
        if self.sd_encoding not in ENCODINGS:
            raise CmtoolError(f"control.sd_encoding: {self.sd_encoding} is not an SD raster encoding of this cmtool "
                              f"({', '.join(f'{k}: {v}' for k, v in ENCODINGS.items())})")
