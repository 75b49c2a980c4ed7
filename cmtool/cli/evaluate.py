"""``cmtool metrics`` and ``cmtool eval``: scoring generated lane graphs, evaluating a checkpoint."""

from __future__ import annotations

import time

import click

from cmtool.cli.common import (FEATURE_PRECISION_OPTION, LANE_COUNTS_OPTION, PRECISION_OPTION, SEED, SMOOTH_OPTION,
                               WORKERS_OPTION, DatasetDir, Finite, InPath, OutPath, _device, _generator, attach_init,
                               init_options, sampler_options)
from cmtool.core.errors import CmtoolError


@click.command()
@click.option("--generated", required=True, multiple=True, type=InPath(dir_okay=False),
              help="Generated lane graphs (.jsonl); repeat it to score several generators side by side (e.g. "
                   "`cmtool sample` and `cmtool baseline rules` maps of the same inputs), a column each.")
@click.option("--reference", required=True, type=InPath(dir_okay=False),
              help="Reference (ground-truth) lane graphs (.jsonl), paired line by line.")
@click.option("--control", type=InPath(),
              help="SD controls, paired in order: a folder of SD pictures or a .npy stack (N, 128, 128, 3).")
@click.option("--json", "json_out", type=OutPath(dir_okay=False), help="Write all numbers here.")
@click.option("--backbone", default="resnet50-seeded", show_default=True,
              type=click.Choice(["resnet50-seeded", "resnet50-imagenet"]),
              help="Feature network of the recall metrics.")
@click.option("--weights", type=InPath(dir_okay=False),
              help="ImageNet ResNet-50 weights file [default: torchvision's file in the torch hub cache].")
@click.option("--no-features", is_flag=True, help="Skip the feature metrics (precision/recall, Control/GT Recall).")
@click.option("--device", help="torch device [default: cuda when available, else cpu].")
@FEATURE_PRECISION_OPTION
@WORKERS_OPTION
@click.option("--quiet", is_flag=True, help="No progress line.")
def metrics(generated, reference, control, json_out, backbone, weights, no_features, device, feature_precision, workers,
            quiet):
    """Score generated lane graphs against a reference set (and their SD controls): topology FDs,
    improved precision/recall, Control / GT Recall with p-values, and geometric lane metrics."""
    from cmtool.core.jsonio import write_json
    from cmtool.core.workers import cores
    from cmtool.formats.mapfile import read_lane_graphs
    from cmtool.metrics.features import FeatureExtractor
    from cmtool.metrics.suite import evaluate, load_controls, summary_table

    names = [p.name for p in generated]
    if len(set(names)) < len(names):
        names = [str(p) for p in generated]
    if len(set(names)) < len(names):
        raise CmtoolError("--generated: a file given twice")
    sets, ref = [read_lane_graphs(p) for p in generated], read_lane_graphs(reference)
    controls = load_controls(control) if control is not None else None
    extractor = None if no_features else FeatureExtractor(backbone, weights, _device(device),
                                                          precision=feature_precision)
    began = time.perf_counter()
    results = {name: evaluate(gen, ref, controls, extractor, features=not no_features, progress=not quiet,
                              workers=workers or cores()) for name, gen in zip(names, sets)}
    click.echo(summary_table(results))
    first = next(iter(results.values()))
    click.echo(f"{first['scenes']} scene pairs{f' x {len(results)} sets' if len(results) > 1 else ''} in "
               f"{time.perf_counter() - began:.1f} s (" + ", ".join(f"{k} {v:.1f} s" for k, v in first["seconds"].items())
               + (" for the first set" if len(results) > 1 else "") + ", per-scene families summed over the processes)"
               + ("" if no_features else f"; features: {first['backbone']['name']}"))
    if json_out is not None:
        head = {"reference": str(reference), "control": str(control) if control else None}
        if len(results) == 1:
            write_json(json_out, {"generated": str(generated[0]), **head, **first})
        else:
            write_json(json_out, {**head, "generated": {n: str(p) for n, p in zip(names, generated)}, "sets": results})
        click.echo(f"wrote {json_out}")


@click.command("eval")
@click.option("--ckpt", type=InPath(),
              help="ControlMap checkpoint or run folder [default: the weights shipped with cmtool].")
@click.option("--data", "data_dir", required=True, type=DatasetDir(),
              help="Dataset cache (cmtool data build).")
@click.option("--split", default="test", show_default=True, help="Split to evaluate on.")
@click.option("--n", default=3904, show_default=True, type=click.IntRange(min=1),
              help="Scenes (the first N of the split).")
@click.option("--cfg", default=1.0, show_default=True, type=Finite(min=0), help="ControlMap's guidance weight.")
@sampler_options
@init_options
@click.option("--seed", default=0, show_default=True, type=SEED, help="Random seed (the same noise for both methods).")
@SMOOTH_OPTION
@click.option("--batch", default=64, show_default=True, type=click.IntRange(min=1), help="Maps per forward pass.")
@click.option("--out", required=True, type=OutPath(file_okay=False),
              help="Folder for metrics.json, summary.md, eval.rrd and the generation cache.")
@click.option("--backbone", default="resnet50-seeded", show_default=True,
              type=click.Choice(["resnet50-seeded", "resnet50-imagenet"]),
              help="Feature network of the recall metrics.")
@click.option("--weights", type=InPath(dir_okay=False), help="ImageNet ResNet-50 weights file.")
@click.option("--no-features", is_flag=True, help="Skip the feature metrics.")
@click.option("--rrd-samples", default=64, show_default=True, type=click.IntRange(min=0),
              help="Scenes whose maps go into eval.rrd (scores go in for all).")
@LANE_COUNTS_OPTION
@click.option("--device", help="torch device [default: cuda when available, else cpu].")
@PRECISION_OPTION
@WORKERS_OPTION
@click.option("--quiet", is_flag=True, help="No progress line.")
def eval_cmd(ckpt, data_dir, split, n, cfg, steps, sampler, init, strength, encoder_path, seed, smooth, batch, out,
             backbone, weights, no_features, rrd_samples, lane_counts, device, precision, workers, quiet):
    """Evaluate a ControlMap checkpoint on a test split against its unguided DiT (paper Tables 1-2).
    Under torchrun the processes share the generation (the same maps as one process)."""

    from cmtool.core import dist as D
    from cmtool.core.workers import cores
    from cmtool.eval.evaluation import EvalSettings, run_eval
    from cmtool.metrics.features import FeatureExtractor

    info = D.setup(str(_device(device)))
    try:
        gen = _generator(ckpt, str(info.device), smooth, precision)
        attach_init(gen, init, encoder_path)
        gen.schedule.timesteps(steps)
        extractor = None if no_features or not info.main else FeatureExtractor(backbone, weights, gen.device)
        settings = EvalSettings(data=str(data_dir.resolve()), split=split, n=n, cfg=cfg, steps=steps,
                                sampler=sampler, seed=seed, batch=batch, precision=precision, init=init,
                                strength=strength if init != "none" else 1.0, lane_counts=lane_counts)
        run_eval(gen, settings, out, extractor, rrd_samples=rrd_samples, progress=not quiet, info=info,
                 workers=workers or cores())
    finally:
        D.cleanup()
    if info.main:
        click.echo((out / "summary.md").read_text())
        click.echo(f"wrote {out / 'metrics.json'}, {out / 'summary.md'}, {out / 'gallery.png'}, {out / 'eval.rrd'}")
