"""``cmtool sample``: HD maps for a list of SD inputs, as lane graph JSON, pictures and one recording.

Maps are generated in batches; every input gets ``num`` maps. A batch's randomness comes from
``seed`` and the number of its first map, so the same command (inputs, options, checkpoint,
device) gives the same maps, also when the processes of a ``torchrun`` share the batches.
Outputs per map in ``out``: ``<name>.json`` (the lane graph, successors inferred), ``<name>.png``
(SD | generated | ground truth when known; none with ``pictures`` off) and ``<name>.gt.json`` (the ground truth,
when known);
plus one ``.rrd`` with every denoising step of every map (:mod:`cmtool.viz.trajectory`). The files
are written as one set: each to a temporary file, all renamed into place when the run succeeds, so
a failed run leaves earlier files as they were.
"""

from __future__ import annotations

import time
from functools import partial
from pathlib import Path

import numpy as np
import rerun as rr

from cmtool.core import dist as D
from cmtool.core.errors import CmtoolError
from cmtool.core.jsonio import OutputSet
from cmtool.core.outputs import target
from cmtool.core.progress import Progress
from cmtool.data.layouts import layout_raster
from cmtool.maps.lanegraph import LaneGraph
from cmtool.metrics.decisions import unexplained
from cmtool.model import checkpoint as ckpt
from cmtool.model.controlmap import NO_LAYOUT
from cmtool.sample.checks import check_maps
from cmtool.sample.files import MAP_FILES, MapFiles
from cmtool.sample.generator import MapGenerator
from cmtool.sample.inputs import ControlInput
from cmtool.sample.job import AUTO, Job, SampledMap, SampleSettings
from cmtool.sample.layouts import NO_INIT, layout_scenes
from cmtool.sample.pool import pipelined
from cmtool.sample.roads import frame_roads
from cmtool.sample.scores import SCORES, SCORES_NOTE, choose
from cmtool.viz.recording import log_decoded, log_lanes, log_layout, log_sd
from cmtool.viz.trajectory import TrajectoryLogger, log_scores, sampling_blueprint
from cmtool.viz.viewer import drop_recording, finish_recording, run_recording


def plan(gen: MapGenerator, inputs: list[ControlInput], settings: SampleSettings) -> list[Job]:
    """The maps to make (validates the options against the checkpoint before anything runs)."""
    settings.check()
    gen.schedule.timesteps(settings.steps)  # a step count the schedule cannot do fails here
    if any(item.sd is not None for item in inputs) and not gen.has_control:
        raise CmtoolError(f"{gen.path}: a DiT checkpoint has no control branch; give a ControlMap checkpoint "
                          "or no SD input")
    starts = controls = [None] * len(inputs)
    if settings.init != NO_INIT:
        gen.encode([])  # an RVAE without an encoder fails here, before any layout is made
        starts = layout_scenes(inputs, settings.init)
    if gen.layout != NO_LAYOUT:  # a picture whose roads could not be traced has no map: its channels stay empty
        mapped = [k for k, item in enumerate(inputs) if item.sd_map is not None and item.pose is not None]
        if settings.init == gen.layout:
            scenes = [starts[k] for k in mapped]
        else:
            scenes = layout_scenes([inputs[k] for k in mapped], gen.layout)
        controls = [None] * len(inputs)
        for k, scene in zip(mapped, scenes):
            controls[k] = layout_raster(scene, inputs[k].sd.shape[0])
    jobs = []
    for item, start, control in zip(inputs, starts, controls):
        label = gen.known_label(item.city) if settings.city.lower() == AUTO else gen.label(settings.city)
        for k in range(settings.num):
            for c in range(settings.candidates):
                jobs.append(Job(item.name if settings.num == 1 else f"{item.name}_s{k}", item, label, k, init=start,
                                layout=control, candidate=c))
    if len(jobs) > 1:
        for i, job in enumerate(jobs):
            job.prefix = f"sample_{i}/"
    return jobs


def run_sample(gen: MapGenerator, jobs: list[Job], settings: SampleSettings, out: Path, rrd: Path | None = None,
               viewer: str | None = None, command: str = "", progress: bool = True,
               grid: Path | None = None, info: D.DistInfo = D.SINGLE, pictures: bool = True,
               workers: int = 1) -> list[SampledMap] | None:
    """Generate every job's map, write its files to ``out`` and (unless ``rrd`` and ``viewer`` are
    None) record every step; ``viewer`` is "spawn", "serve" (the recording is served from this process until it
    ends) or a Rerun gRPC URL to stream to live; ``grid`` is a PNG that gets all maps' pictures stacked;
    ``pictures``: a picture per map (else the lane graphs only); ``workers``: processes that check the maps and make
    their files (:mod:`cmtool.sample.pool`; 1: a thread of this process). Under
    ``torchrun`` (``info``, several processes, no recording) the main process writes the files and returns the maps,
    the others only generate their share and return None."""
    if info.world > 1 and (rrd is not None or viewer is not None):
        raise CmtoolError(f"the {info.world} processes of a torchrun record no denoising steps: add --no-log")
    if not info.main:
        return generate_maps(gen, jobs, settings, None, progress, info)
    for job in jobs:  # refused before any work: a map's file that would replace an input (an SD picture in OUT)
        for suffix in MAP_FILES:
            target(out / f"{job.name}{suffix}")
    outputs = OutputSet()
    rec = None
    created = not out.exists()
    try:
        out.mkdir(parents=True, exist_ok=True)
        if rrd is not None or viewer is not None:
            rec = run_recording("sample", rrd, viewer)
            header = log_run_header(rec, gen, jobs, settings, command)
        strength = f", city cfg {settings.city_cfg:g}" if settings.city_cfg != 1 else ""
        files = MapFiles(out, f"generated: {{city}}, w = {settings.cfg:g}{strength}", outputs, pictures, grid)
        early = settings.candidates == 1  # each map's files staged as soon as it is checked, else the chosen ones
        made = generate_maps(gen, jobs, settings, rec, progress, info, files if early else None, workers)
        if rec is not None:
            log_map_scores(rec, header, made)
        maps = choose(made, settings.candidates)
        if not early:
            files.stage([m.job for m in maps], [m.graph for m in maps])
        files.finish()
        if rec is not None:
            finish_recording(rec, rrd, viewer, outputs)
            rec = None
        outputs.commit()
        return maps
    except BaseException:
        if rec is not None:
            drop_recording(rec, rrd)
        outputs.discard()
        if created and out.is_dir() and not any(out.iterdir()):
            out.rmdir()
        raise


def generate_maps(gen: MapGenerator, jobs: list[Job], settings: SampleSettings, rec, progress: bool,
                  info: D.DistInfo = D.SINGLE, files: MapFiles | None = None,
                  workers: int = 1) -> list[SampledMap] | None:
    """Sample, decode and (when ``rec`` is a recording) log every step of the jobs' maps, in batches, each map checked
    (:func:`~cmtool.sample.checks.check_maps`) and, with ``files`` (on the main process), its files staged there.
    Under ``torchrun`` (``info``) the processes take turns at the batches and the main process gets all maps (the
    others None); one process checks each batch in ``workers`` beside the denoising of the batches after it when
    there are several (:func:`cmtool.sample.pool.pipelined`)."""
    maps = []
    with Progress(len(jobs), "sample", "maps", enabled=progress and len(jobs) > 1 and info.main) as bar:
        if info.world == 1 and len(jobs) > settings.batch:
            decoded: dict[int, list[LaneGraph]] = {}  # with a recording: each batch's maps as decoded, until logged
            recorded = denoiser(gen, settings, rec)

            def denoise(batch: list[Job], start: int) -> list[LaneGraph]:
                graphs = recorded(batch, start)
                if rec is not None:
                    decoded[start] = list(graphs)
                return graphs

            def finished(start: int, graphs: list[LaneGraph], seconds: float) -> None:
                batch = jobs[start:start + len(graphs)]
                if rec is not None:
                    _log_maps(rec, batch, graphs, decoded.pop(start))
                maps.extend(SampledMap(job, graph, seconds) for job, graph in zip(batch, graphs))
                bar.update(len(graphs))

            pipelined(jobs, settings, denoise, files, workers, finished)
            return maps
        make = lambda start: (start, batch_maps(gen, jobs[start:start + settings.batch], start, settings, rec))  # noqa: E731
        for start, batch in D.dealt(list(range(0, len(jobs), settings.batch)), info, make):
            if files is not None:
                files.stage(jobs[start:start + len(batch)], [graph for graph, _ in batch])
            maps += [SampledMap(jobs[start + k], graph, seconds) for k, (graph, seconds) in enumerate(batch)]
            bar.update(len(batch))
    return maps if info.main else None


def batch_maps(gen: MapGenerator, batch: list[Job], start: int, settings: SampleSettings,
               rec, placed: bool = False) -> list[tuple[LaneGraph, float]]:
    """The lane graphs of the jobs ``batch`` (jobs ``start``, ``start + 1``, ...) with each map's share of the
    time; the batch's noise depends on the seed and ``start`` alone, as in ``cmtool eval``. ``rec``: records every
    step of each map under its job's prefix, and the map; ``placed``: only the steps, the caller placing each prefix
    (:class:`~cmtool.viz.trajectory.TrajectoryLogger`'s ``ego``)."""
    logger = None if rec is None else _step_logger(gen, rec, batch, settings, ego=not placed)
    began = time.perf_counter()
    graphs = _denoised(gen, batch, start, settings, logger)
    decoded = list(graphs)
    check_maps(batch, graphs, settings)
    if logger is not None:
        logger.finish(_estimates(decoded))
        if not placed:
            _log_maps(rec, batch, graphs, decoded)
    seconds = (time.perf_counter() - began) / len(batch)
    return [(graph, seconds) for graph in graphs]


def denoiser(gen: MapGenerator, settings: SampleSettings, rec, ego: bool = True, recorded=None):
    """``denoise(batch, start)``: a batch's lane graphs as the model drew them (:func:`_denoised`), every step
    recorded to ``rec`` (when not None) for the batches whose start ``recorded(start)`` is true (all by default);
    ``ego``: as :class:`~cmtool.viz.trajectory.TrajectoryLogger`'s."""
    def denoise(batch: list[Job], start: int) -> list[LaneGraph]:
        logger = None
        if rec is not None and (recorded is None or recorded(start)):
            logger = _step_logger(gen, rec, batch, settings, ego)
        graphs = _denoised(gen, batch, start, settings, logger)
        if logger is not None:
            logger.finish(_estimates(graphs))
        return graphs
    return denoise


def _estimates(graphs: list[LaneGraph]) -> list[dict]:
    """The maps as decoded, as :meth:`~cmtool.viz.trajectory.TrajectoryLogger.finish` takes them."""
    return [{"lines": g.lanes, "green": g.green_lights, "red": g.red_lights} for g in graphs]


def _step_logger(gen: MapGenerator, rec, batch: list[Job], settings: SampleSettings, ego: bool = True):
    return TrajectoryLogger(rec, [j.prefix for j in batch], partial(gen.decode, preview=True), settings.cfg, ego=ego)


def _log_maps(rec, batch: list[Job], graphs: list[LaneGraph], decoded: list[LaneGraph]) -> None:
    """Log each job's map and, where the guarantee changed it, the map as decoded beneath it, the lanes it left out
    marked (:func:`~cmtool.viz.recording.log_decoded`)."""
    for job, graph, raw in zip(batch, graphs, decoded):
        log_lanes(rec, job.prefix, graph.lanes, graph.green_lights, graph.red_lights, graph.successors, static=True)
        if "raw" in graph.meta and not _same_lanes(graph, raw):
            src = job.source
            dropped = unexplained(raw, frame_roads(src.sd_map, src.pose, raw.frame_m)) if "composed" in graph.meta \
                else []
            log_decoded(rec, job.prefix, raw.lanes, dropped)


def _same_lanes(a: LaneGraph, b: LaneGraph) -> bool:
    return len(a.lanes) == len(b.lanes) and all(np.array_equal(x, y) for x, y in zip(a.lanes, b.lanes))


def _denoised(gen: MapGenerator, batch: list[Job], start: int, settings: SampleSettings,
              logger: TrajectoryLogger | None) -> list[LaneGraph]:
    """The jobs' lane graphs as the model made them (:meth:`MapGenerator.generate`), ``logger`` getting every step;
    their lanes' neighbours are left to the checks (:func:`~cmtool.sample.checks.check_maps`, in the workers)."""
    sds = [j.source.sd for j in batch]
    sd = None if all(s is None for s in sds) else np.stack(sds)
    init = gen.encode([j.init for j in batch]) if settings.init != NO_INIT else None
    return gen.generate(sd, [j.label for j in batch], settings, start, city_cfg=settings.city_cfg, eta=settings.eta,
                        init=init, strength=settings.strength, layouts=[j.layout for j in batch],
                        metas=[_meta(gen, j, settings) for j in batch], callback=logger, found=False)


def _meta(gen: MapGenerator, job: Job, settings: SampleSettings) -> dict:
    geo = {} if job.source.geo is None else {"geo": job.source.geo}
    return {"source": job.source.source, "checkpoint": ckpt.shown(gen.path), "seed": settings.seed, "index": job.index,
            "cfg": settings.cfg, "city_cfg": settings.city_cfg, "steps": settings.steps, "sampler": settings.sampler,
            "eta": settings.eta, "smooth": gen.smooth, "precision": gen.precision, **geo,
            **({"init": settings.init, "strength": settings.strength} if settings.init != NO_INIT else {}),
            **({"layout": gen.layout if job.layout is not None else NO_LAYOUT} if gen.layout != NO_LAYOUT else {})}


def log_run_header(rec, gen: MapGenerator, jobs: list[Job], settings: SampleSettings, command: str) -> str:
    """Send the layout, each map's SD input, layout channels and ground truth, and the run's info document; returns
    the document's text, which :func:`log_map_scores` extends."""
    names = [f"{j.name}{f' #{j.candidate}' if settings.candidates > 1 else ''} ({gen.city_name(j.label) or 'no city'})"
             for j in jobs]
    rec.send_blueprint(sampling_blueprint([j.prefix for j in jobs], names, gen.control_blocks,
                                          any(j.source.truth is not None for j in jobs)))
    lines = [f"# cmtool sample\n\n`{command}`\n" if command else "# cmtool sample\n",
             f"- checkpoint: `{ckpt.shown(gen.path)}` ({gen.config['kind']})",
             f"- seed {settings.seed}, cfg w = {settings.cfg}, city cfg {settings.city_cfg}, "
             f"{settings.steps} {settings.sampler} steps"
             + (f", eta {settings.eta}" if settings.sampler == "ddim" else ""), "",
             "Maps (number: name, city, input):", ""]
    lines += [f"- {k}: {name}, {j.source.source}" for k, (j, name) in enumerate(zip(jobs, names))]
    header = "\n".join(lines)
    rec.log("info", rr.TextDocument(header, media_type="text/markdown"), static=True)
    for job in jobs:
        if job.source.sd is not None:
            log_sd(rec, job.prefix, job.source.sd, static=True)
        if job.layout is not None:
            log_layout(rec, job.prefix, job.layout)
        truth = job.source.truth
        if truth is not None:
            log_lanes(rec, f"{job.prefix}truth/", truth.lanes, truth.green_lights, truth.red_lights, truth.successors,
                      static=True)
    return header


def log_map_scores(rec, header: str, maps: list[SampledMap]) -> None:
    """Add the scores of every map made (in the order of the jobs) to the info document ``header``, as a table, and
    log them as bars (:func:`~cmtool.viz.trajectory.log_scores`)."""
    scores = {key: [m.graph.meta.get(key) for m in maps] for key in SCORES}
    dash = lambda v: "-" if v is None else f"{v:.3f}"  # noqa: E731
    rows = ["| map | " + " | ".join(SCORES.values()) + " |", "|---" * (len(SCORES) + 1) + "|"]
    rows += [f"| {k} | " + " | ".join(dash(scores[key][k]) for key in SCORES) + " |" for k in range(len(maps))]
    rec.log("info", rr.TextDocument("\n".join([header, "", *rows, "", SCORES_NOTE]), media_type="text/markdown"),
            static=True)
    log_scores(rec, {name: scores[key] for key, name in SCORES.items()})
