"""Recipes: TOML files that fix every setting of a run: the dataset (``[data]``, :mod:`cmtool.data.recipe`),
the models, their training and the whole chain (``[pipeline]``).

Every field has a default; a recipe file overrides any of them. A recipe has one table per section
(a new section is a new dataclass and one more field of :class:`Recipe`).
Unknown keys and wrong types raise :class:`CmtoolError` naming the file and the key::

    [data]
    name = "tiny"
    maps_per_city = 1
    [data.sd_jitter]
    offset_m = 1.0
    [[data.real_maps]]
    format = "av2"
    path = "../shared/data/av2/*.json"
    split = "test"
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

from cmtool.core.errors import CmtoolError
from cmtool.core.tables import from_table, read_toml, toml_fields
from cmtool.data.recipe import DataRecipe, RealMapsRecipe
from cmtool.diffusion.settings import SamplerSettings
from cmtool.model.config import ControlConfig, DiTConfig, RVAEConfig, RVAELossConfig, ScheduleConfig
from cmtool.train import PRECISIONS


@dataclass
class TrainRecipe:
    """How a stage trains: inputs, output, optimiser, schedule, checkpoints (``[train]``)."""

    stage: str = ""  # rvae | decoder | encoder | dit | controlnet: the stage this recipe trains
    data: str = ""  # dataset folder (cmtool data build --out)
    out: str = ""  # run folder [default: --out]
    rvae: str = ""  # RVAE run folder with its latent cache (decoder, dit, controlnet stages); encoder stage: the
    #                 RVAE (run or packed weights) whose decoder the new encoder is trained for
    dit: str = ""  # DiT run or checkpoint folder (controlnet stage)
    branch_from: str = ""  # controlnet: start the control branch from this ControlMap run or checkpoint
    #                        (same [control]), e.g. after its DiT was trained further; "" = zero-initialised
    init_from: str = ""  # dit: start from this DiT's weights, or a ControlMap's frozen DiT (e.g. the shipped
    #                      cmtool/weights/controlmap), to train it further on the same latents; "" = random
    steps: int = 1000
    batch_size: int = 32  # global: split over the processes of a torchrun launch
    lr: float = 1e-4
    lr_schedule: str = "cosine"  # cosine | constant (after the warm-up)
    min_lr_ratio: float = 0.1  # the cosine decays to lr * min_lr_ratio
    warmup_steps: int = 100
    weight_decay: float = 0.0
    betas: list[float] = field(default_factory=lambda: [0.9, 0.999])
    grad_clip: float = 1.0
    ema_decay: float = 0.999
    label_dropout: float = 0.2  # probability of replacing the city label by the null label (dit, controlnet)
    mirror: float = 0.0  # dit, controlnet: probability of a scene mirrored left-right, labelled with a city
    #                      driving on the other side (teaches the label the driving side; never dropped)
    sd_shift_m: float = 0.0  # controlnet: move each SD raster sideways by up to this many metres (uniform, whole
    #                          pixels), so that where the road lies in the frame does not give the driving side away
    layout_dropout: float = 0.0  # controlnet with control.layout: share of scenes shown without their layout
    #                              channels, as an SD picture comes (no map to lay lanes out on)
    min_snr_gamma: float = 0.0  # dit, controlnet: Min-SNR-gamma loss weights min(SNR, gamma) / SNR (Hang et al.,
    #                             ICCV 2023, use 5): nearly clean timesteps (SNR > gamma) count less; 0 = plain MSE
    ckpt_every: int = 500
    keep: int = 2  # checkpoints kept in the run folder
    log_every: int = 10  # steps between scalar logs in the Rerun recording
    preview_every: int = 500  # steps between decoded previews (0: off)
    preview_steps: int = 25  # sampler steps of the previews (dit, controlnet)
    workers: int = 0  # DataLoader worker processes
    precision: str = "auto"  # auto: bf16 autocast where the device computes bf16 natively (CUDA 8.0+, a CPU with
    #                          AVX512-BF16 or AMX) and a test block runs faster in it, else fp32; the run says which
    #                          and why | bf16: bf16 autocast on any device | fp32: none
    seed: int = 0

    def check(self, where: str) -> None:
        for key in ("steps", "batch_size", "lr", "ckpt_every", "keep", "log_every", "preview_steps"):
            if getattr(self, key) <= 0:
                raise CmtoolError(f"{where}: train.{key}: must be positive, got {getattr(self, key)}")
        for key in ("warmup_steps", "weight_decay", "grad_clip", "preview_every", "workers", "sd_shift_m",
                    "min_snr_gamma"):
            if getattr(self, key) < 0:
                raise CmtoolError(f"{where}: train.{key}: must not be negative, got {getattr(self, key)}")
        if self.stage not in ("", "rvae", "decoder", "encoder", "dit", "controlnet"):
            raise CmtoolError(f"{where}: train.stage: expected rvae, decoder, encoder, dit or controlnet, "
                              f"got {self.stage!r}")
        if self.mirror > 0 and self.stage not in ("", "dit", "controlnet"):
            raise CmtoolError(f"{where}: train.mirror: mirrored scenes are a dit- and controlnet-stage option")
        if self.min_snr_gamma and self.stage not in ("", "dit", "controlnet"):
            raise CmtoolError(f"{where}: train.min_snr_gamma: a dit- and controlnet-stage option (diffusion loss)")
        if self.sd_shift_m and self.stage not in ("", "controlnet"):
            raise CmtoolError(f"{where}: train.sd_shift_m: SD rasters are a controlnet-stage input")
        if self.layout_dropout and self.stage not in ("", "controlnet"):
            raise CmtoolError(f"{where}: train.layout_dropout: layout channels are a controlnet-stage input")
        if self.branch_from and self.stage not in ("", "controlnet"):
            raise CmtoolError(f"{where}: train.branch_from: a control branch is a controlnet-stage option")
        if self.init_from and self.stage not in ("", "dit"):
            raise CmtoolError(f"{where}: train.init_from: a dit-stage option (the controlnet stage has branch_from)")
        if self.precision not in PRECISIONS:
            raise CmtoolError(f"{where}: train.precision: expected one of {', '.join(PRECISIONS)}, "
                              f"got {self.precision!r}")
        if self.lr_schedule not in ("cosine", "constant"):
            raise CmtoolError(f"{where}: train.lr_schedule: expected cosine or constant, got {self.lr_schedule!r}")
        for key in ("ema_decay", "label_dropout", "mirror", "min_lr_ratio", "layout_dropout"):
            if not 0.0 <= getattr(self, key) <= 1.0:
                raise CmtoolError(f"{where}: train.{key}: must lie in [0, 1], got {getattr(self, key)}")
        if len(self.betas) != 2 or not all(0.0 <= b < 1.0 for b in self.betas):
            raise CmtoolError(f"{where}: train.betas: expected two values in [0, 1), got {self.betas}")


@dataclass(kw_only=True)
class PipelineEval(SamplerSettings):
    """``[pipeline.eval]``: how ``cmtool train pipeline`` evaluates the packed weights (as ``cmtool eval``): the
    sampler settings and the scenes."""

    split: str = "test"
    n: int = 512
    batch: int = 64
    features: bool = False  # the ResNet-50 recall metrics (slow on a CPU)
    rrd_samples: int = 16


@dataclass
class PipelineRecipe:
    """``[pipeline]``: the recipe of every stage of ``cmtool train pipeline`` (paths relative to this file)."""

    data: str = ""
    rvae: str = ""
    decoder: str = ""  # optional: the RVAE's decoder trained further ("" = none)
    dit: str = ""
    controlnet: str = ""
    precision: str = ""  # of every training stage ("" = each recipe's own train.precision)
    eval: PipelineEval = field(default_factory=PipelineEval)

    def check(self, where: str) -> None:
        if self.precision and self.precision not in PRECISIONS:
            raise CmtoolError(f"{where}: pipeline.precision: expected one of {', '.join(PRECISIONS)} or \"\", "
                              f"got {self.precision!r}")
        if self.eval.n <= 0:
            raise CmtoolError(f"{where}: pipeline.eval.n: must be positive, got {self.eval.n}")
        self.eval.check(f"{where}: pipeline.eval.")


@dataclass
class Recipe:
    """A whole recipe: one section per stage."""

    data: DataRecipe = field(default_factory=DataRecipe)
    train: TrainRecipe = field(default_factory=TrainRecipe)
    rvae: RVAEConfig = field(default_factory=RVAEConfig)
    rvae_loss: RVAELossConfig = field(default_factory=RVAELossConfig)
    dit: DiTConfig = field(default_factory=DiTConfig)
    control: ControlConfig = field(default_factory=ControlConfig)
    diffusion: ScheduleConfig = field(default_factory=ScheduleConfig)
    pipeline: PipelineRecipe = field(default_factory=PipelineRecipe)
    path: Path | None = field(default=None, metadata={"toml": False})  # the file it was read from

    def to_dict(self) -> dict:
        """The recipe's values as plain data (for manifests and checkpoints)."""
        return {f.name: dataclasses.asdict(getattr(self, f.name)) for f in toml_fields(Recipe)}

    def real_map_files(self) -> list[tuple[RealMapsRecipe, Path]]:
        """Every real-map file of the data section (sorted within each entry)."""
        return self.data.real_map_files(self.path)


def load_recipe(path) -> Recipe:
    """Read a recipe TOML file; every missing field keeps its default."""
    path = Path(path)
    table = read_toml(path, "recipe")
    if not table:
        raise CmtoolError(f"{path}: an empty recipe; name at least what to build or train (see recipes/)")
    recipe = from_table(Recipe, table, f"{path}: ")
    recipe.path = path
    recipe.data.check(str(path))
    recipe.train.check(str(path))
    recipe.pipeline.check(str(path))
    recipe.real_map_files()
    return recipe
