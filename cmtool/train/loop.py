"""One training loop for all three stages.

A :class:`Stage` says what is trained (model, data, loss, previews, what happens at the end);
:func:`train` does the rest: AdamW with warm-up and cosine decay, gradient clipping, EMA
weights, bf16 autocast or fp32 (``train.precision``; ``auto``: :mod:`cmtool.train.precision`),
DistributedDataParallel under ``torchrun``, atomic checkpoints every ``ckpt_every`` steps with
exact ``--resume``, a progress line and a Rerun recording of the run (``train/loss``,
``train/lr``, ``train/grad_norm``, previews).
"""

from __future__ import annotations

import math
import sys
import time
from abc import ABC, abstractmethod
from pathlib import Path

import rerun as rr
import torch
import torch.distributed as dist
from torch.nn.parallel import DistributedDataParallel
from torch.optim.swa_utils import AveragedModel, get_ema_multi_avg_fn
from torch.utils.data import DataLoader, Dataset

from cmtool.core import dist as D
from cmtool.core.errors import CmtoolError
from cmtool.core.jsonio import read_json
from cmtool.core.memory import check_fits
from cmtool.core.progress import Progress
from cmtool.data.sd_raster import ENCODINGS
from cmtool.model import checkpoint as ckpt
from cmtool.train.data import StepBatches
from cmtool.train.precision import resolve
from cmtool.train.recipe import Recipe, TrainRecipe
from cmtool.viz.recording import ReplayRecording, served, training_blueprint


class Stage(ABC):
    """What one training stage trains: subclasses implement the abstract methods."""

    kind: str  # checkpoint kind: rvae | dit | controlmap
    name = ""  # how progress lines call the stage [default: kind]

    def __init__(self, recipe: Recipe, device: torch.device):
        self.recipe, self.device = recipe, device

    @abstractmethod
    def model(self, weights: bool = True) -> torch.nn.Module:
        """A fresh model; parameters with ``requires_grad`` are the ones trained. ``weights=False``: its layers only,
        no checkpoint weights read into them (to count its parameters on the meta device)."""

    @abstractmethod
    def dataset(self) -> Dataset:
        """The training set (items are dicts of tensors)."""

    @abstractmethod
    def loss(self, model, batch: dict) -> tuple[torch.Tensor, dict[str, float]]:
        """Loss of one batch (already on the device); extra scalars to log. Draw randomness from
        torch's global generator: the loop seeds it per step and rank."""

    @abstractmethod
    def config(self) -> dict:
        """Checkpoint config entries besides the training record (kind, model config, labels...)."""

    def preview(self, model, rec: rr.RecordingStream) -> None:
        """Log a few decoded samples of the (EMA) model at the current ``train_step``."""

    def preview_views(self) -> list[tuple[str, str, list[str]]]:
        """What :meth:`preview` logs, as (title, origin, contents) of one 2D view each, under ``train/preview``."""
        return []

    def finish(self, model, run_dir: Path) -> dict:
        """Work after the last step (e.g. the latent cache), once the final checkpoint is written; returns extra
        config entries. Run again after a stop, it goes on from where that stopped (or starts over)."""
        return {}


def lr_at(step: int, t: TrainRecipe) -> float:
    """Linear warm-up to ``lr``, then constant or cosine decay to ``lr * min_lr_ratio``."""
    if step < t.warmup_steps:
        return t.lr * (step + 1) / t.warmup_steps
    if t.lr_schedule == "constant":
        return t.lr
    span = max(t.steps - t.warmup_steps, 1)
    progress = min((step - t.warmup_steps) / span, 1.0)
    floor = t.lr * t.min_lr_ratio
    return floor + 0.5 * (t.lr - floor) * (1.0 + math.cos(math.pi * progress))


def optimizer(params: list[torch.nn.Parameter], t: TrainRecipe) -> torch.optim.AdamW:
    decay = [p for p in params if p.ndim >= 2]
    rest = [p for p in params if p.ndim < 2]
    groups = [{"params": decay, "weight_decay": t.weight_decay}, {"params": rest, "weight_decay": 0.0}]
    return torch.optim.AdamW(groups, lr=t.lr, betas=tuple(t.betas))


def optimise(stage: Stage, net: torch.nn.Module, opt: torch.optim.Optimizer, params: list[torch.nn.Parameter],
             batch: dict, autocast, step: int) -> tuple[torch.Tensor, dict[str, float], torch.Tensor]:
    """One optimiser step of ``stage``'s loss on ``batch`` (on the device): loss (refused when not finite), the
    stage's extra scalars, and the gradient norm before clipping."""
    with autocast:
        loss, logs = stage.loss(net, batch)
    if not torch.isfinite(loss):
        raise CmtoolError(f"loss became {loss.item()} at step {step}; lower train.lr or raise train.warmup_steps "
                          "(the last checkpoint is intact)")
    opt.zero_grad(set_to_none=True)
    loss.backward()
    grad_norm = torch.nn.utils.clip_grad_norm_(params, stage.recipe.train.grad_clip)
    opt.step()
    return loss, logs, grad_norm


def precision(t: TrainRecipe, device: torch.device, info: D.DistInfo = D.SINGLE,
              kept: str | None = None) -> tuple[bool, torch.autocast]:
    """Whether ``t`` trains in bf16 on ``device`` (:func:`cmtool.train.precision.resolve`; ``kept``: the precision
    of the checkpoint resumed from), and the autocast context that does. The main process decides and says why in
    one line; the others take its choice."""
    bf16, line = resolve(t.precision, device, kept) if info.main else (False, "")
    bf16 = D.broadcast(bf16, info)
    if line:
        print(line, file=sys.stderr, flush=True)
    return bf16, torch.autocast(device.type, dtype=torch.bfloat16, enabled=bf16)


def _fingerprint(model: torch.nn.Module) -> torch.Tensor:
    """Float64 sums of every parameter: replicas that agree here agree bit for bit in practice."""
    sums = [torch.stack([p.detach().double().sum(), p.detach().double().square().sum()]) for p in model.parameters()]
    return torch.cat(sums)


def _check_replicas(model: torch.nn.Module, info: D.DistInfo) -> list[float]:
    """All ranks' parameter fingerprints (reduced to one number each); raise if replicas differ."""
    fp = _fingerprint(model).to(info.device)
    if info.world == 1:
        return [float(fp.sum())]
    gathered = [torch.empty_like(fp) for _ in range(info.world)]
    dist.all_gather(gathered, fp)
    if not all(torch.equal(g, gathered[0]) for g in gathered):
        raise CmtoolError("DDP replicas diverged: parameters differ between processes")
    return [float(g.sum()) for g in gathered]


def _state_tensors(model, opt) -> tuple[dict[str, torch.Tensor], dict]:
    tensors = {f"model/{k}": v for k, v in model.state_dict().items()}
    sd = opt.state_dict()
    for i, st in sd["state"].items():
        for k, v in st.items():
            tensors[f"opt/{i}/{k}"] = v if torch.is_tensor(v) else torch.tensor(v)
    return tensors, {"param_groups": sd["param_groups"]}


def _check_size(stage: Stage) -> None:
    """Refuse, before anything is allocated, a model whose weights, gradients, optimiser moments and EMA copy would
    not fit in memory (its parameters counted on the meta device)."""
    with torch.device("meta"):
        params = sum(p.numel() for p in stage.model(weights=False).parameters())
    where = stage.recipe.path or "the recipe"
    if params > ckpt.MAX_PARAMS:
        raise CmtoolError(f"{where}: a model of {params / 1e9:.1f} billion parameters, more than cmtool trains "
                          f"({ckpt.MAX_PARAMS / 1e9:.0f} billion)")
    check_fits(5 * 4 * params, f"{where}: training a model of {params / 1e6:,.0f} million parameters")


def _load_state(model, opt, checkpoint: Path) -> None:
    """The raw weights and optimiser state of a checkpoint's training state; damaged state is a one-line error that
    names its files."""
    tensors = ckpt.load_tensors(checkpoint / ckpt.STATE)
    meta = read_json(checkpoint / ckpt.STATE_META, ckpt.MAX_JSON_BYTES)
    try:
        model.load_state_dict({k[6:]: v for k, v in tensors.items() if k.startswith("model/")})
        state: dict[int, dict] = {}
        for k, v in tensors.items():
            if k.startswith("opt/"):
                _, i, name = k.split("/", 2)
                state.setdefault(int(i), {})[name] = v
        opt.load_state_dict({"state": state, "param_groups": meta["param_groups"]})
    except (KeyError, TypeError, ValueError, RuntimeError) as e:
        why = f"no {e}" if isinstance(e, KeyError) else str(e).splitlines()[0]
        raise CmtoolError(f"{checkpoint / ckpt.STATE} / {ckpt.STATE_META}: damaged training state ({why}); resume "
                          f"from an earlier checkpoint (delete this one) or start anew") from None


def _resume_point(run_dir: Path, resume: bool, kind: str, model_config: dict,
                  steps: int | None = None) -> tuple[Path, dict] | None:
    """The newest checkpoint of ``run_dir`` and its config, checked against the model to train. Without ``resume``
    only a run trained to its last step of ``steps`` whose work after it a stop cut short: the same command again
    finishes it."""
    found = ckpt.run_checkpoints(run_dir)
    if not found:
        if resume:
            print(f"{run_dir}: no checkpoint yet, starting from step 0", file=sys.stderr)
        return None
    last = found[-1]
    config = ckpt.load_config(last)
    if not resume and (config.get("complete") or not config.get("step") == config.get("steps") == steps):
        raise CmtoolError(f"{run_dir} already holds checkpoints; pass --resume to continue it or choose another --out")
    wanted = ckpt.as_stored(model_config)
    had, want = (c.get("control", {}).get("sd_encoding") for c in (config, wanted))
    if kind == "controlmap" and had != want:
        raise CmtoolError(f"{last}: its control branch reads SD rasters of encoding {had} ({ENCODINGS[had]}); this "
                          f"recipe's reads encoding {want} ({ENCODINGS[want]}). --resume cannot change it: start a new "
                          f"run with train.branch_from = \"{last}\"")
    if config["kind"] != kind or config.get("model") != wanted.get("model") \
            or config.get("control") != wanted.get("control"):
        raise CmtoolError(f"{last}: this run was trained with another model; --resume needs the same recipe")
    if not (last / ckpt.STATE).is_file():
        raise CmtoolError(f"{last}: no training state to resume from")
    return last, config


def _finish(stage: Stage, model: torch.nn.Module, run_dir: Path, final: Path, info: D.DistInfo) -> None:
    """The stage's work after its last step (:meth:`Stage.finish`, on the main process) into the final checkpoint
    ``final``, written before it: then its config says ``complete``, rewritten whole or not at all."""
    if info.main:
        model.eval()
        ckpt.update_config(final, {**stage.finish(model, run_dir), "complete": True})
    D.barrier()  # the other processes go on (to a next stage of a pipeline) once the stage is complete


def train(stage: Stage, run_dir: Path, resume: bool = False, progress: bool = True, serve: int | None = None,
          log: bool = True) -> Path:
    """Train ``stage`` into ``run_dir``; returns the final checkpoint directory. ``serve``: a port to serve the
    recording on (gRPC, for viewers elsewhere) while the stage trains; ``log=False``: no recording (train.rrd) and
    no previews. The final checkpoint is written before the stage's work after the last step (:meth:`Stage.finish`),
    so a stop there keeps every step: the same command again (or ``resume``) does only that work."""
    t = stage.recipe.train
    info = D.setup(str(stage.device))
    stage.device = info.device
    if t.batch_size % info.world:
        raise CmtoolError(f"train.batch_size {t.batch_size} is not divisible by the {info.world} processes")
    torch.manual_seed(t.seed)  # identical initial weights on every rank
    _check_size(stage)
    model = stage.model().to(info.device)
    params = [p for p in model.parameters() if p.requires_grad]
    opt = optimizer(params, t)
    ema = AveragedModel(model, multi_avg_fn=get_ema_multi_avg_fn(t.ema_decay), use_buffers=True)
    base_config = stage.config()

    start, record = 0, {"time_s": 0.0, "samples": 0}
    point = _resume_point(run_dir, resume, stage.kind, base_config, t.steps)
    if point is not None:
        last, config = point
        _load_state(model, opt, last)
        ckpt.load_weights(ema.module, last)
        ema.n_averaged.fill_(config["step"])
        start, record = config["step"], config["training"]
        if start >= t.steps and (config.get("complete") or start >= config.get("steps", start)):
            if not config.get("complete"):
                if info.main:
                    print(f"{run_dir}: trained to step {start} before (no training now); finishing the "
                          f"{stage.name or stage.kind} stage", file=sys.stderr)
                _finish(stage, ema.module, run_dir, last, info)
            elif info.main:
                print(f"{run_dir}: training already complete at step {start}", file=sys.stderr)
            D.cleanup()
            return last

    dataset = stage.dataset()
    per_rank = t.batch_size // info.world
    batches = StepBatches(dataset, per_rank, info.rank, info.world, t.seed, start, t.steps)
    loader = DataLoader(dataset, batch_sampler=batches, num_workers=t.workers,
                        pin_memory=info.device.type == "cuda", persistent_workers=t.workers > 0)
    net = DistributedDataParallel(model, device_ids=[info.device.index] if info.device.type == "cuda" else None) \
        if info.world > 1 else model
    bf16, autocast = precision(t, info.device, info, record.get("precision"))

    rec = None
    if info.main and log:
        run_dir.mkdir(parents=True, exist_ok=True)
        rec = ReplayRecording("train", run_dir / ("train.rrd" if start == 0 else f"train_from_{start:08d}.rrd"),
                              served(serve) if serve else None)
        rec.send_blueprint(training_blueprint(stage.name or stage.kind, stage.preview_views()))

    def save(step: int) -> Path:
        fingerprints = _check_replicas(model, info)
        target = ckpt.step_dir(run_dir, step)
        if info.main:
            tensors, meta = _state_tensors(model, opt)
            config = {**base_config, "step": step, "steps": t.steps, "complete": False,
                      "recipe": stage.recipe.to_dict(), "recipe_path": str(stage.recipe.path or ""),
                      "training": {**record, "hardware": D.hardware(info), "world_size": info.world,
                                   "precision": "bf16" if bf16 else "fp32",
                                   "torch": torch.__version__, "replica_fingerprints": fingerprints}}
            ckpt.save_checkpoint(target, config, ema.module.state_dict(), tensors, meta)
            ckpt.prune(run_dir, t.keep)
            if rec is not None:
                rec.write()
        D.barrier()
        return target

    if start and progress and info.main:
        print(f"{run_dir}: resumed from step {start} of {t.steps} ({point[0].name})", file=sys.stderr)
    bar = Progress(t.steps, label=f"train {stage.name or stage.kind}", unit="steps", enabled=progress and info.main,
                   first=start)
    t0, step = time.perf_counter() - record["time_s"], start
    model.train()
    for step, batch in enumerate(loader, start=start):
        batch = {k: v.to(info.device, non_blocking=True) for k, v in batch.items()}
        lr = lr_at(step, t)
        for group in opt.param_groups:
            group["lr"] = lr
        torch.manual_seed(t.seed * 1_000_003 + info.rank * 7_919 + step)  # noise, dropout: exact on resume
        loss, logs, grad_norm = optimise(stage, net, opt, params, batch, autocast, step)
        ema.update_parameters(model)
        record["samples"] += t.batch_size
        record["last_loss"] = loss.item()
        record["time_s"] = time.perf_counter() - t0
        done = step + 1
        if rec is not None and (done % t.log_every == 0 or done == t.steps):
            rec.set_time("train_step", sequence=done)
            rec.log("train/loss", rr.Scalars(record["last_loss"]))
            rec.log("train/lr", rr.Scalars(lr))
            rec.log("train/grad_norm", rr.Scalars(grad_norm.item()))
            for k, v in logs.items():
                rec.log(f"train/{k}", rr.Scalars(v))
        bar.update(1, loss=f"{record['last_loss']:.4f}", lr=f"{lr:.2e}",
                   **{"samples/s": f"{record['samples'] / max(record['time_s'], 1e-9):.1f}"})
        if rec is not None and t.preview_every and (done % t.preview_every == 0 or done == t.steps):
            rec.set_time("train_step", sequence=done)
            ema.module.eval()
            stage.preview(ema.module, rec)
        if done % t.ckpt_every == 0 and done < t.steps:
            save(done)
    bar.close()
    final = save(t.steps)
    if rec is not None:
        rec.close()  # the final save wrote train.rrd; this frees the served port for the next stage
    _finish(stage, ema.module, run_dir, final, info)
    if info.main:
        print(f"{stage.name or stage.kind}: {t.steps} steps in {record['time_s']:.0f} s, last loss {record.get('last_loss', float('nan')):.4f} -> {final}",
              file=sys.stderr)
    D.cleanup()
    return final
