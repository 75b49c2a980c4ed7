"""Torch datasets of the training stages, and the step-indexed batch order shared by all of them.

Batches are a pure function of (seed, step, rank): each epoch is a ``DistributedSampler``
shuffle cut into fixed batches, so a resumed run sees exactly the batches the crashed run would
have seen, whatever the number of DataLoader workers.
"""

from __future__ import annotations

import os

import numpy as np
import torch
from torch.utils.data import Dataset, DistributedSampler, Sampler

from cmtool.core.errors import CmtoolError
from cmtool.core.workers import pool
from cmtool.data.cache import SceneDataset
from cmtool.data.hd_raster import drawn_pixels, raster_from_pixels, rasterize_scene
from cmtool.data.sd_raster import mirror_sd
from cmtool.model.controlmap import sd_tensor
from cmtool.model.rvae import ELEMENTS
from cmtool.model.rvae_loss import MASK_KEYS

MIRROR = np.array([1.0, -1.0], np.float32)  # y -> -y: the scene mirrored left-right


def vector_targets(arrays: dict, i: int, mirror: bool = False) -> dict[str, torch.Tensor]:
    """The RVAE targets of scene ``i``: polylines (metres, ego frame; mirrored left-right on request),
    their masks, and ``succ`` (L, L) bool: line i flows into line j."""
    lines = len(arrays["lines"][i])
    edges = arrays["edges"][arrays["edge_offsets"][i]:arrays["edge_offsets"][i + 1]]
    succ = torch.zeros(lines, lines, dtype=torch.bool)
    succ[torch.from_numpy(edges[:, 0].astype(np.int64)), torch.from_numpy(edges[:, 1].astype(np.int64))] = True
    out = {"succ": succ}
    for key in ELEMENTS:
        out[key] = torch.from_numpy(np.ascontiguousarray(arrays[key][i] * MIRROR if mirror else arrays[key][i],
                                                         dtype=np.float32))
        out[MASK_KEYS[key]] = torch.from_numpy(np.ascontiguousarray(arrays[MASK_KEYS[key]][i]))
    return out


class SceneRasters(Dataset):
    """Stage 1 items: the HD raster of a scene and its vector targets (metres, ego frame);
    ``mirror``: of the scene mirrored left-right (right-hand traffic becomes left-hand). Every scene is drawn
    once, when the set is made (:func:`drawn_scenes`); an item's raster is filled from that record."""

    def __init__(self, scenes: SceneDataset, mirror: bool = False):
        self.scenes, self.mirror = scenes, mirror
        self.size = int(round(scenes.frame_m / scenes.px_m))
        self.index, self.values, self.offsets = drawn_scenes(scenes, mirror)

    def __len__(self) -> int:
        return len(self.scenes)

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        a, b = self.offsets[i], self.offsets[i + 1]
        raster = raster_from_pixels(self.index[a:b], self.values[a:b], self.size)
        return {"raster": torch.from_numpy(raster), **vector_targets(self.scenes.arrays, i, self.mirror)}


DRAW_CHUNK = 500  # scenes a worker draws at a time
_DRAWN = ("lines", "line_mask", "green", "green_mask", "red", "red_mask")


def drawn_scenes(scenes: SceneDataset, mirror: bool = False,
                 workers: int | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`drawn_pixels` of every scene (mirrored left-right on request), concatenated: pixel indices (N,),
    values (N, 2) and each scene's offsets (S + 1,). Large sets are drawn by ``workers`` processes (default: the
    cores, at most 8)."""
    chunks = [({k: scenes.arrays[k][start:start + DRAW_CHUNK] for k in _DRAWN}, scenes.px_m, scenes.frame_m, mirror)
              for start in range(0, len(scenes), DRAW_CHUNK)]
    workers = min(8, os.cpu_count() or 1) if workers is None else workers
    if workers > 1 and len(chunks) > 1:
        with pool(min(workers, len(chunks))) as processes:
            drawn = [d for part in processes.imap(_draw_chunk, chunks) for d in part]
    else:
        drawn = [d for chunk in chunks for d in _draw_chunk(chunk)]
    offsets = np.concatenate([[0], np.cumsum([len(index) for index, _ in drawn])]).astype(np.int64)
    if not drawn:
        return np.zeros(0, np.int32), np.zeros((0, 2), np.float32), offsets
    return np.concatenate([d[0] for d in drawn]), np.concatenate([d[1] for d in drawn]), offsets


def _draw_chunk(job) -> list[tuple[np.ndarray, np.ndarray]]:
    arrays, px_m, frame_m, mirror = job
    if mirror:
        arrays = {k: v * MIRROR if k in ELEMENTS else v for k, v in arrays.items()}
    return [drawn_pixels(*(arrays[k][i] for k in _DRAWN), px_m=px_m, frame_m=frame_m)
            for i in range(len(arrays["lines"]))]


def scene_raster(scenes: SceneDataset, i: int) -> torch.Tensor:
    """The HD raster of scene ``i``, drawn now (for a few scenes; a training set draws all of them once)."""
    return torch.from_numpy(rasterize_scene(*(scenes.arrays[k][i] for k in _DRAWN), px_m=scenes.px_m,
                                            frame_m=scenes.frame_m))


class CachedPosteriors(Dataset):
    """Decoder fine-tuning items: a scene's cached latent posterior (mean, logvar) and its vector targets."""

    def __init__(self, mean: np.ndarray, logvar: np.ndarray, scenes: SceneDataset):
        self.mean, self.logvar, self.scenes = mean, logvar, scenes

    def __len__(self) -> int:
        return len(self.mean)

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        return {"mean": torch.from_numpy(self.mean[i].astype(np.float32)),
                "logvar": torch.from_numpy(self.logvar[i].astype(np.float32)), **vector_targets(self.scenes.arrays, i)}


def shift_sideways(control: torch.Tensor, max_px: int) -> torch.Tensor:
    """Each raster of ``control`` (B, C, H, W) moved sideways (along W) by a random whole number of
    pixels in [-max_px, max_px] (``torch``'s global generator), the columns it uncovers left empty."""
    out = torch.zeros_like(control)
    width = control.shape[-1]
    for k, s in enumerate(torch.randint(-max_px, max_px + 1, (len(control),)).tolist()):
        out[k, ..., max(s, 0):width + min(s, 0)] = control[k, ..., max(-s, 0):width - max(s, 0)]
    return out


class Latents(Dataset):
    """Stage 2/3 items: a latent posterior (mean, logvar), the city label and, for stage 3, the SD raster.

    With ``mirrored`` (the posteriors of the scenes mirrored left-right and the labels they take),
    items also hold ``mirror_mean``, ``mirror_logvar``, ``mirror_label`` and, with SD rasters,
    ``mirror_sd``; the loss picks one of the two versions per item.
    """

    def __init__(self, mean: np.ndarray, logvar: np.ndarray, label: np.ndarray, sd: np.ndarray | None = None,
                 mirrored: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None):
        self.mean, self.logvar, self.label, self.sd, self.mirrored = mean, logvar, label, sd, mirrored

    def __len__(self) -> int:
        return len(self.mean)

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        item = {"mean": torch.from_numpy(self.mean[i].astype(np.float32)),
                "logvar": torch.from_numpy(self.logvar[i].astype(np.float32)),
                "label": torch.tensor(int(self.label[i]))}
        if self.sd is not None:
            item["sd"] = sd_tensor(self.sd[i])
        if self.mirrored is not None:
            mean, logvar, label = self.mirrored
            item["mirror_mean"] = torch.from_numpy(mean[i].astype(np.float32))
            item["mirror_logvar"] = torch.from_numpy(logvar[i].astype(np.float32))
            item["mirror_label"] = torch.tensor(int(label[i]))
            if self.sd is not None:
                item["mirror_sd"] = sd_tensor(mirror_sd(self.sd[i]))
        return item


class StepBatches(Sampler):
    """Index batches of steps ``start .. total-1`` for one rank (drop-last epochs)."""

    def __init__(self, dataset: Dataset, batch: int, rank: int, world: int, seed: int, start: int, total: int):
        self.dataset, self.batch, self.rank, self.world = dataset, batch, rank, world
        self.seed, self.start, self.total = seed, start, total
        self.per_epoch = len(dataset) // world // batch
        if self.per_epoch == 0:
            raise CmtoolError(f"the training set has {len(dataset)} items, fewer than one batch of "
                              f"{batch} per process x {world} processes; lower train.batch_size")

    def __len__(self) -> int:
        return self.total - self.start

    def __iter__(self):
        epoch, order = None, None
        for step in range(self.start, self.total):
            e, k = divmod(step, self.per_epoch)
            if e != epoch:
                sampler = DistributedSampler(self.dataset, num_replicas=self.world, rank=self.rank, shuffle=True,
                                             seed=self.seed, drop_last=True)
                sampler.set_epoch(e)
                epoch, order = e, list(sampler)
            yield order[k * self.batch:(k + 1) * self.batch]
