"""The latent cache: every scene of a dataset encoded once by the trained RVAE.

Written by ``cmtool train rvae`` when it finishes, into ``<rvae run>/latents/<split>.npz``:
``mean`` and ``logvar`` float16 (N, 64, 8, 8), ``city`` strings and ``pose`` float64 (N, 3) in
the dataset's order (the poses let stage 3 check that its SD rasters line up). Stage 3 with
``train.mirror`` adds ``train_mirrored.npz``, the train scenes mirrored left-right. The latent scale
(1 / std of the train means) goes into the RVAE checkpoint so the DiT sees unit variance.
"""

from __future__ import annotations

import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import DataLoader

from cmtool.core.errors import CmtoolError
from cmtool.core.jsonio import atomic_open
from cmtool.core.progress import Progress
from cmtool.data.cache import load_dataset, load_manifest
from cmtool.train.data import SceneRasters


@dataclass
class LatentSet:
    mean: np.ndarray
    logvar: np.ndarray
    city: np.ndarray
    pose: np.ndarray


@torch.no_grad()
def encode_split(rvae, data_dir, split: str, device, batch: int = 64, progress: bool = True,
                 mirror: bool = False) -> LatentSet:
    """Encode every scene of ``split`` with ``rvae`` (posterior mean and log-variance);
    ``mirror``: the scenes mirrored left-right."""
    scenes = load_dataset(data_dir, split)
    loader = DataLoader(SceneRasters(scenes, mirror=mirror), batch_size=batch, shuffle=False)
    means, logvars = [], []
    rvae.eval()
    label = f"encode {split}" + (" mirrored" if mirror else "")
    with Progress(len(scenes), label=label, unit="scenes", enabled=progress) as bar:
        for item in loader:
            mean, logvar = rvae.encode(item["raster"].to(device))
            means.append(mean.float().cpu().numpy().astype(np.float16))
            logvars.append(logvar.float().cpu().numpy().astype(np.float16))
            bar.update(len(mean))
    return LatentSet(np.concatenate(means), np.concatenate(logvars), scenes.arrays["city"], scenes.arrays["pose"])


def _write(latents: LatentSet, path: Path) -> None:
    with atomic_open(path, "wb") as f:
        np.savez(f, mean=latents.mean, logvar=latents.logvar, city=latents.city, pose=latents.pose)


def write_latents(rvae, data_dir, out_dir: Path, device, progress: bool = True) -> float:
    """Encode all splits of a dataset into ``out_dir``; returns the latent scale."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    scale = None
    for split in load_manifest(data_dir)["splits"]:
        latents = encode_split(rvae, data_dir, split, device, progress=progress)
        _write(latents, out_dir / f"{split}.npz")
        if split == "train":
            scale = float(1.0 / np.std(latents.mean.astype(np.float64)))
    if scale is None:
        raise CmtoolError(f"{data_dir}: the dataset has no train split to compute the latent scale from")
    return scale


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


def data_latents(rvae_loader, rvae_checkpoint: Path, data_dir, device, progress: bool = True) -> tuple[LatentSet, Path]:
    """The train split of ``data_dir`` encoded once by the RVAE of ``rvae_checkpoint`` (``rvae_loader()`` returns it,
    with its encoder) into ``data_dir/latents/<weights digest>/``, and that folder: the latents of data other than the
    RVAE was trained on, e.g. for training the shipped chain further on new data."""
    from cmtool.model.checkpoint import resolve, weights_digest

    out_dir = Path(data_dir) / "latents" / weights_digest(resolve(rvae_checkpoint))
    path = out_dir / "train.npz"
    if not path.is_file():
        out_dir.mkdir(parents=True, exist_ok=True)
        _write(encode_split(rvae_loader(), data_dir, "train", device, progress=progress), path)
    return read_latents(out_dir, "train"), out_dir


def mirrored_latents(rvae_loader, data_dir, out_dir: Path, device, progress: bool = True) -> LatentSet:
    """The train split mirrored left-right, encoded once into ``out_dir/train_mirrored.npz`` (by the RVAE
    ``rvae_loader()`` returns, which must hold its encoder) and read from there afterwards."""
    path = Path(out_dir) / "train_mirrored.npz"
    if not path.is_file():
        _write(encode_split(rvae_loader(), data_dir, "train", device, progress=progress, mirror=True), path)
    return read_latents(out_dir, "train_mirrored")
