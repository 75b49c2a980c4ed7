"""Several processes under ``torchrun``: training (DDP), ``cmtool eval`` and ``cmtool sample``.

``torchrun`` sets RANK, WORLD_SIZE, LOCAL_RANK, MASTER_ADDR and MASTER_PORT; without them the
run is a single process (:func:`cmtool.core.launch.launch`). NCCL is used on CUDA, gloo on CPU. Sampling splits its
batches over the processes (:func:`rounds`) and gathers the maps on the main process (:func:`gather`).
"""

from __future__ import annotations

import platform
from dataclasses import dataclass

import torch
import torch.distributed as dist

from cmtool.core.launch import launch


@dataclass
class DistInfo:
    rank: int
    world: int
    device: torch.device

    @property
    def main(self) -> bool:
        return self.rank == 0


SINGLE = DistInfo(0, 1, torch.device("cpu"))  # a process on its own (its device is not used)


def setup(device: str | None = None) -> DistInfo:
    """Join the process group when launched by torchrun; pick this process's device."""
    rank, world, local = launch()
    if device is None:
        device = "cuda" if torch.cuda.is_available() else "cpu"
    dev = torch.device(device)
    if dev.type == "cuda":
        dev = torch.device("cuda", local if dev.index is None else dev.index)
        torch.cuda.set_device(dev)
    if world > 1 and not dist.is_initialized():
        dist.init_process_group("nccl" if dev.type == "cuda" else "gloo")
    return DistInfo(rank, world, dev)


def cleanup() -> None:
    if dist.is_initialized():
        dist.destroy_process_group()


def barrier() -> None:
    if dist.is_initialized():
        dist.barrier()


def broadcast(obj, info: DistInfo):
    """The main process's ``obj`` on every process."""
    if info.world == 1:
        return obj
    box = [obj]
    dist.broadcast_object_list(box, src=0)
    return box[0]


def gather(obj, info: DistInfo) -> list | None:
    """Every process's ``obj`` in rank order on the main process; None on the others."""
    if info.world == 1:
        return [obj]
    out = [None] * info.world if info.main else None
    dist.gather_object(obj, out, dst=0)
    return out


def rounds(items: list, info: DistInfo) -> list[list]:
    """``items`` dealt round by round, one to each process in rank order: in every round this process's item, or
    none when the items ran out (so every process takes part in every round's :func:`gather`)."""
    per_round = [items[k:k + info.world] for k in range(0, len(items), info.world)]
    return [chunk[info.rank:info.rank + 1] for chunk in per_round]


def dealt(items: list, info: DistInfo, make):
    """``make(item)`` for each of ``items``, the processes taking turns (:func:`rounds`): yields each result on the
    main process, in the order of ``items``, round by round as they are gathered, and nothing on the others (every
    process must run the generator to its end)."""
    for mine in rounds(items, info):
        made = [make(item) for item in mine]
        for part in gather(made, info) or []:
            yield from part


def hardware(info: DistInfo) -> str:
    """A short description of where this run trains, for the checkpoint's record."""
    if info.device.type == "cuda":
        what = torch.cuda.get_device_name(info.device)
    else:
        what = f"{platform.processor() or platform.machine()} CPU, {torch.get_num_threads()} threads"
    return f"{info.world} x {what}" if info.world > 1 else what
