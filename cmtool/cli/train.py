"""``cmtool train``: one training stage, or a whole pipeline recipe."""

from __future__ import annotations

from pathlib import Path

import click

from cmtool.cli.common import DatasetDir, InPath, OutPath, _device
from cmtool.core.errors import CmtoolError
from cmtool.core.launch import launch
from cmtool.core.outputs import claim_folder
from cmtool.train import PRECISIONS


@click.command("train")
@click.argument("stage", type=click.Choice(["rvae", "decoder", "encoder", "dit", "controlnet", "pipeline"]))
@click.option("--recipe", required=True, type=InPath(), help="Recipe TOML (see recipes/).")
@click.option("--out", type=OutPath(file_okay=False),
              help="Run folder [default: the recipe's train.out].")
@click.option("--resume", is_flag=True, help="Continue from the run folder's newest checkpoint (pipeline: from where "
              "it stopped, finished stages skipped). A run stopped after its last step (while it encoded the latent "
              "cache) needs none: the same command finishes it.")
@click.option("--data", "data_dir", type=DatasetDir(),
              help="Override train.data (the dataset cache); pipeline: a dataset built before, instead of its data "
                   "stage.")
@click.option("--steps", type=click.IntRange(min=1), help="Override train.steps (e.g. for a quick try).")
@click.option("--precision", type=click.Choice(PRECISIONS),
              help="Override train.precision: bf16 autocast pays on CUDA and on CPUs with native bf16 "
                   "(AVX512-BF16, AMX); auto takes it where the device has it and a test block runs faster in it "
                   "(a line says which and why), fp32 elsewhere.")
@click.option("--device", help="torch device [default: cuda when available, else cpu].")
@click.option("--quiet", is_flag=True, help="No progress line.")
@click.option("--serve", is_flag=True, help="Serve the training recording and Rerun's web viewer from this machine "
                                            "(ports 9876 and 9090) while it trains: watch it from a browser elsewhere.")
@click.option("--no-log", is_flag=True, help="Write no Rerun recording (train.rrd, previews; pipeline: eval.rrd too), "
                                             "e.g. on a machine without rerun-sdk.")
def train_cmd(stage, recipe, out, resume, data_dir, steps, precision, device, quiet, serve, no_log):
    """Train one stage: rvae (stage 1), dit (stage 2) or controlnet (stage 3); decoder trains a
    finished RVAE's decoder further on its frozen encoder's latents (DiTs trained on them stay valid);
    encoder trains an encoder for a frozen decoder, e.g. the shipped one (cmtool/weights/rvae).
    pipeline runs the whole chain of a pipeline recipe (recipes/tiny-cpu/pipeline.toml): data, RVAE,
    decoder, DiT, ControlMap, packed weights and their evaluation, each stage into a folder of --out.

    Multi-GPU / multi-node: launch with torchrun, e.g.
    torchrun --nproc_per_node 8 -m cmtool train dit --recipe recipes/paper/dit-b.toml
    """
    from cmtool.train.recipe import load_recipe

    rec = load_recipe(recipe)
    if serve and no_log:
        raise CmtoolError("--serve and --no-log: a recording to serve needs logging")
    port = None
    if serve and launch()[0] == 0:  # the main process of a torchrun launch records
        from cmtool.viz.recording import GRPC_PORT, serve_web_viewer

        click.echo(serve_web_viewer(), err=True)
        port = GRPC_PORT
    if stage == "pipeline":
        _train_pipeline(rec, out, resume, data_dir, steps, precision, device, quiet, port, not no_log)
        return
    if rec.pipeline.rvae:
        raise CmtoolError(f"{recipe}: a pipeline recipe; run it with `cmtool train pipeline`")
    if rec.train.stage and rec.train.stage != stage:
        raise CmtoolError(f"{recipe}: a recipe for the {rec.train.stage} stage, not {stage}")
    if steps is not None:
        rec.train.steps = steps
    if precision is not None:
        rec.train.precision = precision
    if data_dir is not None:
        rec.train.data = str(data_dir)
    run_dir = out or (Path(rec.train.out) if rec.train.out else None)
    if run_dir is None:
        raise CmtoolError(f"{recipe}: no run folder: give --out or set train.out")
    claim_folder(run_dir)  # --out is claimed as it is parsed; the recipe's folder here

    from cmtool.train.loop import train
    from cmtool.train.stages import STAGES

    final = train(STAGES[stage](rec, _device(device)), run_dir, resume=resume, progress=not quiet, serve=port,
                  log=not no_log)
    click.echo(f"checkpoint: {final}")


def _train_pipeline(rec, out, resume, data_dir, steps, precision, device, quiet, serve, log):
    from cmtool.pipeline import Pipeline, summary

    if not rec.pipeline.rvae:
        raise CmtoolError(f"{rec.path}: no [pipeline] table; `train pipeline` takes a pipeline recipe "
                          "(recipes/tiny-cpu/pipeline.toml)")
    if steps is not None:
        raise CmtoolError("--steps: set train.steps in the stage recipes a pipeline names")
    if out is None:
        raise CmtoolError("train pipeline: give --out, the folder of its stages")
    if (out / "pipeline.json").exists() and not resume and launch()[0] == 0:
        raise CmtoolError(f"{out}: holds a pipeline run; pass --resume to continue it or choose another --out")
    if data_dir is not None and not (data_dir / "manifest.json").is_file():
        raise CmtoolError(f"--data {data_dir}: not a dataset (no manifest.json); build one with `cmtool data build`")
    if precision is not None:
        rec.pipeline.precision = precision
    report = Pipeline(rec, out, _device(device), progress=not quiet, data_dir=data_dir, serve=serve, log=log).run()
    click.echo(summary(report))
    if (out / "eval" / "summary.md").is_file():
        click.echo(f"evaluation: {out / 'eval' / 'summary.md'}; weights: {out / 'weights'}")
