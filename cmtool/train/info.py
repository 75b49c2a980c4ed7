"""``cmtool info``: what a checkpoint holds, or how big the models of a recipe are."""

from __future__ import annotations

import json
from pathlib import Path

import torch

from cmtool.core.errors import CmtoolError
from cmtool.core.progress import format_seconds
from cmtool.model import checkpoint as ckpt

KIND_OF_STAGE = {"rvae": "rvae", "decoder": "rvae", "encoder": "rvae", "dit": "dit", "controlnet": "controlmap"}


def param_counts(model: torch.nn.Module) -> dict[str, int]:
    """Total parameters; for a ControlMap also the frozen base and the trainable branch."""
    total = sum(p.numel() for p in model.parameters())
    counts = {"total": total}
    if hasattr(model, "base"):
        base = sum(p.numel() for p in model.base.parameters())
        counts.update(base=base, branch=total - base)
    return counts


def _count_line(counts: dict[str, int]) -> str:
    line = f"{counts['total']:,} ({counts['total'] / 1e6:.1f}M)"
    if "base" in counts:
        line += f" = frozen DiT {counts['base'] / 1e6:.1f}M + control branch {counts['branch'] / 1e6:.1f}M"
    return line


def _fields(obj: dict) -> str:
    return " ".join(f"{k}={v}" for k, v in obj.items())


def _dit_line(record: dict) -> str:
    tr = record["training"]
    return (f"{format_seconds(tr.get('time_s', 0))} on {tr.get('hardware', '?')}, {record.get('step')} steps, "
            f"{tr.get('samples', 0):,} samples, recipe {record.get('recipe_path') or '?'}")


def _state(config: dict, checkpoint: Path) -> str:
    """Complete; in progress (training); or trained, its work after the last step not done (or cut short by a stop):
    for an RVAE that encodes the latent cache, how far that is."""
    if config.get("complete"):
        return "complete"
    step, steps = config.get("step"), config.get("steps")
    if not (isinstance(step, int) and isinstance(steps, int) and step >= steps):
        return "in progress"
    latents = checkpoint.parent.parent / "latents"
    if config["kind"] == "rvae" and "data" in config and latents.is_dir():
        from cmtool.train.latents import encoding_progress

        try:
            done, total = encoding_progress(latents, config["data"], ckpt.weights_digest(checkpoint))
        except CmtoolError:  # the dataset is gone: how far is not known
            return "trained, encoding latents"
        if done < total:
            return f"trained, encoding latents {done:,}/{total:,}"
    return "trained, finishing"


def describe(path: Path, as_json: bool = False) -> str:
    path = Path(path)
    if path.suffix == ".toml":
        return describe_recipe(path)
    config = ckpt.load_config(path)
    if as_json:
        return json.dumps(config, indent=1)
    where = ckpt.resolve(path)
    with torch.device("meta"):
        counts = param_counts(ckpt.build_model(config, str(where)))
    rows = [("checkpoint", ckpt.shown(where)),
            ("kind", f"{config['kind']} ({_state(config, where)}, step {config.get('step')}/{config.get('steps')})"),
            ("model", _fields(config["model"]))]
    if "control" in config:
        rows.append(("control", _fields(config["control"])))
    rows.append(("parameters", _count_line(counts)))
    if "cities" in config:
        rows.append(("city labels", ", ".join(config["cities"]) + " (+ null)"))
    if "latent_scale" in config:
        rows.append(("latent scale", f"{config['latent_scale']:.5g}"))
    if "schedule" in config:
        rows.append(("schedule", _fields(config["schedule"])))
    tr = config.get("training", {})
    if tr:
        rows.append(("trained", f"{format_seconds(tr.get('time_s', 0))} on {tr.get('hardware', '?')}, "
                                f"{tr.get('samples', 0):,} samples, torch {tr.get('torch', '?')}"))
    rows.append(("recipe", config.get("recipe_path") or "?"))
    dit = config.get("dit_training")
    if dit and dit.get("training"):
        rows.append(("DiT trained", _dit_line(dit)))
    source = (dit or config).get("init_from")
    while source:  # a DiT trained further from another one's weights, and so on back
        rows.append(("DiT started from", f"{source['path']}: {_dit_line(source)}" if source.get("training")
                     else source["path"]))
        source = source.get("init_from")
    if config.get("weights") == "decoder":
        rows.append(("weights", "decoder only (latent -> lanes), as shipped; encoding needs the training run"))
    if config.get("encoder_trained"):
        enc = config["encoder_trained"]
        rows.append(("encoder", f"trained for this decoder by `cmtool train encoder` ({enc['path']}, "
                                f"{enc.get('step', '?')} steps; the scale of its own latents "
                                f"{enc.get('own_latent_scale', float('nan')):.4f})"))
    if config.get("packed_from"):
        rows.append(("packed from", config["packed_from"]))
    if config.get("encoder_from"):
        rows.append(("encoder", f"frozen, from {config['encoder_from']} (decoder trained further on its latents)"))
    if config.get("decoder_from"):
        rows.append(("decoder", f"frozen, from {config['decoder_from']} (encoder trained for it; the scale of its "
                                f"own latents {config.get('own_latent_scale', float('nan')):.4f})"))
    for key in ("data", "rvae", "dit", "branch_from"):
        if key in config:
            rows.append((key, config[key]))
    rec = config.get("reconstruction")
    if rec:
        rows.append(("reconstruction", f"lane precision {rec['precision']:.3f} recall {rec['recall']:.3f} "
                                       f"F1 {rec['f1']:.3f} at {rec['tol_m']} m ({rec['scenes']} {rec['split']} scenes)"))
    width = max(len(k) for k, _ in rows)
    return "\n".join(f"{k:<{width}}  {v}" for k, v in rows)


def describe_recipe(path: Path) -> str:
    """The model a training recipe defines and its parameter count (built on the meta device)."""
    import dataclasses

    from cmtool.train.recipe import load_recipe

    recipe = load_recipe(path)
    stage = recipe.train.stage
    if not stage:
        return f"{path}: not a training recipe (no train.stage)"
    config = {"kind": KIND_OF_STAGE[stage]}
    if stage == "rvae":
        config["model"] = dataclasses.asdict(recipe.rvae)
    elif stage in ("decoder", "encoder"):  # the model is the RVAE run's (or packed weights')
        config["model"] = ckpt.load_config(recipe.train.rvae)["model"]
    else:
        cities = len(recipe.data.train_cities)
        config["model"] = dataclasses.asdict(dataclasses.replace(recipe.dit, num_classes=cities))
        if stage == "controlnet":
            config["control"] = dataclasses.asdict(recipe.control)
    with torch.device("meta"):
        model = ckpt.build_model(config, str(path))
    rows = [("recipe", str(path)), ("stage", stage), ("model", _fields(config["model"]))]
    if stage == "decoder":
        rows.append(("trains", f"the decoder of {recipe.train.rvae}; its encoder stays frozen"))
    if stage == "encoder":
        rows.append(("trains", f"an encoder for the decoder of {recipe.train.rvae}, which stays frozen"))
    if stage == "controlnet":
        rows.append(("control", _fields(config["control"])))
    rows.append(("parameters", _count_line(param_counts(model))))
    t = recipe.train
    rows.append(("training", f"{t.steps:,} steps x batch {t.batch_size}, lr {t.lr:g} ({t.lr_schedule}), "
                             f"EMA {t.ema_decay}"))
    width = max(len(k) for k, _ in rows)
    return "\n".join(f"{k:<{width}}  {v}" for k, v in rows)
