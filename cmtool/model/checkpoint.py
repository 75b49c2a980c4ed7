"""Checkpoints: safetensors weights + a JSON config, one directory per saved step.

A *checkpoint directory* holds::

    config.json              format, kind (rvae | dit | controlmap), model config, city labels,
                             latent scale, the RVAE it decodes with and a digest of its weights,
                             recipe, step, training record
    model.safetensors        the weights to use (EMA weights during training), or, split into
                             files of a size limit, model-0000k-of-0000n.safetensors listed in
                             model.safetensors.index.json (Hugging Face's layout)
    train_state.safetensors  raw weights + optimiser state, for ``--resume`` (training only)
    train_state.json         optimiser hyper-parameters and the step counter (training only)

A *run directory* (what ``cmtool train --out`` writes) keeps its checkpoints under
``checkpoints/step_<step>/``. Each is written into a temporary directory and renamed into place,
so a crash (even ``kill -9``) leaves either the complete new checkpoint or none; :func:`resolve`
maps a run directory to its newest complete checkpoint. Nothing is unpickled when loading.
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import json
import math
import os
import re
import shutil
from collections import Counter
from pathlib import Path

import torch
from safetensors import SafetensorError, safe_open
from safetensors.torch import load_file, save_file

from cmtool.core.errors import CmtoolError
from cmtool.core.jsonio import atomic_open, file_mode, read_json
from cmtool.core.outputs import os_reason

FORMAT = "cmtool.checkpoint"
CONFIG, WEIGHTS, INDEX = "config.json", "model.safetensors", "model.safetensors.index.json"
STATE, STATE_META = "train_state.safetensors", "train_state.json"
MAX_JSON_BYTES = 16 << 20  # a checkpoint's JSON file (config, weight index, training state) larger is refused unread
KINDS = ("rvae", "dit", "controlmap")
DIT_RECORD = ("step", "steps", "training", "recipe_path", "init_from")  # how a DiT was trained (packs keep it)


def _fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _write_tensors(path: Path, tensors: dict[str, torch.Tensor]) -> None:
    save_file({k: v.detach().contiguous().cpu() for k, v in tensors.items()}, str(path))
    os.chmod(path, file_mode())  # safetensors writes 0600 files; weights to ship and share get the usual ones
    with open(path, "rb") as f:
        os.fsync(f.fileno())


def _write_json(path: Path, obj) -> None:
    with open(path, "w", encoding="utf-8") as f:
        _dump_json(f, obj)


def _dump_json(f, obj) -> None:
    json.dump(obj, f, indent=1, default=_plain)
    f.write("\n")
    f.flush()
    os.fsync(f.fileno())


def update_config(checkpoint: Path, entries: dict) -> None:
    """Add ``entries`` to the config.json of the written checkpoint ``checkpoint``, rewritten whole or not at all."""
    config = read_json(checkpoint / CONFIG, MAX_JSON_BYTES)
    with atomic_open(checkpoint / CONFIG) as f:
        _dump_json(f, {**config, **entries})


def _plain(obj):
    if dataclasses.is_dataclass(obj):
        return dataclasses.asdict(obj)
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")


def as_stored(config: dict) -> dict:
    """``config`` as a checkpoint's config.json holds it (tuples become lists, paths strings)."""
    return json.loads(json.dumps(config, default=_plain))


def _write_shards(folder: Path, tensors: dict[str, torch.Tensor], max_bytes: int) -> None:
    """The weights in files of at most ``max_bytes`` each (tensors in name order) and their index."""
    groups: list[dict[str, torch.Tensor]] = [{}]
    size = 0
    for name in sorted(tensors):
        t = tensors[name]
        nbytes = t.nbytes
        if nbytes + 4096 > max_bytes:  # room for the file's header
            raise CmtoolError(f"weight {name} alone ({nbytes / 2**20:.1f} MiB) exceeds the file limit of "
                              f"{max_bytes / 2**20:.1f} MiB")
        if groups[-1] and size + nbytes + 256 * (len(groups[-1]) + 1) > max_bytes:
            groups.append({})
            size = 0
        groups[-1][name] = t
        size += nbytes
    weight_map = {}
    for k, group in enumerate(groups, 1):
        name = f"model-{k:05d}-of-{len(groups):05d}.safetensors"
        _write_tensors(folder / name, group)
        weight_map.update({t: name for t in group})
    _write_json(folder / INDEX, {"metadata": {"total_size": sum(t.nbytes for t in tensors.values())},
                                 "weight_map": weight_map})


def save_checkpoint(target: Path, config: dict, weights: dict[str, torch.Tensor],
                    state: dict[str, torch.Tensor] | None = None, state_meta: dict | None = None,
                    max_file_bytes: int | None = None) -> Path:
    """Write a checkpoint directory at ``target`` atomically (replacing an existing one); with
    ``max_file_bytes``, weights larger than that are split into files of at most that size."""
    target = Path(target)
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = target.with_name(f".{target.name}.tmp-{os.getpid()}")
    shutil.rmtree(tmp, ignore_errors=True)
    try:
        tmp.mkdir()
        if max_file_bytes and sum(t.nbytes for t in weights.values()) + 4096 > max_file_bytes:
            _write_shards(tmp, weights, max_file_bytes)
        else:
            _write_tensors(tmp / WEIGHTS, weights)
        if state is not None:
            _write_tensors(tmp / STATE, state)
            _write_json(tmp / STATE_META, state_meta or {})
        _write_json(tmp / CONFIG, {"format": FORMAT, "version": 1, **config})
        _fsync_dir(tmp)
    except BaseException as e:  # a full disk, a signal: no half-written checkpoint folder stays behind
        shutil.rmtree(tmp, ignore_errors=True)
        if isinstance(e, (OSError, SafetensorError)):
            why = os_reason(e) if isinstance(e, OSError) else str(e)
            raise CmtoolError(f"cannot write the checkpoint {target}: {why}") from None
        raise
    replace_folder(tmp, target)
    _fsync_dir(target.parent)
    return target


def replace_folder(new: Path, target: Path) -> None:
    """Rename the finished folder ``new`` to ``target``; an existing ``target`` is renamed aside first and then
    deleted, so ``target`` holds the old set or the new one, never a mixture."""
    if target.exists():
        old = target.with_name(f".{target.name}.old-{os.getpid()}")
        os.rename(target, old)
        os.rename(new, target)
        shutil.rmtree(old)
    else:
        os.rename(new, target)


def step_dir(run_dir: Path, step: int) -> Path:
    return Path(run_dir) / "checkpoints" / f"step_{step:08d}"


def run_checkpoints(run_dir: Path) -> list[Path]:
    """Complete checkpoints of a run directory, oldest first."""
    root = Path(run_dir) / "checkpoints"
    if not root.is_dir():
        return []
    return sorted(p for p in root.glob("step_*") if (p / CONFIG).is_file() and weight_files(p))


def prune(run_dir: Path, keep: int) -> None:
    """Delete all but the newest ``keep`` checkpoints, and what an interrupted save or prune left behind. A folder
    is renamed to a temporary name before it is deleted, so a kill midway leaves a temporary folder (removed by
    the next prune), never a half-deleted ``step_*`` folder that looks like a checkpoint."""
    root = Path(run_dir) / "checkpoints"
    complete = run_checkpoints(run_dir)
    for p in complete[:-keep] + [p for p in root.glob("step_*") if p not in complete]:
        trash = p.with_name(f".{p.name}.old-{os.getpid()}")
        os.rename(p, trash)
        shutil.rmtree(trash)
    for p in root.glob(".step_*.*-*"):
        shutil.rmtree(p, ignore_errors=True)


def resolve(path) -> Path:
    """A checkpoint directory, or a run directory -> its newest complete checkpoint."""
    path = Path(path)
    if (path / CONFIG).is_file() and weight_files(path):
        return path
    found = run_checkpoints(path)
    if found:
        return found[-1]
    if not path.exists():
        raise CmtoolError(f"{path}: no such checkpoint")
    raise CmtoolError(f"{path}: not a checkpoint (no {CONFIG} + {WEIGHTS} or {INDEX}, no checkpoints/step_*)")


def file_sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def weight_files(checkpoint: Path) -> list[Path]:
    """The weight files of a checkpoint folder: ``model.safetensors``, or the files its index lists
    (empty when it has neither, or when a listed file is missing)."""
    checkpoint = Path(checkpoint)
    if (checkpoint / WEIGHTS).is_file():
        return [checkpoint / WEIGHTS]
    if not (checkpoint / INDEX).is_file():
        return []
    index = read_json(checkpoint / INDEX, MAX_JSON_BYTES)
    try:
        names = sorted(set(index["weight_map"].values()))
    except (CmtoolError, KeyError, TypeError, AttributeError):
        raise CmtoolError(f"{checkpoint / INDEX}: not a weight index (expected a weight_map of files)") from None
    odd = [n for n in names if not (isinstance(n, str) and _WEIGHT_FILE.fullmatch(n))]
    if odd or len(names) > MAX_WEIGHT_FILES:
        raise CmtoolError(f"{checkpoint / INDEX}: not a weight index of this folder ("
                          + (f"file {str(odd[0])[:80]!r}" if odd else f"{len(names)} files") + ")")
    files = [checkpoint / n for n in names]
    return files if all(f.is_file() for f in files) else []


_WEIGHT_FILE = re.compile(r"model-\d{5}-of-\d{5}\.safetensors")  # the names _write_shards gives, in this folder
MAX_WEIGHT_FILES = 1000


def weights_digest(*checkpoints: Path) -> str:
    """A short SHA-256 over the weights of checkpoint folders: tells their contents apart where
    their paths are the same (e.g. the shipped weights after a re-pack)."""
    return hashlib.sha256("".join(file_sha256(f) for c in checkpoints for f in weight_files(c)).encode()
                          ).hexdigest()[:16]


PACKAGE = Path(__file__).resolve().parents[1]


def portable(path) -> str:
    """``path`` without the folders of the machine it is on, for files that travel (shipped configs, reports): inside
    the package from its root (``cmtool/weights/rvae``), a run's checkpoint from its run folder on
    (``controlnet/checkpoints/step_00004000``), any other absolute path by its name; a relative path as it is."""
    path = Path(path)
    if not path.is_absolute():
        return path.as_posix()
    if path.resolve().is_relative_to(PACKAGE):
        return path.resolve().relative_to(PACKAGE.parent).as_posix()
    return "/".join(path.parts[-3:]) if path.parent.name == "checkpoints" else path.name


def shown(path) -> str:
    """``path`` as maps' meta and recordings show it: the shipped weights from the package's root
    (``cmtool/weights/controlmap``, wherever it is installed), any other path as it is."""
    return portable(path) if Path(path).resolve().is_relative_to(PACKAGE) else str(path)


def linked(checkpoint: Path, target: str) -> Path:
    """A path a checkpoint config names (its RVAE, its DiT): absolute, or relative to the checkpoint."""
    path = Path(target)
    return path if path.is_absolute() else Path(checkpoint) / path


def rvae_of(checkpoint: Path, config: dict) -> Path:
    """The RVAE checkpoint that the DiT or ControlMap ``checkpoint`` (its ``config``) decodes with: its config's
    ``rvae`` (a run's newest checkpoint), refused where its weights are not the ``rvae_weights`` it was trained on
    (the run trained further, or the folder re-packed): its latents would decode into other maps, with no error."""
    rvae = resolve(linked(checkpoint, config["rvae"]))
    want = config.get("rvae_weights")
    if want is not None and (have := weights_digest(rvae)) != want:
        raise CmtoolError(f"{checkpoint}: trained on the RVAE weights {want}, but its RVAE {rvae} now holds others "
                          f"({have}), into whose latent space it does not denoise; put the RVAE it was trained on "
                          "back, or pack the model with it (`cmtool pack`)")
    return rvae


def load_config(path, encoder: bool = True) -> dict:
    """The config of a checkpoint (or of a run directory's newest checkpoint); ``encoder=False``: an RVAE's encoder
    is left out of the checks of its model (:func:`build_model`)."""
    path = resolve(path) / CONFIG
    config = read_json(path, MAX_JSON_BYTES)
    if not isinstance(config, dict) or config.get("format") != FORMAT:
        raise CmtoolError(f"{path}: not a cmtool checkpoint config")
    if config.get("kind") not in KINDS:
        raise CmtoolError(f"{path}: unknown checkpoint kind {config.get('kind')!r} (known: {', '.join(KINDS)})")
    for key, (ok, what) in _FIELDS.items():
        if key in config and not ok(config[key]):
            raise CmtoolError(f"{path}: {key}: expected {what}, got {json.dumps(config[key])[:40]}")
    for key in ("model", "control") if config["kind"] == "controlmap" else ("model",):
        if key not in config:
            raise CmtoolError(f"{path}: {key}: missing")
    if config["kind"] == "controlmap" and isinstance(config["control"], dict):
        config["control"].setdefault("sd_encoding", 1)  # written before the road class came into the SD raster
    with torch.device("meta"), _uninitialised():  # the config's types, ranges and size, before anything is allocated
        params = sum(p.numel() for p in build_model(config, str(path), encoder).parameters())
    if params > MAX_PARAMS:
        raise CmtoolError(f"{path}: model: {params / 1e9:.1f} billion parameters, more than cmtool loads "
                          f"({MAX_PARAMS / 1e9:.0f} billion)")
    return config


@contextlib.contextmanager
def _uninitialised():
    """Modules built without their initial values (``torch.nn.init``'s functions leave their tensor as it is, as
    transformers' ``no_init_weights`` does): initialising a tensor on the meta device makes torch import its compiler,
    2-3 s of every checkpoint load."""
    names = [n for n in dir(torch.nn.init) if n.endswith("_") and not n.startswith("_")]
    saved = {n: getattr(torch.nn.init, n) for n in names}
    try:
        for n in names:
            setattr(torch.nn.init, n, lambda tensor, *args, **kwargs: tensor)
        yield
    finally:
        for n, function in saved.items():
            setattr(torch.nn.init, n, function)


def _number(v, low: float = 0.0) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v > low


MAX_PARAMS = 3_000_000_000  # 12 GB in float32: ControlMap on DiT-XL is under a third of it
_FIELDS = {  # top-level config fields the commands read: (valid?, what they must be)
    "cities": (lambda v: isinstance(v, list) and all(isinstance(c, str) for c in v), "a list of city labels"),
    "latent_scale": (lambda v: v is None or _number(v), "a finite number > 0"),
    "rvae": (lambda v: v is None or isinstance(v, str), "a path"),
    "dit": (lambda v: v is None or isinstance(v, str), "a path"),
    "model": (lambda v: isinstance(v, dict), "an object"),
    "control": (lambda v: isinstance(v, dict), "an object"),
    "schedule": (lambda v: isinstance(v, dict), "an object"),
    "step": (lambda v: isinstance(v, int) and not isinstance(v, bool) and v >= 0, "a step count"),
    "steps": (lambda v: isinstance(v, int) and not isinstance(v, bool) and v >= 0, "a step count"),
}


def load_tensors(path: Path) -> dict[str, torch.Tensor]:
    check_tensors(path)
    try:
        return load_file(str(path))
    except (SafetensorError, OSError, ValueError) as e:
        raise CmtoolError(f"{path}: unreadable weights ({type(e).__name__}: {e})") from None


def check_tensors(path: Path) -> None:
    """Refuse a file that is not a valid safetensors file: :func:`_check_header`, then the safetensors reader's own
    checks (the weights themselves are not read)."""
    try:
        _check_header(Path(path))
        with safe_open(str(path), "pt"):
            pass
    except (SafetensorError, OSError, ValueError, KeyError, TypeError, AttributeError) as e:
        raise CmtoolError(f"{path}: not a valid safetensors file ({type(e).__name__}: {e})") from None


def _unique(pairs: list[tuple[str, object]]) -> dict:
    """A JSON object whose keys are all different."""
    twice = [k for k, c in Counter(k for k, _ in pairs).items() if c > 1]
    if twice:
        raise ValueError(f"the header names {twice[0]!r} twice")
    return dict(pairs)


_DTYPE_BYTES = {"F64": 8, "F32": 4, "F16": 2, "BF16": 2, "I64": 8, "I32": 4, "I16": 2, "I8": 1, "U8": 1, "BOOL": 1}
MAX_HEADER = 100 << 20  # bytes, as the safetensors reader allows


def _check_header(path: Path) -> None:
    """Refuse a safetensors file whose header names a tensor twice, or whose tensors overlap, leave gaps, run past
    the file or do not fit their shapes (the safetensors reader lets some of these through)."""
    size = path.stat().st_size
    with open(path, "rb") as f:
        n = int.from_bytes(f.read(8), "little")
        if size < 8 or not 2 <= n <= min(size - 8, MAX_HEADER):
            raise ValueError(f"a header of {n} bytes in a file of {size}")
        header = json.loads(f.read(n), object_pairs_hook=_unique)
    spans = []
    for name, info in header.items():
        if name == "__metadata__":
            continue
        begin, end = info["data_offsets"]
        if end - begin != math.prod(info["shape"]) * _DTYPE_BYTES.get(info["dtype"], 0):
            raise ValueError(f"tensor {name!r}: {end - begin} bytes for shape {info['shape']} of {info['dtype']}")
        spans.append((begin, end, name))
    at = 0
    for begin, end, name in sorted(spans):
        if begin != at:
            raise ValueError(f"tensor {name!r} starts at byte {begin}, " +
                             ("overlapping the one before" if begin < at else f"leaving a gap after byte {at}"))
        at = end
    if at != size - 8 - n:
        raise ValueError(f"the tensors take {at} bytes, the file holds {size - 8 - n}")


def read_weights(checkpoint: Path) -> dict[str, torch.Tensor]:
    """All weights of a checkpoint folder, from one file or from the files of its index."""
    files = weight_files(checkpoint)
    if not files:
        raise CmtoolError(f"{checkpoint}: no weights ({WEIGHTS}, or {INDEX} and every file it lists)")
    tensors, placed = {}, {}
    for f in files:
        part = load_tensors(f)
        tensors.update(part)
        placed.update(dict.fromkeys(part, f.name))
    if files[0].name != WEIGHTS and placed != read_json(checkpoint / INDEX, MAX_JSON_BYTES)["weight_map"]:
        raise CmtoolError(f"{checkpoint / INDEX}: lists other weights than its files hold")
    return tensors


def load_weights(module: torch.nn.Module, checkpoint: Path, leave: tuple[str, ...] = ()) -> None:
    """Load a checkpoint folder's weights into ``module``, those whose keys start with one of ``leave`` left out; a
    key or shape mismatch is a one-line error."""
    tensors = {k: v for k, v in read_weights(checkpoint).items() if not k.startswith(leave)}
    own = module.state_dict()
    missing, unexpected = sorted(set(own) - set(tensors)), sorted(set(tensors) - set(own))
    if missing or unexpected:
        what = f"missing {missing[:3]}" if missing else f"unexpected {unexpected[:3]}"
        raise CmtoolError(f"{checkpoint}: weights do not match the model in its config ({what})")
    for k, v in tensors.items():
        if v.shape != own[k].shape:
            raise CmtoolError(f"{checkpoint}: weight {k} has shape {tuple(v.shape)}, the model expects "
                              f"{tuple(own[k].shape)}")
    module.load_state_dict({k: v.to(own[k].dtype) for k, v in tensors.items()})


def build_model(config: dict, where: str = "checkpoint", encoder: bool = True) -> torch.nn.Module:
    """An untrained model of the kind and configuration a checkpoint config describes (``encoder=False``: an RVAE
    without its encoder, as a sampler decodes with it)."""
    from cmtool.core.tables import from_table
    from cmtool.model.controlmap import ControlConfig, ControlMap
    from cmtool.model.dit import DiT, DiTConfig
    from cmtool.model.rvae import RVAE, RVAEConfig

    kind = config["kind"]
    if kind == "rvae":
        return RVAE(from_table(RVAEConfig, config["model"], f"{where}: ", "model."),
                    encoder=encoder and config.get("weights") != "decoder")
    dit = DiT(from_table(DiTConfig, config["model"], f"{where}: ", "model."))
    if kind == "dit":
        return dit
    return ControlMap(dit, from_table(ControlConfig, config["control"], f"{where}: ", "control."))


def load_model(path, device="cpu", encoder: bool = True) -> tuple[torch.nn.Module, dict]:
    """The model of a checkpoint (or a run's newest one) with its weights, in eval mode; ``encoder=False``: an RVAE
    without its encoder (faster: the encoder's trunk comes from torchvision, 2-3 s to import)."""
    from cmtool.model.rvae import ENCODER_PREFIXES

    path = resolve(path)
    config = load_config(path, encoder)
    model = build_model(config, str(path / CONFIG), encoder)
    load_weights(model, path, () if encoder else ENCODER_PREFIXES)
    return model.to(device).eval(), config
