"""The latent cache: every scene of a dataset encoded once by the trained RVAE.

Written by ``cmtool train rvae`` when it finishes, into ``<rvae run>/latents/<split>.npz``:
``mean`` and ``logvar`` float16 (N, 64, 8, 8), ``city`` strings and ``pose`` float64 (N, 3) in
the dataset's order (the poses let stage 3 check that its SD rasters line up), and ``weights``, the
digest of the RVAE weights that encoded them. Stage 3 with ``train.mirror`` adds ``train_mirrored.npz``,
the train scenes mirrored left-right. The latent scale (1 / std of the train means) goes into the RVAE
checkpoint so the DiT sees unit variance. A file is encoded in parts of :data:`CHUNK` scenes, each
written whole into ``.<name>.parts/`` beside it: an encoding stopped midway goes on from its parts.
"""

from __future__ import annotations

import re
import shutil
import sys
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import DataLoader, Subset

from cmtool.core.errors import CmtoolError
from cmtool.core.jsonio import atomic_open
from cmtool.core.progress import Progress
from cmtool.data.cache import load_dataset, load_manifest
from cmtool.train.data import SceneRasters

CHUNK = 512  # scenes a part of an encoding holds: a stop loses at most one part's work
_PART = re.compile(r"(\d{8})-(\d{8})\.npz")


@dataclass
class LatentSet:
    mean: np.ndarray
    logvar: np.ndarray
    city: np.ndarray
    pose: np.ndarray


def _save(path: Path, **arrays) -> None:
    with atomic_open(path, "wb") as f:
        np.savez(f, **arrays)


def weights_of(path: Path) -> str | None:
    """The digest of the RVAE weights that encoded a latent file ("" where it does not say; None: no such file, or
    not readable)."""
    try:
        with np.load(path) as z:
            return str(z["weights"]) if "weights" in z.files else ""
    except (OSError, ValueError, EOFError, zipfile.BadZipFile):
        return None


def _parts(path: Path) -> Path:
    """The folder the parts of the encoding into ``path`` wait in until it is whole."""
    return path.with_name(f".{path.stem}.parts")


def _scenes(part: str) -> int:
    """Scenes a part holds, by its name (FIRST-END.npz)."""
    m = _PART.fullmatch(part)
    return int(m[2]) - int(m[1]) if m else 0


@torch.no_grad()
def encode_split(rvae, data_dir, split: str, path: Path, device, weights: str, batch: int = 64,
                 progress: bool = True, mirror: bool = False) -> None:
    """Encode every scene of ``split`` with ``rvae`` (posterior mean and log-variance; ``mirror``: the scenes
    mirrored left-right) into ``path``, recording ``weights`` (the digest of ``rvae``'s). Run again after a stop, it
    goes on from the parts of the same weights, and says so."""
    scenes = load_dataset(data_dir, split)
    parts = _parts(Path(path))
    names = [f"{a:08d}-{min(a + CHUNK, len(scenes)):08d}.npz" for a in range(0, len(scenes), CHUNK)]
    todo = [name for name in names if weights_of(parts / name) != weights]
    label = f"encode {split}" + (" mirrored" if mirror else "")
    first = len(scenes) - sum(map(_scenes, todo))
    if todo:
        if first and progress:
            print(f"{label}: going on from {first:,} of {len(scenes):,} scenes encoded before", file=sys.stderr)
        rasters = SceneRasters(scenes, mirror=mirror)
        rvae.eval()
        with Progress(len(scenes), label=label, unit="scenes", enabled=progress, first=first) as bar:
            for name in todo:
                a, b = map(int, _PART.fullmatch(name).groups())
                means, logvars = [], []
                for item in DataLoader(Subset(rasters, range(a, b)), batch_size=batch, shuffle=False):
                    mean, logvar = rvae.encode(item["raster"].to(device))
                    means.append(mean.float().cpu().numpy().astype(np.float16))
                    logvars.append(logvar.float().cpu().numpy().astype(np.float16))
                    bar.update(len(mean))
                _save(parts / name, mean=np.concatenate(means), logvar=np.concatenate(logvars), weights=weights)
    whole = {"mean": [], "logvar": []}
    for name in names:
        with np.load(parts / name) as z:
            for key, arrays in whole.items():
                arrays.append(z[key])
    _save(path, mean=np.concatenate(whole["mean"]), logvar=np.concatenate(whole["logvar"]),
          city=scenes.arrays["city"], pose=scenes.arrays["pose"], weights=weights)
    shutil.rmtree(parts)


def write_latents(rvae, data_dir, out_dir: Path, device, weights: str, progress: bool = True) -> float:
    """Encode all splits of a dataset into ``out_dir`` by the RVAE whose weights' digest is ``weights``; returns the
    latent scale. The splits these weights encoded before are kept: run again after a stop, it goes on from there."""
    out_dir = Path(out_dir)
    splits = load_manifest(data_dir)["splits"]
    if "train" not in splits:
        raise CmtoolError(f"{data_dir}: the dataset has no train split to compute the latent scale from")
    out_dir.mkdir(parents=True, exist_ok=True)  # `cmtool info` shows the encoding from its start
    for split in splits:
        path = out_dir / f"{split}.npz"
        if weights_of(path) != weights:
            encode_split(rvae, data_dir, split, path, device, weights, progress=progress)
    return float(1.0 / np.std(read_latents(out_dir, "train").mean.astype(np.float64)))


def encoding_progress(out_dir: Path, data_dir, weights: str) -> tuple[int, int]:
    """Scenes of a dataset's splits that the RVAE whose weights' digest is ``weights`` has encoded into ``out_dir``
    so far, and scenes in all."""
    done = total = 0
    for split, entry in load_manifest(data_dir)["splits"].items():
        path = Path(out_dir) / f"{split}.npz"
        total += entry["scenes"]
        done += entry["scenes"] if weights_of(path) == weights else \
            sum(_scenes(part.name) for part in _parts(path).glob("*.npz") if weights_of(part) == weights)
    return done, total


def latent_dir(rvae_run: Path, config: dict) -> Path:
    """The latent cache of an RVAE run: its own ``latents/``, or for a decoder fine-tune (whose
    encoder is its parent's) the absolute path of the parent's cache that its config records."""
    path = Path(config.get("latents", "latents"))
    return path if path.is_absolute() else Path(rvae_run) / path


def read_latents(out_dir: Path, split: str) -> LatentSet:
    path = Path(out_dir) / f"{split}.npz"
    if not path.is_file():
        raise CmtoolError(f"{path}: no latent cache; `cmtool train rvae` writes it when it finishes "
                          "(re-run it with --resume to finish an interrupted run)")
    try:
        with np.load(path) as z:
            return LatentSet(z["mean"], z["logvar"], z["city"], z["pose"])
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as e:
        raise CmtoolError(f"{path}: unreadable latent cache ({e}); delete it and re-run `cmtool train rvae "
                          "--resume`") from None


def data_latents(rvae_loader, digest: str, data_dir, device, progress: bool = True) -> tuple[LatentSet, Path]:
    """The train split of ``data_dir`` encoded once by the RVAE whose weights' digest is ``digest``
    (:func:`cmtool.model.checkpoint.weights_digest`; ``rvae_loader()`` returns it, with its encoder) into
    ``data_dir/latents/<digest>/``, and that folder: the latents of data other than the RVAE was trained on, e.g. for
    training the shipped chain further on new data."""
    out_dir = Path(data_dir) / "latents" / digest
    if not (out_dir / "train.npz").is_file():
        encode_split(rvae_loader(), data_dir, "train", out_dir / "train.npz", device, digest, progress=progress)
    return read_latents(out_dir, "train"), out_dir


def mirrored_latents(rvae_loader, data_dir, out_dir: Path, device, progress: bool = True) -> LatentSet:
    """The train split mirrored left-right, encoded once into ``out_dir/train_mirrored.npz`` (by the RVAE
    ``rvae_loader()`` returns, which must hold its encoder) and read from there afterwards, until the RVAE's train
    latents are of other weights (a run trained further)."""
    path = Path(out_dir) / "train_mirrored.npz"
    weights = weights_of(Path(out_dir) / "train.npz") or ""
    if weights_of(path) != weights:
        encode_split(rvae_loader(), data_dir, "train", path, device, weights, progress=progress, mirror=True)
    return read_latents(out_dir, "train_mirrored")
