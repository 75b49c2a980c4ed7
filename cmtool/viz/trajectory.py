"""Rerun recording of a sampling run: every denoising step of every map.

:class:`TrajectoryLogger` is the sampler's per-step callback. It keeps each step's tensors and
sends them in columns (one ``send_columns`` per entity for many steps), which costs a fraction
of logging row by row; pending steps go out every ``flush_s`` seconds when a live viewer follows
the run, else all at the end of the batch. Per map, under ``<prefix>`` (``sample_{k}/`` when a recording holds
several maps), on the ``diffusion_step`` timeline (0: the start, pure noise or the noised ``--init`` layout; k: what
the k-th model pass predicted and the latent it left; the last: the clean latent the map is decoded from) and the
``timestep`` timeline (each model pass's t: the latent it took and what it predicted):

- ``diffusion/latent``: the latent x_t (Tensor channel x row x col, shown as one channel's 8 x 8
  grid with a channel slider; each step's value range spans its own values);
- ``diffusion/x0/lanes``, ``diffusion/x0/lights/{green,red}``: the predicted clean latent decoded by
  the RVAE (all steps' latents decoded in one batch per flush);
- ``diffusion/eps/{cond,uncond,guided}``: L2 norms of the noise predictions, and
  ``diffusion/eps/delta``, the norm of the guidance term ``w (eps_cond - eps_uncond)`` (at w = 1 the guided
  prediction is the conditioned one and no unconditioned pass runs: no ``uncond`` and ``delta``);
- ``control/residual/block_{m}``: per-token L2 norm of the residual added to DiT block m (an 8 x 8
  ``DepthImage``, rows = latent rows, each step's colour range spanning its own values, so the heatmap shows
  where the control acts at every step; placed in rows of three, framed and named by ``control/residual/frames``),
  and ``control/residual/block_{m}/norm``, its total L2 norm.

:func:`log_scores` adds each map's scores (``scores/...``) when the maps are made."""

from __future__ import annotations

import math
import time
from typing import Callable

import numpy as np
import pyarrow as pa
import rerun as rr
import rerun.blueprint as rrb
from rerun._baseclasses import ComponentColumn, ComponentColumnList
from rerun.encodings import TensorDimensionIndexSelection, TensorDimensionSelection

from cmtool.diffusion.samplers import StepInfo
from cmtool.viz.draw import GREEN, RED, heading_colours, light_bars
from cmtool.viz.recording import LANE_RADIUS_M, LIGHT_DRAW_ORDER, LIGHT_RADIUS_M, in_memory, lane_colours, log_ego_frame

LATENT_DIMS = ("channel", "row", "col")
MAX_TABS = 16  # maps that get their own tab in the default layout
# the noise-prediction norms: each series' legend name and colour (the conditioned and unconditioned far apart)
EPS_SERIES = {"cond": ("cond", [70, 140, 255]), "uncond": ("uncond", [255, 150, 30]),
              "guided": ("guided", [235, 235, 235]), "delta": ("guided - uncond", [220, 60, 200])}
SCORE_COLOURS = ([70, 140, 255], [255, 150, 30], [90, 200, 90])
# the keys of the noise norms' and the residual norms' plots (under a map's prefix) and of the scores' bars
NOISE_KEY, RESIDUAL_KEY, SCORES_KEY = "keys/noise_norms", "keys/residual_norms", "keys/scores"
KEY_GAP, KEY_DOT = 3, rr.components.Radius.ui_points(4.0)  # a key's gap between names (characters), its dots'
# radius (on screen, whatever the row's width)


class _Column:
    """A prebuilt arrow array in the shape ``ComponentColumn`` expects of a component batch."""

    def __init__(self, array: pa.Array):
        self.array = array

    def as_arrow_array(self) -> pa.Array:
        return self.array


def tensor_column(arrays: np.ndarray, dim_names) -> ComponentColumnList:
    """A ``Tensor`` column of ``len(arrays)`` float32 tensors, for ``send_columns``.

    rerun-sdk 0.41's ``rr.Tensor.columns`` takes one tensor only; this builds the same arrow
    layout (shape, names, F32 buffer) for many rows in one go.
    """
    arrays = np.ascontiguousarray(arrays, dtype=np.float32)
    rows, shape = len(arrays), arrays.shape[1:]
    dtype = rr.components.TensorDataBatch._ARROW_DATATYPE

    def repeated(values, typ) -> pa.Array:
        offsets = pa.array(np.arange(rows + 1, dtype=np.int32) * len(values))
        return pa.ListArray.from_arrays(offsets, pa.array(list(values) * rows, typ))

    union = dtype.field("buffer").type
    f32 = [f.name for f in union].index("F32")
    size = int(np.prod(shape))
    children = [pa.nulls(0, type=f.type) for f in union]
    children[f32] = pa.ListArray.from_arrays(pa.array(np.arange(rows + 1, dtype=np.int32) * size),
                                             pa.array(arrays.reshape(-1))).cast(union[f32].type)
    buffer = pa.Array.from_buffers(type=union, length=rows, children=children, buffers=[
        None, pa.array(np.full(rows, f32, np.int8)).buffers()[1], pa.array(np.arange(rows, dtype=np.int32)).buffers()[1]])
    batch = pa.StructArray.from_arrays([repeated([int(d) for d in shape], pa.uint64()).cast(dtype.field("shape").type),
                                        repeated(list(dim_names), pa.string()).cast(dtype.field("names").type),
                                        buffer], fields=list(dtype))
    descriptor = next(iter(rr.Tensor.columns(data=arrays[0]))).descriptor
    return ComponentColumnList([ComponentColumn(descriptor, _Column(batch))])


def tensor_columns(arrays: np.ndarray, dim_names) -> ComponentColumnList:
    """:func:`tensor_column` with each tensor's own [min, max] as its value range (a colour map over the
    values of that step, not over a fixed range that flattens steps of small values)."""
    arrays = np.asarray(arrays, np.float32)
    return ComponentColumnList([*tensor_column(arrays, dim_names), *rr.Tensor.columns(value_range=_ranges(arrays))])


def heatmap_columns(maps: np.ndarray) -> ComponentColumnList:
    """``DepthImage`` columns of ``(N, H, W)`` heatmaps, each coloured over its own [min, max] (drawn in a 2D view,
    which puts no dimension labels over them as a tensor view does)."""
    maps = np.ascontiguousarray(maps, np.float32)
    n, h, w = maps.shape
    image_format = rr.components.ImageFormat(width=w, height=h, channel_datatype="F32")
    return rr.DepthImage.columns(buffer=maps.reshape(n, -1).view(np.uint8), format=[image_format] * n,
                                 depth_range=_ranges(maps))


def block_colours(blocks: int) -> np.ndarray:
    """(blocks, 3) RGB: one colour per injected block (its heatmap's frame, its norm's series), hues evenly apart."""
    return heading_colours(2 * np.pi * (np.arange(blocks) + 0.5) / max(blocks, 1))


def heatmap_cells(blocks: int) -> np.ndarray:
    """(blocks, 2): the top-left corner of each block's heatmap, scaled to a unit square, in rows of three with room
    for a label under each."""
    return np.array([[(m % 3) * 1.1, (m // 3) * 1.3] for m in range(blocks)], np.float64).reshape(-1, 2)


def _ranges(arrays: np.ndarray) -> np.ndarray:
    """(N, 2): each array's [min, max], widened where flat."""
    flat = arrays.reshape(len(arrays), -1)
    lo, hi = flat.min(axis=1), flat.max(axis=1)
    return np.stack([lo, np.maximum(hi, lo + 1e-6)], axis=1).astype(np.float64)


def strips_column(strips: np.ndarray) -> ComponentColumn:
    """The ``LineStrips2D`` strips of equal-length polylines ``(N, P, 2)`` as one column, built in
    one go (``rr.LineStrips2D.columns`` converts strip by strip)."""
    n, p = strips.shape[:2]
    dtype = rr.components.LineStrip2DBatch._ARROW_DATATYPE
    points = pa.FixedSizeListArray.from_arrays(pa.array(np.ascontiguousarray(strips, np.float32).reshape(-1)), 2)
    array = pa.ListArray.from_arrays(pa.array(np.arange(n + 1, dtype=np.int32) * p), points).cast(dtype)
    descriptor = next(iter(rr.LineStrips2D.columns(strips=np.zeros((1, 2, 2), np.float32)))).descriptor
    return ComponentColumn(descriptor, _Column(array))


def _norms(x) -> np.ndarray:
    """Per-item L2 norm of a (B, ...) tensor."""
    return x.detach().float().flatten(1).norm(dim=1).cpu().numpy()


class TrajectoryLogger:
    """Sampler callback that records every step of a batch of maps, one ``prefix`` per map: ``diffusion_step`` 0
    holds the latent the sampler starts from, step k what its k-th model pass predicted and the latent that pass
    left (see the module doc). ``flush_s``: seconds between flushes [default: 0.5 for a live viewer; none before
    :meth:`finish` for a recording kept in memory, so that all steps' latents are decoded in one batch]; ``ego``:
    make each map's ``diffusion/x0`` an ego-frame space shown forward-up (else the caller places each prefix, as
    ``area.rrd`` places its tiles)."""

    def __init__(self, rec: rr.RecordingStream, prefixes: list[str], decode: Callable, cfg: float,
                 flush_s: float | None = None, ego: bool = True):
        if flush_s is None:
            flush_s = math.inf if in_memory(rec) else 0.5
        self.rec, self.prefixes, self.decode, self.cfg, self.flush_s = rec, prefixes, decode, cfg, flush_s
        self.pending: list[dict] = []
        self.last = None  # the last step seen
        self.placed = False  # the heatmaps placed (and, with ``ego``, the noise norms' key logged)
        self.ego = ego
        self.last_flush = time.perf_counter()
        for prefix in prefixes if ego else ():
            log_ego_frame(rec, f"{prefix}diffusion/x0")

    def __call__(self, info: StepInfo) -> None:
        step = {"step": info.step, "t": info.t, "latent": info.x_t.detach().float().cpu(), "x0": info.x0.detach(),
                "guided": _norms(info.eps)}
        if info.eps_uncond is not None:
            step["uncond"] = _norms(info.eps_uncond)
        if info.eps_cond is not None:
            step["cond"] = _norms(info.eps_cond)
        if info.eps_cond is not None and info.eps_uncond is not None:
            step["delta"] = _norms(info.eps - info.eps_uncond)
        if info.residuals is not None:
            side = int(round(info.residuals[0].shape[1] ** 0.5))
            per_token = [r.detach().float().norm(dim=-1) for r in info.residuals]  # M x (B, T)
            step["heatmaps"] = [h.reshape(len(h), side, side).cpu().numpy() for h in per_token]
            step["residual_norms"] = [h.norm(dim=1).cpu().numpy() for h in per_token]
        self.pending.append(step)
        self.last = step
        if time.perf_counter() - self.last_flush >= self.flush_s:
            self.flush()

    def flush(self, last: list[dict] | None = None) -> None:
        """Send the pending steps of every map as columns: each step's latent at its own number, what its model
        pass predicted at the next; ``last``: as :meth:`finish`'s."""
        if not self.pending:
            return
        steps, self.pending = self.pending, []
        if not self.placed:
            self._place_heatmaps(steps[0])
            if self.ego:  # the keys under the plots: the series this run has (no uncond at w = 1), the blocks
                blocks = [(f"block {m}" if m == 0 else str(m), c.tolist())
                          for m, c in enumerate(block_colours(len(steps[0].get("heatmaps", []))))]
                for prefix in self.prefixes:
                    log_key(self.rec, f"{prefix}{NOISE_KEY}", [EPS_SERIES[k] for k in EPS_SERIES if k in steps[0]])
                    log_key(self.rec, f"{prefix}{RESIDUAL_KEY}", blocks)
        n, b = len(steps), len(self.prefixes)
        import torch

        estimates = [s["x0"] for s in (steps if last is None else steps[:-1])]
        decoded = self.decode(torch.cat(estimates)) if estimates else []  # step-major: row i * b + k
        decoded += last or []
        timesteps = rr.TimeColumn("timestep", sequence=[s["t"] for s in steps])
        inputs = [rr.TimeColumn("diffusion_step", sequence=[s["step"] for s in steps]), timesteps]
        times = [rr.TimeColumn("diffusion_step", sequence=[s["step"] + 1 for s in steps]), timesteps]
        latents = np.stack([s["latent"].numpy() for s in steps], axis=1)  # (B, n, C, H, W)
        for k, prefix in enumerate(self.prefixes):
            send = self.rec.send_columns
            send(f"{prefix}diffusion/latent", indexes=inputs, columns=tensor_columns(latents[k], LATENT_DIMS))
            mine = [decoded[i * b + k] for i in range(n)]
            self._send_lines(f"{prefix}diffusion/x0/lanes", times, [d["lines"] for d in mine], None, LANE_RADIUS_M)
            for state, colour in (("green", GREEN), ("red", RED)):  # each light a bar across its lane, over them
                self._send_lines(f"{prefix}diffusion/x0/lights/{state}", times,
                                 [light_bars(d[state]) for d in mine], colour, LIGHT_RADIUS_M, LIGHT_DRAW_ORDER)
            for key in EPS_SERIES:
                if key in steps[0]:
                    send(f"{prefix}diffusion/eps/{key}", indexes=times,
                         columns=rr.Scalars.columns(scalars=[float(s[key][k]) for s in steps]))
            for m in range(len(steps[0].get("heatmaps", []))):
                path = f"{prefix}control/residual/block_{m}"
                send(path, indexes=times, columns=heatmap_columns(np.stack([s["heatmaps"][m][k] for s in steps])))
                send(f"{path}/norm", indexes=times,
                     columns=rr.Scalars.columns(scalars=[float(s["residual_norms"][m][k]) for s in steps]))
        self.last_flush = time.perf_counter()

    def finish(self, last: list[dict] | None = None) -> None:
        """Flush, then record the clean latent the sampler ended on after the last step (its last model pass's
        clean estimate: every sampler's last update lands on it), without a timestep; ``last``: each map as that
        latent was decoded (``{"lines", "green", "red"}``), when the caller has it, so that it is not decoded again
        as the last step's estimate."""
        self.flush(last)
        if self.last is None:
            return
        final = self.last["x0"].float().cpu().numpy()[:, None]  # (B, 1, C, H, W)
        times = [rr.TimeColumn("diffusion_step", sequence=[self.last["step"] + 1])]
        for k, prefix in enumerate(self.prefixes):
            self.rec.send_columns(f"{prefix}diffusion/latent", indexes=times,
                                  columns=tensor_columns(final[k], LATENT_DIMS))

    def _place_heatmaps(self, step: dict) -> None:
        """Place each map's heatmaps (:func:`heatmap_cells`), each framed and named in the colour of its norm's
        series (the frames on an entity of their own: Rerun places a label by the box's own coordinates, not by its
        entity's transform)."""
        self.placed = True
        heatmaps = step.get("heatmaps", [])
        at = heatmap_cells(len(heatmaps))
        for prefix in self.prefixes if heatmaps else ():
            self.rec.log(f"{prefix}control/residual/frames", rr.Boxes2D(
                mins=at, sizes=np.ones_like(at), labels=[f"block {m}" for m in range(len(heatmaps))],
                colors=block_colours(len(heatmaps)), radii=0.006), static=True)
            for m, (x, y) in enumerate(at):
                self.rec.log(f"{prefix}control/residual/block_{m}", rr.Transform3D(
                    translation=[x, y, 0.0], scale=1.0 / heatmaps[m].shape[-1]), static=True)

    def _send_lines(self, path: str, times, per_step: list[np.ndarray], colour, radius: float,
                    draw_order: float | None = None) -> None:
        counts = [len(lines) for lines in per_step]
        nonempty = [np.asarray(lines, np.float32) for lines in per_step if len(lines)]
        strips = np.concatenate(nonempty) if nonempty else np.zeros((0, 2, 2), np.float32)
        colours = lane_colours(strips) if colour is None else np.tile(np.array(colour, np.uint8), (len(strips), 1))
        columns = rr.LineStrips2D.columns(colors=colours, radii=np.full(len(strips), radius, np.float32))
        columns = ComponentColumnList([*columns, strips_column(strips)]).partition(counts)
        if draw_order is not None:  # one a row
            columns = ComponentColumnList([*columns, *rr.LineStrips2D.columns(draw_order=[draw_order] * len(counts))])
        self.rec.send_columns(path, indexes=times, columns=columns)


def log_scores(rec: rr.RecordingStream, scores: dict[str, list]) -> None:
    """Each score of every map as a bar at the map's number (``scores``: name -> a value or None per map, in the
    order of the maps' prefixes), the scores of a map side by side, under ``scores/NAME`` (spaces as ``_``); a score
    no map has is left out; their key (:func:`log_key`) at ``keys/scores``."""
    width, key = 0.8 / len(scores), []
    for i, (name, values) in enumerate(scores.items()):
        bars = np.array([np.nan if v is None else v for v in values], np.float64)
        if np.isnan(bars).all():
            continue
        at = np.arange(len(bars)) + (i - (len(scores) - 1) / 2) * width
        chart = rr.BarChart(bars, abscissa=at, widths=np.full(len(bars), 0.9 * width),
                            color=SCORE_COLOURS[i % len(SCORE_COLOURS)])
        rec.log(f"scores/{name.replace(' ', '_')}", chart, static=True)
        key.append((name, SCORE_COLOURS[i % len(SCORE_COLOURS)]))
    log_key(rec, SCORES_KEY, key)


def log_key(rec: rr.RecordingStream, path: str, entries: list[tuple[str, list[int]]]) -> None:
    """A plot's key, drawn by :func:`key_view` under the plot instead of Rerun's legend inside it (which covers the
    lines or bars it names): each entry's name in its colour, under a dot of that colour, in one row."""
    if not entries:
        return
    rec.log(path, rr.Points2D(key_positions([n for n, _ in entries]), labels=[n for n, _ in entries],
                              colors=[c for _, c in entries], radii=KEY_DOT, show_labels=True), static=True)


def key_positions(names: list[str]) -> np.ndarray:
    """(N, 2): where :func:`log_key` puts each name's dot across the row from 0 to 1, each name in a cell as wide
    as its characters and a gap."""
    widths = np.array([len(n) + KEY_GAP for n in names], np.float64)
    return np.stack([(np.cumsum(widths) - widths / 2) / widths.sum(), np.zeros(len(names))], axis=1)


def key_view(path: str, name: str) -> rrb.Spatial2DView:
    """The view of a key of :func:`log_key`: its row across the view's width, no title bar."""
    return rrb.Spatial2DView(origin=path, name=name, titlebar=False,
                             visual_bounds=rrb.VisualBounds2D(x_range=[0.0, 1.0], y_range=[-0.002, 0.006]))


def plot(name: str, origin: str, series: dict[str, tuple[str, list[int]]]) -> rrb.TimeSeriesView:
    """A time series view of ``series`` (entity path -> (name, colour)) that reads at two steps as well as at fifty:
    each value a dot on its series' line, the axis from step 0 to one step past the time cursor (no dot on the
    view's edge), and no legend over the lines (:func:`key_view`, or the title, names the series)."""
    overrides = {path: [rr.SeriesLines(colors=colour, names=label, widths=1.5).visualizer(),
                        rr.SeriesPoints(colors=colour, names=label, markers="circle", marker_sizes=3.5).visualizer()]
                 for path, (label, colour) in series.items()}
    steps = rr.TimeRange(start=rr.TimeRangeBoundary.absolute(seq=0), end=rr.TimeRangeBoundary.cursor_relative(seq=1))
    return rrb.TimeSeriesView(name=name, origin=origin, overrides=overrides, axis_x=rrb.TimeAxis(view_range=steps),
                              plot_legend=rrb.PlotLegend(visible=False))


def sample_view(prefix: str, name: str, blocks: int, truth: bool) -> rrb.Container:
    """One map's layout: SD | x0 lanes over the steps | final lanes (| ground truth) above
    latent | residual heatmaps | noise-prediction norms | residual norms."""
    root = "/" + prefix
    bounds = rrb.VisualBounds2D(x_range=[-32.0, 32.0], y_range=[-32.0, 32.0])

    def spatial(title: str, *paths: str) -> rrb.Spatial2DView:
        return rrb.Spatial2DView(origin=root or "/", name=title, visual_bounds=bounds,
                                 contents=[f"{root}{p}" for p in paths])

    top = [spatial("SD control", "control/sd"),
           spatial("x0 lanes over diffusion steps", "control/sd", "diffusion/x0/**"),
           spatial("generated (grey: as decoded, white: left out)", "control/sd", "decoded/**", "hd/**")]
    if truth:
        top.append(spatial("ground truth", "control/sd", "truth/**"))
    grid = rrb.TensorSliceSelection(width=TensorDimensionSelection(2), height=TensorDimensionSelection(1),
                                    indices=[TensorDimensionIndexSelection(0, 0)], slider=[0])  # (channel, row, col)
    # the whole 8 x 8 grid, as large as the view lets it be ("Fill" cut its columns off at the view's edge)
    bottom = [rrb.TensorView(origin=f"{root}diffusion/latent", name="latent x_t", slice_selection=grid,
                             view_fit="FillKeepAspectRatio")]
    eps = plot("noise prediction norms", f"{root}diffusion/eps",
               {f"{root}diffusion/eps/{key}": series for key, series in EPS_SERIES.items()})
    plots = [rrb.Vertical(eps, key_view(f"{root}{NOISE_KEY}", "noise prediction norms: key"), row_shares=[6, 1])]
    if blocks:
        far = heatmap_cells(blocks).max(axis=0)  # the last column's and row's corner; a label under each heatmap
        bounds = rrb.VisualBounds2D(x_range=[-0.05, far[0] + 1.05], y_range=[-0.05, far[1] + 1.3])
        heatmap = rr.DepthImage.from_fields(colormap="viridis", magnification_filter="Nearest")
        bottom.append(rrb.Spatial2DView(origin=f"{root}control/residual", name="control residual of each block",
                                        visual_bounds=bounds, defaults=[heatmap]))
        # each block's series in the colour of its heatmap's frame and name
        residual = plot("control residual norms", f"{root}control/residual",
                        {f"{root}control/residual/block_{m}/norm": (f"block {m}", c.tolist())
                         for m, c in enumerate(block_colours(blocks))})
        plots.append(rrb.Vertical(residual, key_view(f"{root}{RESIDUAL_KEY}", "control residual norms: key"),
                                  row_shares=[6, 1]))
    shares = [2.6, 4.5][:len(bottom)] + [3] * len(plots)
    return rrb.Vertical(rrb.Horizontal(*top), rrb.Horizontal(*bottom, *plots, column_shares=shares),
                        row_shares=[1, 1], name=name)


def sampling_blueprint(prefixes: list[str], names: list[str], blocks: int, truth: bool) -> rrb.Blueprint:
    """Tabs with one :func:`sample_view` per map (the first ``MAX_TABS``; the others are in the
    entity tree), beside the run's info document above the scores of every map."""
    views = [sample_view(p, n, blocks, truth) for p, n in zip(prefixes[:MAX_TABS], names)]
    body = views[0] if len(views) == 1 else rrb.Tabs(*views)
    side = rrb.Vertical(rrb.TextDocumentView(origin="/info", name="info"),
                        rrb.BarChartView(origin="/scores", name="scores of each map (x: map number)",
                                         plot_legend=rrb.PlotLegend(visible=False)),
                        key_view(f"/{SCORES_KEY}", "scores: key"), row_shares=[4, 2, 0.35])
    return rrb.Blueprint(rrb.Horizontal(body, side, column_shares=[3, 1]),
                         rrb.BlueprintPanel(expanded=False), rrb.SelectionPanel(expanded=False),
                         rrb.TimePanel(expanded=True, timeline="diffusion_step"))
