"""``cmtool eval``: generate one map per test scene twice and score both, and the rule-based layout of the same SD
input, against the ground truth.

- **unguided** baseline: the DiT alone, no SD control and no city label (the paper's SLEDGE rows);
- **rules** baseline: the rule-based lane layout of the scene's SD map (:mod:`cmtool.data.rules`), cropped as the
  scene was, and **netconvert**, SUMO's layout of it (:mod:`cmtool.formats.sumo`) when SUMO is installed; both
  left out, with a note, for datasets built before they stored their SD maps;
- **ControlMap**: the scene's SD raster as control at guidance weight ``cfg``, with the scene's city
  label when the checkpoint knows it (else the null label).

Both use the same initial noise per scene (drawn per batch from the seed and the batch's first
scene, so processes under ``torchrun`` can share the batches). Generated maps go to a cache,
``<out>/cache/{unguided,controlmap}.jsonl``, one batch at a time, so an interrupted run continues
where it stopped (the cache remembers its settings and refuses to mix runs). Then ``metrics.json``, ``summary.md``
(tables shaped like the paper's Tables 1 and 2 plus our geometric metrics, lanes per map and lane F1 in junction
frames and the others, lanes per SD road direction, junction movements and the lane length no SD road explains:
:mod:`cmtool.metrics.decisions`), ``gallery.png`` (a few junction frames and others, every method side by side) and ``eval.rrd``
(on the ``sample`` timeline: SD | unguided | rules | netconvert | ControlMap | ground truth of the first
``rrd_samples`` scenes with their scores, and per-scene scores of all scenes).
"""

from __future__ import annotations

import json
import sys
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from cmtool.core import dist as D
from cmtool.core.errors import CmtoolError
from cmtool.core.jsonio import read_json, write_json, write_text_atomic
from cmtool.core.progress import Progress
from cmtool.core.workers import each
from cmtool.data.cache import MissingSDMaps, load_dataset, scene_sd_maps
from cmtool.data.layouts import LAYOUTS, layout_raster, scene_layouts
from cmtool.data.scene import Scene
from cmtool.diffusion.settings import SamplerSettings
from cmtool.formats.sumo import netconvert_path
from cmtool.maps.hdmap import drives_on
from cmtool.maps.lanegraph import LaneGraph, write_jsonl
from cmtool.metrics.decisions import decisions
from cmtool.metrics.features import FeatureExtractor
from cmtool.metrics.lanes import lane_scores
from cmtool.metrics.suite import evaluate, shared_features, summary_table
from cmtool.metrics.validity import check
from cmtool.model import checkpoint as ckpt
from cmtool.model.controlmap import NO_LAYOUT
from cmtool.model.release import BUNDLED
from cmtool.sample import DEFAULT_COUNTS, DEFAULT_SMOOTH
from cmtool.sample.checks import guaranteed
from cmtool.sample.compose import check_counts
from cmtool.sample.generator import MapGenerator
from cmtool.sample.layouts import NO_INIT, check_init
from cmtool.sample.roads import drawn_lane_counts, frame_roads
from cmtool.viz.draw import graph_panel, grid, sd_panel, title_strip
from cmtool.viz.recording import close_recording, log_lanes, log_sd, open_recording
from cmtool.viz.show import write_png
from cmtool.viz.trajectory import key_view, log_key

METHODS = ("unguided", "controlmap")
# How each batch's noise is drawn (x_T from the scene seed, step noise from ``step_generator``). Caches
# written before the step noise had a stream of its own lack it, so they are refused, not extended.
NOISE = "x_T per batch, steps on their own stream"


@dataclass(kw_only=True)
class EvalSettings(SamplerSettings):
    """``cmtool eval``'s settings: the sampler's, the scenes, and what the maps were made with (the cache's key)."""

    data: str
    split: str = "test"
    n: int = 3904
    batch: int = 64
    smooth: int = DEFAULT_SMOOTH  # Bézier control points of the decoded lanes (the generator's)
    checkpoint: str = ""
    weights: str = ""  # digest of the ControlMap's and its RVAE's weights (a re-pack keeps the path)
    noise: str = NOISE
    precision: str = "fp32"  # of the denoising model (MapGenerator.precision)
    init: str = NO_INIT  # ControlMap starts from this layout of the scene's SD map (cmtool.sample.layouts), encoded
    strength: float = 1.0  # ... noised this far up the schedule
    lane_counts: str = DEFAULT_COUNTS  # an untagged road's lanes in the "+ guarantee" maps (cmtool.sample.compose)

    def check(self, prefix: str = "--") -> None:
        super().check(prefix)
        check_init(self.init, self.strength, prefix)
        check_counts(self.lane_counts, prefix)


def run_eval(gen: MapGenerator, settings: EvalSettings, out: Path, extractor: FeatureExtractor | None,
             rrd_samples: int = 64, progress: bool = True, info: D.DistInfo = D.SINGLE,
             workers: int = 1, record: bool = True) -> dict | None:
    """Generate (or continue generating) both sets, compute the metrics and write the reports. Under ``torchrun``
    (``info``) the processes take turns at the batches and the main process scores and writes everything; the
    others return None. ``workers``: processes for the per-scene metrics (:func:`cmtool.metrics.suite.evaluate`) and
    the guarantee (:func:`as_sampled`, 64 scenes or more);
    ``record=False``: no ``eval.rrd``."""
    settings.check()
    if not gen.has_control:
        raise CmtoolError(f"{gen.path}: eval compares ControlMap with its unguided DiT; give a ControlMap checkpoint")
    data = load_dataset(settings.data, settings.split)
    n = min(settings.n, len(data))
    settings.n, settings.checkpoint, settings.smooth = n, str(gen.path), gen.smooth
    settings.weights = ckpt.weights_digest(gen.path, gen.rvae_checkpoint,
                                           *([gen.encoder_path] if settings.init != NO_INIT and gen.encoder_path else []))
    scenes = [data.scene(i) for i in range(n)]
    starts = layouts = None
    if settings.init != NO_INIT:
        gen.encode([])  # an RVAE without an encoder fails here
        starts = scene_layouts(settings.data, settings.split, scenes, settings.init)
    if gen.layout != NO_LAYOUT:
        read = starts if settings.init == gen.layout else scene_layouts(settings.data, settings.split, scenes,
                                                                         gen.layout)
        layouts = [layout_raster(scene, s.sd.shape[0]) for scene, s in zip(read, scenes)]
    generated = _generate(gen, scenes, settings, out / "cache", progress, info, starts, layouts)
    if not info.main:
        return None
    roads = None
    try:
        baselines = {m: [_as_map(s, m, k) for k, s in enumerate(
                         starts if m == settings.init else scene_layouts(settings.data, settings.split, scenes, m))]
                     for m in baseline_methods()}
        final = as_sampled(generated["controlmap"], settings.data, settings.split, scenes, settings.lane_counts,
                           workers)
        sd_maps = scene_sd_maps(settings.data, settings.split)
        counts = lane_count_agreement(scenes, {"model": generated["controlmap"], "guaranteed": final,
                                               "rules": baselines["rules"]}, sd_maps)
        roads = [frame_roads(sd_map, s.pose.as_array(), s.frame_m) for s, sd_map in zip(scenes, sd_maps)]
        generated = {"unguided": generated["unguided"], **baselines, "controlmap": generated["controlmap"],
                     "guaranteed": final}
    except MissingSDMaps as e:
        print(f"note: no rule-based columns: {e}", file=sys.stderr)
        counts = None
    reference = [s.to_lanegraph() for s in scenes]
    controls = np.stack([s.sd for s in scenes])
    shared = {}
    if extractor is not None:  # the ground truth's and the controls' features serve both methods
        shared = shared_features(reference, controls, extractor)
    results = {m: evaluate(maps, reference, controls, extractor, features=extractor is not None,
                           progress=progress, workers=workers, **shared) for m, maps in generated.items()}
    truth = [check(g) for g in reference]
    report = {"settings": asdict(settings), "methods": results, "frames": frame_groups(scenes, reference, generated),
              "ground_truth_validity": float(np.mean([r.score for r in truth])),
              "ground_truth_routable": float(np.mean([r.routable_with_changes for r in truth])),
              **({"lane_counts": counts} if counts else {}),
              **({"decisions": decisions(generated, reference, roads)} if roads is not None else {})}
    write_json(out / "metrics.json", report)
    write_text_atomic(out / "summary.md", summary_markdown(report))
    if record:
        _write_recording(out / "eval.rrd", scenes, reference, generated, results, rrd_samples)
    write_png(out / "gallery.png", gallery(scenes, reference, generated))
    return report


def baseline_methods() -> list[str]:
    """The layouts of the SD map eval compares (:data:`cmtool.data.layouts.LAYOUTS`; netconvert where SUMO is
    installed)."""
    return [m for m in LAYOUTS if m != "netconvert" or netconvert_path() is not None]


def lane_count_agreement(scenes, maps: dict[str, list[LaneGraph]], sd_maps) -> dict:
    """How many lanes a direction of each SD road in the frames has in each of ``maps`` (the model's own, the maps
    ``cmtool sample`` writes, the rules') against the ground truth, all counted by :func:`drawn_lane_counts`, over the
    road directions where the ground truth has lanes: the share equal to the truth's, the mean difference and the mean
    absolute difference."""
    diffs = {k: [] for k in maps}
    for f, (scene, sd_map) in enumerate(zip(scenes, sd_maps)):
        roads, side = frame_roads(sd_map, scene.pose.as_array(), scene.frame_m), drives_on(scene.city)
        truth = drawn_lane_counts(scene.to_lanegraph(), roads, side)
        for k, m in maps.items():
            drawn = drawn_lane_counts(m[f], roads, side)
            diffs[k] += [drawn.get(key, 0) - n for key, n in truth.items()]
    return {k: {"road_directions": len(v), "equal": float(np.mean(np.equal(v, 0))),
                "mean_difference": float(np.mean(v)), "mean_abs_difference": float(np.mean(np.abs(v)))}
            for k, v in diffs.items() if v}


def as_sampled(maps: list[LaneGraph], data, split: str, scenes, counts: str = DEFAULT_COUNTS,
               workers: int = 1) -> list[LaneGraph]:
    """The maps of a dataset split's first scenes as ``cmtool sample`` writes them (:func:`guaranteed`: composed from
    the scenes' SD maps; ``counts``: :func:`cmtool.sample.compose.compose`'s), in ``workers`` processes; raises
    ``MissingSDMaps`` for a dataset built before SD maps were stored."""
    items = [(m, s, sd_map, counts) for m, s, sd_map in zip(maps, scenes, scene_sd_maps(data, split))]
    return each(guaranteed, items, workers, least=AS_SAMPLED_POOL)


AS_SAMPLED_POOL = 64  # fewer maps are laid in this process: starting workers costs a second or two


GALLERY_SCENES = 3  # junction frames and as many others in gallery.png


def gallery(scenes, reference, generated: dict[str, list], panel: int = 200) -> np.ndarray:
    """The first junction frames and the first others, a row each: SD | every method's map | ground truth."""
    junction = [k for k, s in enumerate(scenes) if s.kind.startswith("junction")][:GALLERY_SCENES]
    other = [k for k, s in enumerate(scenes) if not s.kind.startswith("junction")][:GALLERY_SCENES]
    tiles = []
    for k in junction + other:
        row = [(f"{k}: SD, {scenes[k].kind or 'frame'}", sd_panel(scenes[k].sd, panel))]
        row += [(PANELS[m], graph_panel(maps[k], panel)) for m, maps in generated.items()]
        row.append(("ground truth", graph_panel(reference[k], panel)))
        tiles += [np.concatenate([title_strip(title, panel), img], axis=0) for title, img in row]
    return grid(tiles, len(generated) + 2)


def frame_groups(scenes, reference, generated: dict[str, list]) -> dict:
    """Lanes per map (the ground truth's too) and lane precision, recall and F1 at 1 m in junction frames and in the
    others (the frame kinds of :mod:`cmtool.data.frames`), per method."""
    junction = np.array([s.kind.startswith("junction") for s in scenes], bool)
    out = {"scenes": {"junction": int(junction.sum()), "other": int((~junction).sum())},
           "lanes_per_map": {"truth": float(np.mean([len(g.lanes) for g in reference]))},
           **{f"lane_{key}": {} for key in FRAME_SCORES}}
    for m, maps in generated.items():
        scores = [lane_scores(g.lanes, r.lanes) for g, r in zip(maps, reference)]
        out["lanes_per_map"][m] = float(np.mean([len(g.lanes) for g in maps]))
        for key in FRAME_SCORES:
            values = np.array([s[key] for s in scores])
            out[f"lane_{key}"][m] = {k: float(values[sel].mean()) if sel.any() else None
                                     for k, sel in (("junction", junction), ("other", ~junction))}
    return out


FRAME_SCORES = ("f1", "precision", "recall")  # lane scores at 1 m, by frame kind


def _as_map(scene: Scene, method: str, k: int) -> LaneGraph:
    graph = scene.to_lanegraph()
    graph.meta = {"method": method, "scene": k}
    return graph


def _generate(gen: MapGenerator, scenes, settings: EvalSettings, cache: Path, progress: bool,
              info: D.DistInfo, starts: list[Scene] | None, layouts: list | None) -> dict[str, list] | None:
    """Both methods' maps for ``scenes``, continuing from (and extending) the cache: on the main process; the
    others generate their turns' batches and get None."""
    start, done = None, None
    if info.main:
        try:
            start, done = _open_cache(cache, settings)
        except CmtoolError as e:
            start = e  # every process stops with it
    start = D.broadcast(start, info)
    if isinstance(start, CmtoolError):
        raise start
    with Progress(len(scenes), "eval", "scenes", enabled=progress and info.main) as bar:
        bar.update(start)
        make = lambda b0: _batch_lines(gen, scenes[b0:b0 + settings.batch], b0, settings,  # noqa: E731
                                       None if starts is None else starts[b0:b0 + settings.batch],
                                       None if layouts is None else layouts[b0:b0 + settings.batch])
        for lines in D.dealt(list(range(start, len(scenes), settings.batch)), info, make):
            for m in METHODS:
                with (cache / f"{m}.jsonl").open("a", encoding="utf-8") as f:
                    f.write("".join(line + "\n" for line in lines[m]))
                # scored as cached (coordinates to the millimetre): a resumed run scores what a whole one does
                done[m] += [LaneGraph.from_json(json.loads(line)) for line in lines[m]]
            bar.update(len(lines[METHODS[0]]))
    return done


def _open_cache(cache: Path, settings: EvalSettings) -> tuple[int, dict[str, list]]:
    """The first scene still to generate and both methods' maps so far (whole batches of both: a crash may have
    left one method a batch ahead), after checking that the cache was made with these settings."""
    cache.mkdir(parents=True, exist_ok=True)
    meta = cache / "settings.json"
    mine = {k: v for k, v in asdict(settings).items()  # caches from before --init have no init entries
            if k not in ("n", "lane_counts") and not (k in ("init", "strength") and settings.init == NO_INIT)}
    if meta.is_file():
        theirs = read_json(meta)
        if theirs != mine:
            diff = sorted(k for k in set(mine) | set(theirs) if mine.get(k) != theirs.get(k))
            raise CmtoolError(f"{cache}: the cached maps were made with other settings ({', '.join(diff)}); "
                              "use another --out")
    else:
        write_json(meta, mine)
    done = {m: read_cache(cache / f"{m}.jsonl") for m in METHODS}
    start = min(len(v) for v in done.values()) // settings.batch * settings.batch
    done = {m: v[:start] for m, v in done.items()}
    for m in METHODS:
        write_jsonl(cache / f"{m}.jsonl", done[m])
    return start, done


def _batch_lines(gen: MapGenerator, batch, b0: int, settings: EvalSettings, starts: list[Scene] | None,
                 layouts: list | None) -> dict[str, list[str]]:
    """Both methods' maps of the scenes ``batch`` (starting at scene ``b0``; ControlMap from the layouts ``starts``
    when given, reading the layout rasters ``layouts`` when its branch reads one) as JSON lines; the batch's noise depends on ``b0`` alone, so the maps do not depend on which
    process makes them."""
    lines = {}
    for m in METHODS:  # the same noise for both methods
        init = None
        if m == "unguided":
            labels, sd = [len(gen.cities)] * len(batch), None
        else:
            labels, sd = [gen.known_label(s.city) for s in batch], np.stack([s.sd for s in batch])
            init = None if starts is None else gen.encode(starts)
        metas = [{"method": m, "scene": b0 + k, "seed": settings.seed} for k in range(len(batch))]
        lines[m] = [json.dumps(g.to_json(), separators=(",", ":")) for g in
                    gen.generate(sd, labels, settings, b0, init=init, strength=settings.strength, layouts=layouts,
                                 metas=metas)]
    return lines


def read_cache(path: Path) -> list[LaneGraph]:
    """The maps of a cache file, up to the first line a crash left incomplete."""
    graphs = []
    if path.is_file():
        for line in path.read_text("utf-8").splitlines():
            try:
                graphs.append(LaneGraph.from_json(json.loads(line)))
            except (json.JSONDecodeError, CmtoolError):
                break
    return graphs


def summary_markdown(report: dict) -> str:
    """``summary.md``: settings, then the metric table with one column per method."""
    s = report["settings"]
    methods = report["methods"]
    first = next(iter(methods.values()))
    backbone = first.get("backbone", {}).get("name", "none (feature metrics skipped)")
    path = Path(s["checkpoint"])
    if path.resolve() == (BUNDLED / "controlmap").resolve():
        title = "the weights shipped with cmtool"
    else:
        title = path.parent.parent.name if path.parent.name == "checkpoints" else ckpt.portable(path)
    head = [f"# cmtool eval: {title}", "",
            f"- checkpoint `{ckpt.portable(s['checkpoint'])}`",
            f"- data `{ckpt.portable(s['data'])}`, split {s['split']}, {s['n']} scenes",
            f"- ControlMap: guidance w = {s['cfg']}"
            + (f", started from the {s['init']} layout noised to strength {s['strength']:g}" if s.get("init", NO_INIT)
               != NO_INIT else "") + f"; both: {s['steps']} {s['sampler']} steps, seed {s['seed']}, "
            "the same initial noise per scene",
            f"- lanes: {_smoothing(s['smooth'])}",
            "- unguided: the frozen DiT without SD control or city label (the paper's SLEDGE rows)",
            "- rules: the rule-based lane layout of the same SD map (lane counts from the tags or the road class, "
            "one-way roads one way, junction connectors); netconvert: SUMO's, when it is installed",
            "- + guarantee: ControlMap's maps as `cmtool sample` writes them: composed from the SD map (every SD road "
            f"carries its lanes and nothing else does, junctions joined from them; lane counts of untagged roads from "
            f"the {'model' if s.get('lane_counts') == 'model' else 'road class'}, movements from the model)",
            f"- features: {backbone}; recall metrics in batches of 64, top 3, p = P(chance >= observed)",
            (f"- validity score of the ground truth itself: {report['ground_truth_validity']:.3f}; its lane pairs "
             f"routable with lane changes: {report.get('ground_truth_routable', float('nan')):.3f}"), "", ""]
    frames = report.get("frames")
    tail = []
    if frames:
        names = list(frames["lane_f1"])
        cell = lambda v: "–" if v is None else f"{v:.3f}"  # noqa: E731
        tail = ["", "", "### By frame", "",
                "| | " + " | ".join(SHORT[m] for m in names) + " | ground truth |", "|---|" + "---|" * (len(names) + 1),
                "| lanes per map | " + " | ".join(cell(frames["lanes_per_map"][m]) for m in names)
                + f" | {frames['lanes_per_map']['truth']:.3f} |"]
        tail += [f"| lane {label} @1 m, {k} frames ({frames['scenes'][k]}) ↑ | "
                 + " | ".join(cell(frames[f"lane_{key}"][m][k]) for m in names) + " | 1 |"
                 for key, label in zip(FRAME_SCORES, ("F1", "precision", "recall")) if f"lane_{key}" in frames
                 for k in ("junction", "other")]
    counts = report.get("lane_counts")
    if counts:
        cols = [(k, label) for k, label in (("model", "ControlMap (the model's own)"), ("guaranteed", "+ guarantee"),
                                            ("rules", "rules (tag, else road class)")) if k in counts]
        tail += ["", "", f"### Lanes per road direction ({counts['model']['road_directions']} SD road directions with "
                 "ground-truth lanes)", "", "| | " + " | ".join(label for _, label in cols) + " |",
                 "|---|" + "---|" * len(cols)]
        tail += [f"| {label} | " + " | ".join(f"{counts[c][k]:.3f}" for c, _ in cols) + " |" for k, label in
                 (("equal", "equal to the ground truth's ↑"), ("mean_difference", "mean difference (lanes)"),
                  ("mean_abs_difference", "mean absolute difference ↓"))]
    tail += decision_rows(report.get("decisions"), s["n"])
    return "\n".join(head) + summary_table({SHORT[k]: v for k, v in methods.items()}) + "\n".join(tail) + "\n"


def decision_rows(made: dict | None, frames: int) -> list[str]:
    """The "Decisions on the SD roads" table of ``summary.md`` (:func:`cmtool.metrics.decisions.decisions` of every
    method and of the ground truth over ``frames`` scenes), or nothing without it."""
    if not made:
        return []
    names = [m for m in made if m != "truth"]
    truth = made["truth"]
    out = ["", "", (f"### Decisions on the SD roads ({truth['truth_movements']} junction movements in the ground truth "
                    f"of the {frames} frames, pooled)"), "",
           "| | " + " | ".join(SHORT[m] for m in names) + " | ground truth |", "|---|" + "---|" * (len(names) + 1)]
    out += [f"| junction movements, {label} ↑ | " + " | ".join(f"{made[m][f'movement_{key}']:.3f}" for m in names)
            + " | 1 |" for key, label in (("precision", "precision"), ("recall", "recall"), ("f1", "F1"))]
    out.append("| junction movements per frame | " + " | ".join(f"{made[m]['movements'] / frames:.2f}" for m in names)
               + f" | {truth['movements'] / frames:.2f} |")
    out.append("| share of the lane length no SD road explains ↓ | "
               + " | ".join(f"{made[m]['unexplained_share']:.3f}" for m in names + ["truth"]) + " |")
    return out


def _smoothing(control_points: int) -> str:
    if control_points:
        return f"least-squares Bézier curves with {control_points} control points through the decoded points"
    return "the decoder's raw points (--smooth 0)"


RECORDED_SCORES = {"lane_f1": "lane F1 at 1 m", "chamfer_m": "lane Chamfer, m", "validity": "validity"}
PANELS = {"unguided": "unguided DiT", "rules": "rules", "netconvert": "netconvert", "controlmap": "ControlMap",
          "guaranteed": "ControlMap + guarantee", "truth": "ground truth"}
SHORT = {"unguided": "unguided", "rules": "rules", "netconvert": "netconvert", "controlmap": "ControlMap",
         "guaranteed": "+ guarantee"}
METHODS_KEY = "keys/methods"  # the key under the score plots (:func:`cmtool.viz.trajectory.log_key`)
SERIES_COLOURS = {"unguided": [230, 140, 40], "rules": [150, 150, 150], "netconvert": [150, 220, 120],
                  "controlmap": [60, 150, 255], "guaranteed": [200, 90, 230]}


def _write_recording(path: Path, scenes, reference, generated, results: dict, rrd_samples: int) -> None:
    """eval.rrd: on the ``sample`` timeline, scene k's SD, each method's map and the ground truth (the first
    ``rrd_samples`` scenes) beside its scores, and each score of every scene as a plot per score."""
    methods = list(generated)
    rec = open_recording("eval")
    rec.send_blueprint(_eval_blueprint())
    for key in RECORDED_SCORES:
        for m in methods:
            rec.log(f"metrics/{key}/{m}", rr.SeriesLines(colors=SERIES_COLOURS[m], names=PANELS[m]), static=True)
    log_key(rec, METHODS_KEY, [(PANELS[m], SERIES_COLOURS[m]) for m in methods])
    shown = min(rrd_samples, len(scenes))
    for k, (scene, truth) in enumerate(zip(scenes, reference)):
        rec.set_time("sample", sequence=k)
        values = {m: {key: results[m]["geometry"][key]["per_scene"][k] for key in RECORDED_SCORES} for m in methods}
        for m in methods:
            for key, value in values[m].items():
                if value is not None:
                    rec.log(f"metrics/{key}/{m}", rr.Scalars(value))
            if k < shown:
                g = generated[m][k]
                log_lanes(rec, f"scene/{m}/", g.lanes, g.green_lights, g.red_lights, g.successors)
        if k < shown:
            log_sd(rec, "scene/", scene.sd, scene.frame_m)
            log_lanes(rec, "scene/truth/", truth.lanes, truth.green_lights, truth.red_lights, truth.successors)
            table = [f"### scene {k}: {scene.city}" + (f", {scene.kind}" if scene.kind else ""), "",
                     "| | " + " | ".join(SHORT[m] for m in methods) + " |", "|---|" + "---|" * len(methods)]
            table += [f"| {title} | " + " | ".join("-" if values[m][key] is None else f"{values[m][key]:.3f}"
                                                    for m in methods) + " |" for key, title in RECORDED_SCORES.items()]
            rec.log("scene/scores", rr.TextDocument("\n".join(table), media_type="text/markdown"))
    close_recording(rec, path)


def _eval_blueprint() -> rrb.Blueprint:
    bounds = rrb.VisualBounds2D(x_range=[-32.0, 32.0], y_range=[-32.0, 32.0])
    maps = [rrb.Spatial2DView(origin="/scene", name="SD input", contents=["/scene/control/sd"], visual_bounds=bounds)]
    maps += [rrb.Spatial2DView(origin="/scene", name=title, contents=["/scene/control/sd", f"/scene/{m}/**"],
                               visual_bounds=bounds) for m, title in PANELS.items()]
    plots = [rrb.TimeSeriesView(origin=f"/metrics/{key}", name=title, plot_legend=rrb.PlotLegend(visible=False))
             for key, title in RECORDED_SCORES.items()]  # no legend over the lines: the key under them names them
    top = rrb.Grid(*maps, rrb.TextDocumentView(origin="/scene/scores", name="scores of this scene"),
                   grid_columns=(len(maps) + 2) // 2)  # two rows: SD and the baselines, then the model and the truth
    return rrb.Blueprint(rrb.Vertical(top, rrb.Horizontal(*plots), key_view(METHODS_KEY, "key"),
                                      row_shares=[3, 2, 0.3]),
                         rrb.BlueprintPanel(expanded=False), rrb.SelectionPanel(expanded=False),
                         rrb.TimePanel(expanded=True, timeline="sample"))
