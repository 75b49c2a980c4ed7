"""Helpers and options that several command modules share."""

from __future__ import annotations

import functools
import math
from pathlib import Path

import click

from cmtool.core.errors import CmtoolError
from cmtool.diffusion.settings import DEFAULT_SAMPLER, DEFAULT_STEPS, SAMPLERS
from cmtool.sample import COUNTS, DEFAULT_COUNTS, DEFAULT_SMOOTH


class Finite(click.FloatRange):
    """A finite number (never nan or inf), optionally within a range: every numeric option's type."""

    def __init__(self, min: float | None = None, max: float | None = None, **kwargs):
        super().__init__(min, max, **kwargs)
        if min is None and max is None:
            self.name = "float"

    def convert(self, value, param, ctx):
        number = super().convert(value, param, ctx)
        if not math.isfinite(number):
            self.fail(f"{value!r} is not a finite number.", param, ctx)
        return number

    def _describe_range(self) -> str:
        return "" if self.min is None and self.max is None else super()._describe_range()


class InPath(click.Path):
    """A file or folder the command reads: no output of the command may be written over it."""

    def __init__(self, **kwargs):
        super().__init__(path_type=Path, **kwargs)

    def convert(self, value, param, ctx):
        from cmtool.core import outputs

        path = super().convert(value, param, ctx)
        outputs.note_input(path)
        for out in ctx.meta.get("cmtool.outputs", []) if ctx is not None else []:
            if outputs.is_input(out) is not None:
                self.fail(f"{path}: this command's input is also its output {out}; write the output to another path",
                          param, ctx)
        return path


class OutPath(click.Path):
    """A file (or, with ``file_okay=False``, a folder) the command writes: refused at once when it is one of the
    command's inputs or a device, FIFO or socket; a folder is locked for the run (two runs never mix their files)."""

    def __init__(self, **kwargs):
        super().__init__(path_type=Path, **kwargs)

    def convert(self, value, param, ctx):
        from cmtool.core import outputs

        path = super().convert(value, param, ctx)
        try:
            outputs.target(path)
            if not self.file_okay:
                outputs.claim_folder(path)
        except CmtoolError as e:
            self.fail(str(e), param, ctx)
        if ctx is not None:
            ctx.meta.setdefault("cmtool.outputs", []).append(path)
        return path


class DatasetDir(InPath):
    """A dataset folder (``cmtool data build``); a map file gets a line saying how to make a dataset of it."""

    def __init__(self):
        super().__init__(file_okay=False)

    def convert(self, value, param, ctx):
        path = Path(value)
        if path.is_file():
            from cmtool.formats.mapfile import map_kind

            try:
                kind, obj = map_kind(path)
            except (CmtoolError, OSError, UnicodeDecodeError):
                kind = obj = None
            if kind not in (None, "lanegraph") or obj is not None or path.suffix == ".jsonl":
                self.fail(f"{path} is a map file ({kind}), not a dataset: list it under [[data.real_maps]] in a recipe "
                          f"and run `cmtool data build` (docs/data.md), or try the map itself with "
                          f"`cmtool sample --from-hd`", param, ctx)
        return super().convert(value, param, ctx)


SEED_MAX = 2**32 - 1
SEED = click.IntRange(0, SEED_MAX)  # the same rule for every command's seed: what numpy and torch both take

CITY_CFG_HELP = ("Guidance weight on the city label (1: the label as trained; > 1 strengthens the city's style, "
                 "such as its driving side, at one more model pass per step).")

SMOOTH_OPTION = click.option(
    "--smooth", default=DEFAULT_SMOOTH, show_default=True, type=click.IntRange(min=0),
    help="Replace each decoded lane and light line by its least-squares Bezier curve with this many control points "
         "(0: the decoder's raw points).")


def sampler_options(fn):
    """``--steps`` and ``--sampler``; without ``--steps`` the command gets the sampler's own step count."""
    counts = ", ".join(f"{n} for {s}" for s, n in DEFAULT_STEPS.items())

    @functools.wraps(fn)
    def command(*args, steps, sampler, **kwargs):
        return fn(*args, steps=steps or DEFAULT_STEPS[sampler], sampler=sampler, **kwargs)

    sampler = click.option("--sampler", default=DEFAULT_SAMPLER, show_default=True, type=click.Choice(SAMPLERS))
    return click.option("--steps", type=click.IntRange(min=1), help=f"Denoising steps [default: {counts}].")(
        sampler(command))


LANE_COUNTS_OPTION = click.option(
    "--lane-counts", default=DEFAULT_COUNTS, show_default=True, type=click.Choice(COUNTS),
    help="Lanes per direction of an SD road without a lanes tag: as many as the model drew along it (its class's "
         "usual count where it drew none), or its class's usual count (docs/baselines.md).")

PRECISION_OPTION = click.option(
    "--precision", default="fp32", show_default=True, type=click.Choice(["fp32", "bf16"]),
    help="bf16: the denoising model (and the decoding of recorded step previews) under bf16 autocast, faster where "
         "the CPU computes bf16 natively (AVX512-BF16, AMX) or on a GPU; maps stay within about 1% of fp32's latents "
         "(docs/speed.md).")

WORKERS_OPTION = click.option(
    "--workers", type=click.IntRange(min=1),
    help="Processes that share the per-scene metrics (topology, lane distances, validity, SD adherence) of sets of "
         "256 scenes or more, and eval's guarantee of the maps [default: one per CPU core].")

FEATURE_PRECISION_OPTION = click.option(
    "--feature-precision", default="fp32", show_default=True, type=click.Choice(["fp32", "bf16"]),
    help="bf16: the ResNet-50 of the feature metrics under bf16 autocast, about 2.5x faster where the CPU computes "
         "bf16 natively (AVX512-BF16, AMX); recall values move slightly (docs/speed.md). `eval` and `ablate` keep "
         "fp32 features, so that their numbers compare across runs.")


def _generator(ckpt, device, smooth: int = DEFAULT_SMOOTH, precision: str = "fp32"):
    """The generator of ``--ckpt`` (default: the shipped weights) on ``--device``, warning when bf16 would be
    emulated."""
    from cmtool.sample.generator import MapGenerator
    from cmtool.train.precision import cpu_has_native_bf16

    dev = _device(device)
    if precision == "bf16" and dev.type == "cpu" and not cpu_has_native_bf16():
        click.echo("warning: this CPU has no native bf16 (AVX512-BF16 or AMX); bf16 is emulated and slower than "
                   "fp32", err=True)
    return MapGenerator.load(_checkpoint(ckpt), dev, smooth, precision)


def _origin(value: str) -> tuple[float, float]:
    """``--origin LAT,LON`` as numbers within the range the local projection serves."""
    from cmtool.sample.inputs import parse_points

    lat0, lon0 = parse_points(value, ("lat", "lon"), {}, "--origin")[0]
    if not (-80.0 <= lat0 <= 80.0 and -180.0 <= lon0 <= 180.0):
        raise CmtoolError(f"--origin {value}: latitude must be within [-80, 80], longitude within [-180, 180]")
    return lat0, lon0


def _device(name: str | None):
    import torch

    try:
        dev = torch.device(name) if name else torch.device("cuda" if torch.cuda.is_available() else "cpu")
    except RuntimeError:
        raise CmtoolError(f"--device {name}: not a torch device (cpu, cuda, cuda:1, ...)") from None
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise CmtoolError(f"--device {name}: CUDA is not available on this machine")
    return dev


def _checkpoint(path: Path | None) -> Path:
    """``--ckpt``, or the ControlMap shipped with the package when it is not given."""
    from cmtool.model.release import bundled_checkpoint

    return bundled_checkpoint() if path is None else path


def map_input_options(command):
    """--osm/--center/--heading and --from-hd/--pose: SD inputs cut from a map (``cmtool sample`` and ``baseline``)."""
    for option in reversed([
        click.option("--osm", type=InPath(), help="OpenStreetMap .osm/.osm.pbf file."),
        click.option("--center", help="With --osm: LAT,LON of the frame centre, or a .jsonl of {lat, lon, heading}."),
        click.option("--heading", default=0.0, show_default=True, type=Finite(),
                     help="With --osm: compass heading that points up, degrees."),
        click.option("--from-hd", "from_hd", type=InPath(),
                     help="HD map JSON (procedural or imported)."),
        click.option("--pose", help="With --from-hd: X,Y,YAW (m, m, degrees) or a .jsonl of {x, y, yaw} [default: a "
                                    "random drivable pose]."),
    ]):
        command = option(command)
    return command


def map_inputs(osm, center, heading, from_hd, pose, seed, whole: bool = False) -> list:
    """The frames that the map input options name (:func:`map_input_options`; at most one of --osm and --from-hd
    given, none of them: no frames); ``whole``: frames are optional (a whole map is asked for)."""
    check_map_inputs(osm, center, from_hd, pose, whole)
    from cmtool.sample import inputs as src

    if osm is not None:
        if center is None:
            return []
        return src.osm_inputs(osm, src.parse_points(center, ("lat", "lon", "heading"), {"heading": heading},
                                                    "--center"))
    if from_hd is not None:
        if pose is None and whole:
            return []
        poses = src.parse_points(pose, ("x", "y", "yaw"), {}, "--pose") if pose is not None else None
        return src.hd_inputs(from_hd, poses, seed)
    return []


def check_map_inputs(osm, center, from_hd, pose, whole: bool = False) -> None:
    """Refuse map input options that do not go together (:func:`map_inputs`), before any file is read."""
    if center is not None and osm is None:
        raise CmtoolError("--center goes with --osm")
    if pose is not None and from_hd is None:
        raise CmtoolError("--pose goes with --from-hd")
    if osm is not None and center is None and not whole:
        raise CmtoolError("--osm needs --center LAT,LON (or a .jsonl of centres)")


def init_options(command):
    """--init, --strength and --encoder: SDEdit from a rule-based layout (``cmtool sample`` and ``cmtool eval``)."""
    for option in reversed([
        click.option("--init", "init", default="none", show_default=True,
                     type=click.Choice(["none", "rules", "netconvert"]),
                     help="Start each map from this rule-based layout of its SD map (`cmtool baseline`), encoded and "
                          "noised --strength of the way, instead of from noise alone (SDEdit); needs SD maps "
                          "(--osm, --from-hd, a dataset) and an encoder."),
        click.option("--strength", default=0.5, show_default=True, type=Finite(min=0, max=1, min_open=True),
                     help="With --init: how far up the noise schedule the layout is noised (1: as from noise; small: "
                          "the layout kept nearly as it is)."),
        click.option("--encoder", "encoder_path", type=InPath(),
                     help="With --init: an RVAE run whose encoder encodes into the checkpoint's latent space (`cmtool "
                          "train encoder`) [default: the checkpoint's own RVAE, when it holds an encoder]."),
    ]):
        command = option(command)
    return command


def attach_init(gen, init: str, encoder_path) -> None:
    """Check the --init options and attach the --encoder to the generator."""
    if init == "none" and encoder_path is not None:
        raise CmtoolError("--encoder goes with --init")
    if encoder_path is not None:
        gen.attach_encoder(encoder_path)
