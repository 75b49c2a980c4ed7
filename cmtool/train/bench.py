"""``cmtool bench train``: what bounds a training stage, its data path or its model step.

For one stage, with its recipe's batch size, DataLoader workers, precision and optimiser, three rates in
samples per second: the data path alone (batches drawn from the DataLoader, nothing computed on them),
the model step alone (forward, backward and optimiser step on one batch held on the device), and the two
together as the training loop runs them. Preparing the training set (e.g. drawing every scene's HD raster
once) is timed on its own.
"""

from __future__ import annotations

import time

import torch
from torch.utils.data import DataLoader

from cmtool.train.data import StepBatches
from cmtool.train.loop import Stage, optimise, optimizer, precision


def _synchronise(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def bench_stage(stage: Stage, steps: int, workers: int | None = None) -> dict:
    """The three rates of ``stage`` over ``steps`` batches each (after one batch or step to warm up), and the
    seconds the training set took to prepare; ``workers``: DataLoader workers [default: the recipe's]."""
    t, device = stage.recipe.train, stage.device
    workers = t.workers if workers is None else workers
    start = time.perf_counter()
    dataset = stage.dataset()
    prepare = time.perf_counter() - start

    def batches():
        sampler = StepBatches(dataset, t.batch_size, 0, 1, t.seed, 0, steps + 1)
        return iter(DataLoader(dataset, batch_sampler=sampler, num_workers=workers,
                               pin_memory=device.type == "cuda"))

    def to_device(batch):
        return {k: v.to(device, non_blocking=True) for k, v in batch.items()}

    loader = batches()
    next(loader)  # workers started
    start = time.perf_counter()
    for batch in loader:
        to_device(batch)
    _synchronise(device)
    data = steps * t.batch_size / (time.perf_counter() - start)

    torch.manual_seed(t.seed)
    model = stage.model().to(device)
    model.train()
    params = [p for p in model.parameters() if p.requires_grad]
    opt = optimizer(params, t)
    _, autocast = precision(t, device)
    loader = batches()
    held = to_device(next(loader))
    optimise(stage, model, opt, params, held, autocast, 0)
    _synchronise(device)
    start = time.perf_counter()
    for step in range(steps):
        optimise(stage, model, opt, params, held, autocast, step)
    _synchronise(device)
    model_rate = steps * t.batch_size / (time.perf_counter() - start)

    start = time.perf_counter()
    for step, batch in enumerate(loader):
        optimise(stage, model, opt, params, to_device(batch), autocast, step)
    _synchronise(device)
    both = steps * t.batch_size / (time.perf_counter() - start)
    return {"stage": stage.name or stage.kind, "batch": t.batch_size, "workers": workers, "prepare_s": prepare,
            "data": data, "model": model_rate, "both": both}
