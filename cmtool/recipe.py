"""Recipes: TOML files that fix every setting of a run (data set, later the models).

Every field has a default here; a recipe file overrides any of them. A recipe has one table per
stage (``[data]`` now; a new stage is a new dataclass and one more field of :class:`Recipe`).
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
import glob
import math
import sys
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path

from cmtool.data.frames import KINDS, FrameMix
from cmtool.data.importers import FORMATS as IMPORT_FORMATS
from cmtool.data.sd_jitter import SDJitter
from cmtool.errors import CmtoolError
from cmtool.model.config import ControlConfig, DiTConfig, RVAEConfig, RVAELossConfig, ScheduleConfig
from cmtool.sample import DEFAULT_SAMPLER, SAMPLERS
from cmtool.train import PRECISIONS

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

@dataclass
class RealMapsRecipe:
    """Real HD maps to import: every file matching ``path`` becomes one work unit."""

    format: str  # av2 | lanelet2 | nuplan
    path: str  # file or glob, relative to the recipe's folder (or the current folder)
    split: str = "train"
    city: str | None = None  # city label; None keeps the importer's
    scenes_per_map: int | None = None  # None: the data recipe's scenes_per_map


@dataclass
class DataRecipe:
    """The scene data set: which maps, how many scenes, and the scene/raster geometry."""

    name: str = "data"
    seed: int = 0
    train_cities: list[str] = field(default_factory=lambda: ["LAV", "PIT", "SGP"])
    test_cities: list[str] = field(default_factory=lambda: ["BOS"])
    maps_per_city: int = 4  # procedural maps per train city
    test_maps_per_city: int = 1  # procedural maps per test city
    scenes_per_map: int = 250
    extent: float = 800.0  # side of each procedural city (m)
    px_m: float = 0.5  # HD raster pixel size (m): 0.5 -> 128 px, 0.25 -> 256 px
    frame_m: float = 64.0  # scene square side (m)
    num_lines: int = 50  # lane pieces kept per scene, nearest first (SLEDGE: 50); the build counts those cut
    num_points: int = 20
    num_lights: int = 10  # per light state (green, red)
    min_piece_m: float = 2.0  # clipped lane pieces shorter than this are dropped
    min_pose_spacing_m: float = 16.0  # ego poses of one map are kept this far apart when possible
    shard_size: int = 250  # scenes per shard file
    frame_mix: FrameMix = field(default_factory=FrameMix)  # shares of the frame kinds (cmtool.data.frames)
    sd_jitter: SDJitter = field(default_factory=SDJitter)  # OSM-like imperfections of the SD maps (default: off)
    real_maps: list[RealMapsRecipe] = field(default_factory=list)

    def check(self, where: str) -> None:
        """Reject values that are well-typed but meaningless."""
        positive = ("extent", "px_m", "frame_m", "num_lines", "num_points", "shard_size")
        for key in positive:
            if getattr(self, key) <= 0:
                raise CmtoolError(f"{where}: data.{key}: must be positive, got {getattr(self, key)}")
        for key in ("maps_per_city", "test_maps_per_city", "scenes_per_map", "num_lights", "min_piece_m"):
            if getattr(self, key) < 0:
                raise CmtoolError(f"{where}: data.{key}: must not be negative, got {getattr(self, key)}")
        if (self.frame_m / self.px_m) % 1:
            raise CmtoolError(f"{where}: data.px_m: frame_m / px_m must be a whole number of pixels")
        both = sorted(set(self.train_cities) & set(self.test_cities))
        if both:
            raise CmtoolError(f"{where}: data.test_cities: {both} also in train_cities (splits are by city)")
        for problem in self.sd_jitter.problems():
            raise CmtoolError(f"{where}: data.sd_jitter.{problem}")
        shares = self.frame_mix.as_dict()
        bad = [k for k, v in shares.items() if not (math.isfinite(v) and v >= 0)]
        if bad or sum(shares.values()) <= 0:
            raise CmtoolError(f"{where}: data.frame_mix: shares of {', '.join(KINDS)} must be finite, >= 0 and not "
                              "all 0" + (f" ({bad[0]} = {shares[bad[0]]})" if bad else ""))
        for i, rm in enumerate(self.real_maps):
            if rm.format not in IMPORT_FORMATS:
                raise CmtoolError(f"{where}: data.real_maps[{i}].format: expected one of {IMPORT_FORMATS}, got {rm.format!r}")


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
    min_snr_gamma: float = 0.0  # dit, controlnet: Min-SNR-gamma loss weights min(SNR, gamma) / SNR (Hang et al.,
    #                             ICCV 2023, use 5): nearly clean timesteps (SNR > gamma) count less; 0 = plain MSE
    ckpt_every: int = 500
    keep: int = 2  # checkpoints kept in the run folder
    log_every: int = 10  # steps between scalar logs in the Rerun recording
    preview_every: int = 500  # steps between decoded previews (0: off)
    preview_steps: int = 25  # sampler steps of the previews (dit, controlnet)
    workers: int = 0  # DataLoader worker processes
    precision: str = "auto"  # auto: bf16 autocast on CUDA, fp32 on CPU | bf16: bf16 autocast on any device (on a
    #                          CPU with native bf16, AVX512-BF16 or AMX, about 1.7x faster) | fp32: none
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
        if self.branch_from and self.stage not in ("", "controlnet"):
            raise CmtoolError(f"{where}: train.branch_from: a control branch is a controlnet-stage option")
        if self.init_from and self.stage not in ("", "dit"):
            raise CmtoolError(f"{where}: train.init_from: a dit-stage option (the controlnet stage has branch_from)")
        if self.precision not in PRECISIONS:
            raise CmtoolError(f"{where}: train.precision: expected one of {', '.join(PRECISIONS)}, "
                              f"got {self.precision!r}")
        if self.lr_schedule not in ("cosine", "constant"):
            raise CmtoolError(f"{where}: train.lr_schedule: expected cosine or constant, got {self.lr_schedule!r}")
        for key in ("ema_decay", "label_dropout", "mirror", "min_lr_ratio"):
            if not 0.0 <= getattr(self, key) <= 1.0:
                raise CmtoolError(f"{where}: train.{key}: must lie in [0, 1], got {getattr(self, key)}")
        if len(self.betas) != 2 or not all(0.0 <= b < 1.0 for b in self.betas):
            raise CmtoolError(f"{where}: train.betas: expected two values in [0, 1), got {self.betas}")


@dataclass
class PipelineEval:
    """``[pipeline.eval]``: how ``cmtool train pipeline`` evaluates the packed weights (as ``cmtool eval``)."""

    split: str = "test"
    n: int = 512
    cfg: float = 1.0
    steps: int = 50
    sampler: str = DEFAULT_SAMPLER
    seed: int = 0
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
        for key in ("n", "steps", "batch"):
            if getattr(self.eval, key) <= 0:
                raise CmtoolError(f"{where}: pipeline.eval.{key}: must be positive, got {getattr(self.eval, key)}")
        if self.eval.sampler not in SAMPLERS:
            raise CmtoolError(f"{where}: pipeline.eval.sampler: expected one of {', '.join(SAMPLERS)}, "
                              f"got {self.eval.sampler!r}")
        if not (math.isfinite(self.eval.cfg) and self.eval.cfg >= 0):
            raise CmtoolError(f"{where}: pipeline.eval.cfg: must be a finite number >= 0, got {self.eval.cfg}")


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
        return {f.name: dataclasses.asdict(getattr(self, f.name)) for f in _toml_fields(Recipe)}

    def real_map_files(self) -> list[tuple[RealMapsRecipe, Path]]:
        """Every real-map file of the data section (sorted within each entry)."""
        bases = ([self.path.parent] if self.path else []) + [Path.cwd()]
        out = []
        for i, rm in enumerate(self.data.real_maps):
            for base in bases:
                hits = sorted(glob.glob(str(base / rm.path)))
                if hits:
                    out += [(rm, Path(h)) for h in hits]
                    break
            else:
                raise CmtoolError(f"{self.path or 'recipe'}: data.real_maps[{i}].path: no file matches {rm.path!r}")
        return out


def load_recipe(path) -> Recipe:
    """Read a recipe TOML file; every missing field keeps its default."""
    path = Path(path)
    if not path.is_file():
        raise CmtoolError(f"{path}: no such recipe file")
    try:
        table = tomllib.loads(path.read_text(encoding="utf-8"))
    except tomllib.TOMLDecodeError as e:
        raise CmtoolError(f"{path}: malformed TOML: {e}") from None
    except UnicodeDecodeError:
        raise CmtoolError(f"{path}: not a UTF-8 text file") from None
    if not table:
        raise CmtoolError(f"{path}: an empty recipe; name at least what to build or train (see recipes/)")
    recipe = from_table(Recipe, table, f"{path}: ")
    recipe.path = path
    recipe.data.check(str(path))
    recipe.train.check(str(path))
    recipe.pipeline.check(str(path))
    recipe.real_map_files()
    return recipe


def _toml_fields(cls) -> list[dataclasses.Field]:
    return [f for f in dataclasses.fields(cls) if f.metadata.get("toml", True)]


def from_table(cls, table, where: str, prefix: str = ""):
    """Construct dataclass ``cls`` from a TOML table, checking keys and types."""
    if not isinstance(table, dict):
        raise CmtoolError(f"{where}{prefix.rstrip('.') or 'recipe'}: expected a table")
    fields = {f.name: f for f in _toml_fields(cls)}
    hints = typing.get_type_hints(cls)
    unknown = sorted(set(table) - set(fields))
    if unknown:
        raise CmtoolError(f"{where}{prefix}{unknown[0]}: unknown key (known: {', '.join(fields)})")
    missing = [n for n, f in fields.items() if n not in table and f.default is dataclasses.MISSING
               and f.default_factory is dataclasses.MISSING]
    if missing:
        raise CmtoolError(f"{where}{prefix}{missing[0]}: missing")
    return cls(**{k: _convert(hints[k], v, where, prefix + k) for k, v in table.items()})


def _convert(tp, value, where: str, key: str):
    """Check ``value`` against type hint ``tp`` (int/float/str/bool, lists, tuples, Optional, dataclasses)."""
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:  # TOML has no null; kept for completeness
            return None
        (inner,) = [a for a in args if a is not type(None)]
        return _convert(inner, value, where, key)
    if dataclasses.is_dataclass(tp):
        return from_table(tp, value, where, key + ".")
    if origin in (list, tuple):  # tuple[X, ...] fields take a TOML list too
        if not isinstance(value, (list, tuple)):
            raise CmtoolError(f"{where}{key}: expected a list, got {value!r}")
        items = [_convert(args[0], v, where, f"{key}[{i}]") for i, v in enumerate(value)]
        return items if origin is list else tuple(items)
    ok = {
        bool: isinstance(value, bool),
        int: isinstance(value, int) and not isinstance(value, bool),
        float: isinstance(value, (int, float)) and not isinstance(value, bool),
        str: isinstance(value, str),
    }[tp]
    if not ok:
        raise CmtoolError(f"{where}{key}: expected {tp.__name__}, got {value!r}")
    if tp is float and not math.isfinite(value):
        raise CmtoolError(f"{where}{key}: expected a finite number, got {value!r}")
    return float(value) if tp is float else value
