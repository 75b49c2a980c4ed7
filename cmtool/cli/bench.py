"""``cmtool bench``: timing sampling and the metrics."""

from __future__ import annotations

import click

from cmtool.cli.common import (FEATURE_PRECISION_OPTION, PRECISION_OPTION, WORKERS_OPTION, DatasetDir, Finite, InPath,
                               _device, _generator, check_map_inputs, map_inputs, sampler_options)
from cmtool.diffusion.settings import SAMPLERS, TABLE_STEPS


@click.group()
def bench():
    """Speed measurements (timings are printed, never asserted by tests)."""


@bench.command("sample")
@click.option("--ckpt", type=InPath(),
              help="ControlMap (or DiT) checkpoint or run folder [default: the weights shipped with cmtool].")
@click.option("--sd", "sd_path", type=InPath(), help="SD input [default: a procedural crossing].")
@sampler_options
@click.option("--cfg", default=1.0, show_default=True, type=Finite(min=0), help="Guidance weight.")
@click.option("--batch", type=click.IntRange(2, 4096),
              help="The large batch to compare (with --data: the batch of every row) [default: 64; with --from-hd: "
                   "16, as `cmtool sample`].")
@click.option("--repeats", default=3, show_default=True, type=click.IntRange(1, 1000), help="Timed runs per setting.")
@click.option("--data", type=DatasetDir(),
              help="Instead: the quality-speed table of every sampler over --table-steps, on this dataset's first --n "
                   "test scenes (`cmtool data build`).")
@click.option("--n", default=64, show_default=True, type=click.IntRange(1, 100_000), help="With --data: scenes.")
@click.option("--table-steps", default=",".join(map(str, TABLE_STEPS)), show_default=True,
              help="With --data: the step counts, comma-separated.")
@click.option("--samplers", default=",".join(SAMPLERS), show_default=True,
              help="With --data: the samplers, comma-separated.")
@click.option("--features", is_flag=True,
              help="With --data: GT Recall and the features' precision and recall too (ResNet-50; --n of 64 or more).")
@click.option("--from-hd", type=InPath(dir_okay=False),
              help="Instead: whole runs end to end (frames in, files out) on this HD map's frames at --pose, in maps "
                   "per second for 1 to --workers worker processes and with the recording on.")
@click.option("--pose", help="With --from-hd: X,Y,YAW or a .jsonl file of poses (`cmtool data poses`).")
@click.option("--workers", "max_workers", type=click.IntRange(min=1),
              help="With --from-hd: the most worker processes to time [default: one per CPU core].")
@click.option("--device", help="torch device [default: cuda when available, else cpu].")
@PRECISION_OPTION
def bench_sample_cmd(ckpt, sd_path, steps, sampler, cfg, batch, repeats, data, n, table_steps, samplers, features,
                     from_hd, pose, max_workers, device, precision):
    """Time sampling: per-step logging against --no-log at batch 1, and batch 1 against a large batch; with --data,
    the quality-speed table of the samplers instead (the same noise per scene for every row); with --from-hd, whole
    runs end to end."""
    from cmtool.core.workers import MODEL_THREADS
    from cmtool.eval.bench_sample import LOG_LIMIT, bench_sample, default_sd
    from cmtool.sample.inputs import image_inputs
    from cmtool.sample.job import SampleSettings

    settings = SampleSettings(steps=steps, cfg=cfg, sampler=sampler)
    settings.check()
    counts, names = _step_list(table_steps), _sampler_list(samplers)
    if from_hd is not None:
        if data is not None or sd_path is not None:
            raise click.UsageError("--from-hd times whole runs on its own frames: leave out --data and --sd")
        if pose is None:
            raise click.UsageError("--from-hd: give the frames' poses with --pose (`cmtool data poses`)")
        check_map_inputs(None, None, from_hd, pose)
    elif pose is not None:
        raise click.UsageError("--pose goes with --from-hd")
    gen = _generator(ckpt, device, precision=precision)
    dev = gen.device
    params = sum(p.numel() for p in gen.model.parameters())
    head = f"{gen.path}: {gen.config['kind']}, {params / 1e6:.1f}M parameters; {dev} ({MODEL_THREADS} torch " \
           f"thread{'s' if MODEL_THREADS > 1 else ''} in the model's passes, {precision})"
    if from_hd is not None:
        _end_to_end(gen, head, settings, from_hd, pose, batch or 16, repeats, max_workers)
        return
    batch = batch or 64
    if data is not None:
        _table(gen, head, data, n, counts, names, cfg, batch, features, device)
        return
    sd = image_inputs([sd_path])[0].sd if sd_path else default_sd()
    click.echo(f"{head}; {steps} {settings.sampler} steps, cfg {cfg}")
    r = bench_sample(gen, sd, settings, batch=batch, repeats=repeats)
    verdict = "within" if r["log_ratio"] <= LOG_LIMIT else "OVER"
    click.echo(f"full logging / --no-log at batch 1: {r['log_ratio']:.3f} ({verdict} the {LOG_LIMIT:.2f} limit)")
    click.echo(f"batch {batch} / batch 1, time per map: {1 / r['batch_speedup']:.3f} "
               f"({r['batch_speedup']:.1f}x faster per map)")


def _end_to_end(gen, head: str, settings, from_hd, pose, batch: int, repeats: int, max_workers) -> None:
    """``bench sample --from-hd``: whole runs' maps per second."""
    import platform
    from functools import partial

    from cmtool.core.workers import cores
    from cmtool.eval.bench_sample import E2E_HEAD, end_to_end

    inputs = partial(map_inputs, None, None, None, from_hd, pose, settings.seed)
    settings.batch = batch
    click.echo(f"{head}; {settings.steps} {settings.sampler} steps, cfg {settings.cfg}, batch {batch}, "
               f"{len(inputs())} frames of {from_hd}; "
               f"CPU: {_cpu_name() or platform.processor() or 'unknown'}, {cores()} cores; seconds of a whole run "
               "(frames read, layouts, maps, checks, files), the model loaded once")
    click.echo(E2E_HEAD)
    end_to_end(gen, inputs, settings, list(range(1, (max_workers or cores()) + 1)), repeats, report=click.echo)


def _cpu_name() -> str | None:
    try:
        for line in open("/proc/cpuinfo"):
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        return None
    return None


def _table(gen, head: str, data, n: int, counts: list[int], names: list[str], cfg: float, batch: int, features: bool,
           device) -> None:
    """``bench sample --data``: the quality-speed table."""
    from functools import partial

    from cmtool.data.cache import MissingSDMaps, load_dataset, scene_sd_maps
    from cmtool.data.layouts import scene_layouts
    from cmtool.eval.bench_sample import sampler_table
    from cmtool.eval.evaluation import as_sampled, baseline_methods
    from cmtool.metrics.features import FeatureExtractor

    if not gen.has_control:
        raise click.UsageError("--data: the quality-speed table needs a ControlMap checkpoint")
    for steps in counts:
        gen.schedule.timesteps(steps)  # a count the schedule cannot do fails before any work
    dataset = load_dataset(data, "test")
    scenes = [dataset.scene(i) for i in range(min(n, len(dataset)))]
    if features and len(scenes) < 64:
        raise click.UsageError(f"--features: GT Recall needs at least 64 scenes (batches of 64), got {len(scenes)}")
    extractor = FeatureExtractor("resnet50-seeded", None, _device(device)) if features else None
    try:
        sd_maps = scene_sd_maps(data, "test")[:len(scenes)]
        final = partial(as_sampled, data=data, split="test", scenes=scenes)
        what = "the maps as cmtool sample writes them (composed from the SD map, the guarantee)"
        baselines = {m: [s.to_lanegraph() for s in scene_layouts(data, "test", scenes, m)] for m in baseline_methods()}
    except MissingSDMaps as e:
        final, what, sd_maps, baselines = None, f"the model's maps ({e})", None, None
    click.echo(f"{head}; {len(scenes)} test scenes of {data}, cfg {cfg}, batch {batch}; scores of {what}; seconds "
               "per map: denoising, decoding and lane graphs")
    sampler_table(gen, scenes, cfg, names, counts, batch, extractor=extractor, report=click.echo, final=final,
                  sd_maps=sd_maps, baselines=baselines)


def _step_list(text: str) -> list[int]:
    try:
        counts = [int(v) for v in text.split(",")]
    except ValueError:
        counts = []
    if not counts or min(counts) < 1:
        raise click.BadParameter(f"expected positive whole numbers separated by commas, got {text!r}",
                                 param_hint="--table-steps")
    return counts


def _sampler_list(text: str) -> list[str]:
    names = [v.strip() for v in text.split(",")]
    unknown = [v for v in names if v not in SAMPLERS]
    if unknown:
        raise click.BadParameter(f"unknown sampler {unknown[0]!r} (choose {', '.join(SAMPLERS)})",
                                 param_hint="--samplers")
    return names


@bench.command("dit")
@click.option("--size", default="B", show_default=True, help="DiT size (tiny, S, B, L, XL).")
@click.option("--batch", default=32, show_default=True, type=click.IntRange(1, 4096), help="Latents per forward pass.")
@click.option("--repeats", default=5, show_default=True, type=click.IntRange(1, 1000), help="Timed passes per setting.")
def bench_dit_cmd(size, batch, repeats):
    """This project's DiT forward pass against diffusers' DiTTransformer2DModel of the same shape and batch, fp32
    and bf16 autocast, on the CPU (needs `pip install 'cmtool[bench]'`)."""
    from cmtool.eval.bench_dit import bench_dit

    bench_dit(size, batch, repeats, report=click.echo)


@bench.command("metrics")
@click.option("--eval", "eval_dir", required=True, type=InPath(file_okay=False),
              help="A `cmtool eval --out` folder: its cached maps and the scenes they were made for.")
@click.option("--method", default="controlmap", show_default=True, type=click.Choice(["controlmap", "unguided"]))
@click.option("--tile", default=1, show_default=True, type=click.IntRange(1, 64),
              help="Repeat the set this many times (512 x 8 = 4,096 is the paper's test-set size).")
@click.option("--repeats", default=3, show_default=True, type=click.IntRange(1, 1000), help="Timed runs.")
@click.option("--no-features", is_flag=True, help="Leave out the ResNet-50 metrics.")
@click.option("--device", help="torch device [default: cuda when available, else cpu].")
@FEATURE_PRECISION_OPTION
@WORKERS_OPTION
def bench_metrics_cmd(eval_dir, method, tile, repeats, no_features, device, feature_precision, workers):
    """Time each family of metrics (topology, lane distances, validity, SD adherence, driving side, legal
    one-way, features, recall) on an evaluation's maps: minimum and median over the repeats; with the features,
    also the ResNet-50 passes alone on the same rasters."""
    from cmtool.core.workers import cores
    from cmtool.eval.bench_metrics import bench_metrics, eval_set, report_table
    from cmtool.metrics.features import FeatureExtractor

    generated, reference, controls = eval_set(eval_dir, method, tile)
    extractor = None if no_features else FeatureExtractor("resnet50-seeded", None, _device(device),
                                                          precision=feature_precision)
    click.echo(report_table(bench_metrics(generated, reference, controls, extractor, repeats, workers or cores())))


@bench.command("train")
@click.option("--recipe", required=True, type=InPath(), help="A stage recipe, or a pipeline recipe (each training stage "
                                                               "whose inputs exist).")
@click.option("--data", "data_dir", type=DatasetDir(), help="Dataset folder [default: the recipe's; a pipeline's: "
                                                            "RUN/data].")
@click.option("--run", "run_dir", type=InPath(file_okay=False, exists=True),
              help="A pipeline run folder (`cmtool train pipeline --out`): its finished stages feed the later ones.")
@click.option("--steps", default=10, show_default=True, type=click.IntRange(1, 100_000), help="Timed batches per rate.")
@click.option("--workers", type=click.IntRange(min=0), help="DataLoader workers [default: each recipe's].")
@click.option("--precision", type=click.Choice(["auto", "fp32", "bf16"]), help="Override train.precision.")
@click.option("--device", help="torch device [default: cuda when available, else cpu].")
def bench_train_cmd(recipe, data_dir, run_dir, steps, workers, precision, device):
    """Time each training stage: samples per second of the data path alone, of the model step alone (forward,
    backward, optimiser) and of both together, so you see which one bounds a run."""
    from cmtool.core.errors import CmtoolError
    from cmtool.train.bench import bench_stage
    from cmtool.train.recipe import load_recipe
    from cmtool.train.stages import STAGES

    rec = load_recipe(recipe)
    if rec.pipeline.rvae:
        from cmtool.pipeline import Pipeline

        if data_dir is None and run_dir is None:
            raise CmtoolError("bench train: give --data (the RVAE stage) or --run (every stage it holds the inputs of)")
        run = Pipeline(rec, run_dir or data_dir, _device(device), data_dir=data_dir)
        recipes = {name: run.stage_recipe(name) for name in run.stages if name in STAGES}
        if run_dir is None:
            for name in [n for n in recipes if n != "rvae"]:
                click.echo(f"{name}: not timed (give --run, a pipeline run folder with the stages it reads)", err=True)
                del recipes[name]
    else:
        if run_dir is not None:
            raise click.UsageError(f"--run goes with a pipeline recipe; {recipe} is a stage recipe (its inputs are "
                                   "the folders it names)")
        if data_dir is not None:
            rec.train.data = str(data_dir)
        recipes = {rec.train.stage or "rvae": rec}
    rows = []
    for name, stage_recipe in recipes.items():
        if precision is not None:
            stage_recipe.train.precision = precision
        try:
            rows.append(bench_stage(STAGES[name](stage_recipe, _device(device)), steps, workers))
        except CmtoolError as e:
            click.echo(f"{name}: not timed ({e})", err=True)
    if not rows:
        raise CmtoolError(f"{recipe}: no stage could be timed (give --data, and --run for the stages after the RVAE)")
    click.echo(f"device: {_device(device)}; samples per second over {steps} batches each")
    click.echo("| stage | batch | workers | prepare s | data path | model step | together | data / model | bound by |")
    click.echo("|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        bound = "data" if r["data"] < 1.5 * r["model"] else "model"
        click.echo(f"| {r['stage']} | {r['batch']} | {r['workers']} | {r['prepare_s']:.1f} | {r['data']:,.0f} | "
                   f"{r['model']:,.1f} | {r['both']:,.1f} | {r['data'] / r['model']:,.1f} | {bound} |")
