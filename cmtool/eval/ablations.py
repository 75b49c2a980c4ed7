"""``cmtool ablate``: what the guidance weight and the city label do, on fixed SD maps and seeds.

- :func:`cfg_sweep`: for each guidance weight w, maps for the same scenes and seeds (the same
  initial noise at every w): SD adherence (SD road within 3 m of a lane, lane length within 5 m of
  SD), Ground-Truth Recall (batches of up to 64, top 3) and diversity (mean pairwise lane Chamfer
  distance between the seeds' maps of a scene).
- :func:`city_swap`: the same SD maps and noise under each city label; the driving side per label
  (share of lane length along two-way roads on the left / right), optionally with guidance on the
  city label (``city_cfg``).
- :func:`dit_compare`: several DiTs (or ControlMaps without their control) on the same labels and
  noise, judged as a set against the reference scenes: topology Fréchet distances, validity, lanes
  joined to nothing and crossings per map, and the driving side by oncoming lanes.

Each writes a markdown table and a JSON file, and a PNG (plot or picture grid) to its output
folder; the sweep also an ``.rrd`` whose ``cfg`` timeline counts w in thousandths (700 = 0.7).
"""

from __future__ import annotations

import itertools
import math

import cv2
import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from cmtool.core.jsonio import write_json, write_text_atomic
from cmtool.core.progress import Progress
from cmtool.data.layouts import scene_layout_rasters
from cmtool.diffusion.settings import DEFAULT_SAMPLER, SamplerSettings
from cmtool.maps.hdmap import drives_on
from cmtool.maps.lanegraph import LaneGraph
from cmtool.metrics.features import FeatureExtractor, lanes_image
from cmtool.metrics.geometric import chamfer, driving_side, oncoming_side, sd_adherence
from cmtool.metrics.retrieval import batch_recall
from cmtool.metrics.suite import markdown_table, weighted_mean
from cmtool.metrics.topology import topology_fd
from cmtool.metrics.validity import check
from cmtool.model.controlmap import NO_LAYOUT
from cmtool.sample.generator import MapGenerator
from cmtool.viz.draw import BACKGROUND, TEXT, graph_panel, grid, sd_panel, title_strip
from cmtool.viz.recording import close_recording, log_lanes, log_sd, open_recording
from cmtool.viz.show import write_png

PICTURE_SCENES = 4


def generate(gen: MapGenerator, sds: np.ndarray, labels: list[int], cfg: float, steps: int, seed: int,
             sampler: str = DEFAULT_SAMPLER, batch: int = 64, city_cfg: float = 1.0,
             layouts: list | None = None) -> list[LaneGraph]:
    """One map per SD raster (a DiT ignores them) at guidance weight ``cfg``; a batch's noise depends only on the
    seed and its first scene, so other weights, labels and checkpoints see the same noise. ``layouts``: the layout
    rasters of a branch that reads them (:attr:`MapGenerator.layout`)."""
    settings = SamplerSettings(cfg=cfg, steps=steps, sampler=sampler, seed=seed, batch=batch)
    meta = {"cfg": cfg, "seed": seed, "sampler": sampler, "smooth": gen.smooth}
    return gen.generate_all(sds if gen.has_control else None, labels, settings, [dict(meta) for _ in labels],
                            city_cfg=city_cfg, layouts=layouts)


def layouts_of(gen: MapGenerator, data_dir, split: str, scenes, side: str | None = None) -> list | None:
    """The layout rasters of ``scenes`` (the first of a dataset split) when ``gen``'s branch reads one, else None;
    ``side``: laid out for this driving side [default: each scene's city's]."""
    if gen.layout == NO_LAYOUT:
        return None
    return scene_layout_rasters(data_dir, split, scenes, gen.layout, side)


def cfg_sweep(gen: MapGenerator, scenes, weights: list[float], seeds: int, steps: int, extractor: FeatureExtractor | None,
              out, progress: bool = True, sampler: str = DEFAULT_SAMPLER, layouts: list | None = None) -> list[dict]:
    """The sweep's rows (one per w), written with its plot and recording to ``out``; ``layouts``: see
    :func:`generate`."""
    sds = np.stack([s.sd for s in scenes])
    truth = [s.to_lanegraph() for s in scenes]
    labels = [gen.known_label(s.city) for s in scenes]
    ref_feats = extractor(np.stack([lanes_image(t.lanes) for t in truth])) if extractor else None
    rows, maps_by_w = [], {}
    with Progress(len(weights) * seeds, "ablate cfg", "runs", enabled=progress) as bar:
        for w in weights:
            runs = []
            for seed in range(seeds):
                runs.append(generate(gen, sds, labels, w, steps, seed, sampler, layouts=layouts))
                bar.update()
            maps_by_w[w] = runs[0]
            adherence = [sd_adherence(m.lanes, sd) for m, sd in zip(runs[0], sds)]
            row = {"w": w, "sd_coverage": _mean([a["sd_coverage"] for a in adherence]),
                   "lane_on_sd": _mean([a["lane_on_sd"] for a in adherence])}
            if ref_feats is not None:
                gen_feats = extractor(np.stack([lanes_image(m.lanes) for m in runs[0]]))
                row["gt_recall"] = batch_recall(gen_feats, ref_feats, min(64, len(scenes)), 3)["recall"]
            row["diversity_m"] = _mean([chamfer(a.lanes, b.lanes) for i in range(len(scenes))
                                        for a, b in itertools.combinations([r[i] for r in runs], 2)])
            rows.append(row)
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / "ablate_cfg.json", {"scenes": len(scenes), "seeds": seeds, "steps": steps, "sampler": sampler,
                                          "smooth": gen.smooth, "rows": rows})
    write_text_atomic(out / "ablate_cfg.md", markdown_table(rows, ["w", "sd_coverage", "lane_on_sd", "gt_recall",
                                                                    "diversity_m"]))
    write_png(out / "ablate_cfg.png", _plot(rows))
    rec = open_recording("ablate")
    rec.send_blueprint(_cfg_blueprint(min(PICTURE_SCENES, len(scenes))))
    for k, scene in enumerate(scenes[:PICTURE_SCENES]):
        log_sd(rec, f"sample_{k}/", scene.sd, static=True)
        log_lanes(rec, f"sample_{k}/truth/", truth[k].lanes, static=True)
    for row in rows:
        rec.set_time("cfg", sequence=int(round(row["w"] * 1000)))  # thousandths of w
        for key, value in row.items():
            if key != "w" and value is not None and math.isfinite(value):
                rec.log(f"metrics/{key}", rr.Scalars(value))
        for k in range(min(PICTURE_SCENES, len(scenes))):
            g = maps_by_w[row["w"]][k]
            log_lanes(rec, f"sample_{k}/generated/", g.lanes, g.green_lights, g.red_lights, g.successors)
    close_recording(rec, out / "ablate_cfg.rrd")
    return rows


CFG_SCORES = {"sd_coverage": "SD road within 3 m of a lane", "lane_on_sd": "lane length within 5 m of SD",
              "gt_recall": "GT Recall", "diversity_m": "diversity: Chamfer between seeds, m"}


def _cfg_blueprint(scenes: int) -> rrb.Blueprint:
    """The guidance sweep on the ``cfg`` timeline (thousandths of w): each scene's map at that w above its
    ground truth, over the SD control, and each score against w."""
    bounds = rrb.VisualBounds2D(x_range=[-32.0, 32.0], y_range=[-32.0, 32.0])

    def view(k: int, part: str, title: str) -> rrb.Spatial2DView:
        return rrb.Spatial2DView(origin=f"/sample_{k}", name=f"scene {k}: {title}", visual_bounds=bounds,
                                 contents=[f"/sample_{k}/control/sd", f"/sample_{k}/{part}/**"])

    maps = rrb.Grid(*[view(k, "generated", "at this w") for k in range(scenes)],
                    *[view(k, "truth", "ground truth") for k in range(scenes)], grid_columns=max(scenes, 1))
    plots = rrb.Horizontal(*[rrb.TimeSeriesView(origin=f"/metrics/{key}", name=title,  # one series: the title names it
                                                plot_legend=rrb.PlotLegend(visible=False))
                             for key, title in CFG_SCORES.items()])
    return rrb.Blueprint(rrb.Vertical(maps, plots, row_shares=[3, 1]), rrb.BlueprintPanel(expanded=False),
                         rrb.SelectionPanel(expanded=False), rrb.TimePanel(expanded=True, timeline="cfg"))


def city_swap(gen: MapGenerator, scenes, labels: list[str], steps: int, cfg: float, seed: int, out,
              progress: bool = True, sampler: str = DEFAULT_SAMPLER, city_cfg: float = 1.0,
              layouts: dict[str, list] | None = None) -> list[dict]:
    """Driving side per city label on the same SD maps and noise (judged against the two-way SD roads
    and by the side of oncoming lanes), at city-label guidance ``city_cfg``, written to ``out``; ``layouts``: per
    label, the layout rasters laid out for its driving side (see :func:`generate`)."""
    sds = np.stack([s.sd for s in scenes])
    rows, maps = [], {}
    with Progress(len(labels), "ablate city-swap", "labels", enabled=progress) as bar:
        for name in labels:
            y = gen.label(name)
            maps[name] = generate(gen, sds, [y] * len(scenes), cfg, steps, seed, sampler, city_cfg=city_cfg,
                                  layouts=None if layouts is None else layouts[name])
            shares = [driving_side(m.lanes, sd, "left") for m, sd in zip(maps[name], sds)]
            oncoming = [oncoming_side(m.lanes, "left") for m in maps[name]]
            left = weighted_mean([s for s, n in shares], [n for s, n in shares])
            rows.append({"label": name, "drives_on": drives_on(name), "left_hand": left,
                         "right_hand": None if left is None else 1.0 - left,
                         "judged_points": int(sum(n for _, n in shares)),
                         "left_hand_oncoming": weighted_mean([s for s, n in oncoming], [n for s, n in oncoming]),
                         "oncoming_points": int(sum(n for _, n in oncoming))})
            bar.update()
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / "ablate_city_swap.json", {"scenes": len(scenes), "cfg": cfg, "city_cfg": city_cfg, "steps": steps,
                                                "sampler": sampler, "smooth": gen.smooth, "rows": rows})
    write_text_atomic(out / "ablate_city_swap.md", markdown_table(rows, [
        "label", "drives_on", "left_hand", "right_hand", "judged_points", "left_hand_oncoming", "oncoming_points"]))
    tiles = []
    for k, scene in enumerate(scenes[:PICTURE_SCENES]):
        tiles.append(_titled("SD", sd_panel(scene.sd)))
        tiles += [_titled(f"{name}", graph_panel(maps[name][k])) for name in labels]
    write_png(out / "ablate_city_swap.png", grid(tiles, columns=1 + len(labels)))
    return rows


def dit_compare(gens: dict[str, MapGenerator], scenes, steps: int, seed: int, out, progress: bool = True,
                sampler: str = DEFAULT_SAMPLER) -> list[dict]:
    """One row per checkpoint: maps for the scenes' city labels (the null label where a checkpoint does
    not know the city), without SD control, from the same noise, against the scenes' ground truth."""
    truth = [s.to_lanegraph() for s in scenes]
    sds = np.stack([s.sd for s in scenes])
    rows, maps = [{"name": "ground truth", **_set_scores(truth, truth)}], {}
    with Progress(len(gens), "ablate dit", "checkpoints", enabled=progress) as bar:
        for name, gen in gens.items():
            labels = [gen.known_label(s.city) for s in scenes]
            maps[name] = generate(gen, sds, labels, 0.0, steps, seed, sampler)
            rows.append({"name": name, **_set_scores(maps[name], truth)})
            bar.update()
    out.mkdir(parents=True, exist_ok=True)
    keys = ["name", "lanes", "fd_connectivity", "fd_density", "fd_reach", "fd_convenience", "validity", "dangling",
            "crossings", "oncoming_side"]
    write_json(out / "ablate_dit.json", {"scenes": len(scenes), "steps": steps, "sampler": sampler, "seed": seed,
                                          "checkpoints": {n: str(g.path) for n, g in gens.items()}, "rows": rows})
    write_text_atomic(out / "ablate_dit.md", markdown_table(rows, keys))
    tiles = []
    for k in range(min(PICTURE_SCENES, len(scenes))):
        tiles.append(_titled(f"truth {scenes[k].city}", graph_panel(truth[k])))
        tiles += [_titled(name, graph_panel(maps[name][k])) for name in gens]
    write_png(out / "ablate_dit.png", grid(tiles, columns=1 + len(gens)))
    return rows


def _set_scores(maps: list[LaneGraph], truth: list[LaneGraph]) -> dict:
    """A generated set against the reference set: lanes per map, topology FDs, validity, dangling lanes and
    crossings per map, and the share of judged points whose oncoming lanes run on the side of their city."""
    reports = [check(m, routes=False) for m in maps]
    sides = [oncoming_side(m.lanes, drives_on(t.city)) for m, t in zip(maps, truth)]
    return {"lanes": float(np.mean([len(m.lanes) for m in maps])),
            **{f"fd_{k}": v for k, v in topology_fd(maps, truth).items()},
            "validity": float(np.mean([r.score for r in reports])),
            "dangling": float(np.mean([r.counts().get("dangling", 0) for r in reports])),
            "crossings": float(np.mean([r.counts().get("crossing", 0) for r in reports])),
            "oncoming_side": weighted_mean([v for v, _ in sides], [n for _, n in sides])}


def _titled(title: str, panel: np.ndarray) -> np.ndarray:
    return np.concatenate([title_strip(title, panel.shape[1]), panel], axis=0)


def _mean(values) -> float | None:
    v = np.asarray([x for x in values if x is not None and math.isfinite(x)], float)
    return float(v.mean()) if len(v) else None


def _plot(rows: list[dict], width: int = 640, height: int = 360) -> np.ndarray:
    """Each metric against w as a line (scaled to [0, 1] by its largest value), with a legend."""
    img = np.full((height, width, 3), BACKGROUND, np.uint8)
    left, right, top, bottom = 50, 170, 20, 40
    ws = [r["w"] for r in rows]
    lo, hi = min(ws), max(ws) if max(ws) > min(ws) else min(ws) + 1.0
    x = lambda w: int(left + (w - lo) / (hi - lo) * (width - left - right))  # noqa: E731
    cv2.line(img, (left, height - bottom), (width - right, height - bottom), TEXT, 1)
    cv2.line(img, (left, top), (left, height - bottom), TEXT, 1)
    for w in ws:
        cv2.putText(img, f"{w:g}", (x(w) - 8, height - bottom + 18), cv2.FONT_HERSHEY_SIMPLEX, 0.4, TEXT, 1, cv2.LINE_AA)
    cv2.putText(img, "w", (width - right + 8, height - bottom + 4), cv2.FONT_HERSHEY_SIMPLEX, 0.5, TEXT, 1, cv2.LINE_AA)
    colours = {"sd_coverage": (90, 200, 250), "lane_on_sd": (60, 140, 255), "gt_recall": (250, 180, 60),
               "diversity_m": (200, 90, 220)}
    for i, (key, colour) in enumerate(colours.items()):
        vals = [r.get(key) for r in rows]
        if any(v is None for v in vals):
            continue
        peak = max(max(vals), 1e-9)
        pts = [(x(w), int(height - bottom - v / peak * (height - top - bottom))) for w, v in zip(ws, vals)]
        for a, b in zip(pts, pts[1:]):
            cv2.line(img, a, b, colour, 2, cv2.LINE_AA)
        for p in pts:
            cv2.circle(img, p, 3, colour, -1, cv2.LINE_AA)
        cv2.putText(img, f"{key} (max {peak:.2f})", (width - right + 8, top + 16 + 18 * i), cv2.FONT_HERSHEY_SIMPLEX,
                    0.38, colour, 1, cv2.LINE_AA)
    return img
