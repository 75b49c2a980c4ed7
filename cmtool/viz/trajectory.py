"""Rerun recording of a sampling run: every denoising step of every map.

:class:`TrajectoryLogger` is the sampler's per-step callback. It keeps each step's tensors and
sends them in columns (one ``send_columns`` per entity for many steps), which costs a fraction
of logging row by row; pending steps go out every ``flush_s`` seconds when a live viewer follows
the run, else all at the end of the batch. Per map, under ``<prefix>`` (``sample_{k}/`` when a recording holds several maps) and on
the ``diffusion_step`` (0 = pure noise) and ``timestep`` timelines:

- ``diffusion/latent``: the latent x_t (Tensor channel x row x col, shown as one channel's 8 x 8
  grid with a channel slider; each step's value range spans its own values);
- ``diffusion/x0/lanes``, ``diffusion/x0/lights/{green,red}``: the predicted clean latent decoded by
  the RVAE (all steps' latents decoded in one batch per flush);
- ``diffusion/eps/{cond,uncond,guided}``: L2 norms of the noise predictions, and
  ``diffusion/eps/delta``, the norm of the guidance term ``w (eps_cond - eps_uncond)`` (at w = 1 the guided
  prediction is the conditioned one and no unconditioned pass runs: no ``uncond`` and ``delta``);
- ``control/residual/block_{m}``: per-token L2 norm of the residual added to DiT block m (8 x 8
  Tensor, rows = latent rows, each step's value range spanning its own values, so the heatmap shows
  where the control acts at every step), and ``control/residual/block_{m}/norm``, its total L2 norm.
"""

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
from cmtool.viz.draw import GREEN, RED
from cmtool.viz.recording import LANE_RADIUS_M, LIGHT_RADIUS_M, in_memory, lane_colours, log_ego_frame

LATENT_DIMS = ("channel", "row", "col")
MAX_TABS = 16  # maps that get their own tab in the default layout
HEATMAP_DIMS = ("row", "col")


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
    flat = arrays.reshape(len(arrays), -1)
    lo, hi = flat.min(axis=1), flat.max(axis=1)
    ranges = np.stack([lo, np.maximum(hi, lo + 1e-6)], axis=1).astype(np.float64)
    return ComponentColumnList([*tensor_column(arrays, dim_names), *rr.Tensor.columns(value_range=ranges)])


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
    """Sampler callback that records every step of a batch of maps, one ``prefix`` per map. ``flush_s``: seconds
    between flushes [default: 0.5 for a live viewer; none before the last step for a recording kept in memory,
    so that all steps' latents are decoded in one batch]; ``ego``: make each map's ``diffusion/x0`` an ego-frame
    space shown forward-up (else the caller places each prefix, as ``area.rrd`` places its tiles)."""

    def __init__(self, rec: rr.RecordingStream, prefixes: list[str], decode: Callable, cfg: float,
                 flush_s: float | None = None, ego: bool = True):
        if flush_s is None:
            flush_s = math.inf if in_memory(rec) else 0.5
        self.rec, self.prefixes, self.decode, self.cfg, self.flush_s = rec, prefixes, decode, cfg, flush_s
        self.pending: list[dict] = []
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
        if time.perf_counter() - self.last_flush >= self.flush_s:
            self.flush()

    def flush(self) -> None:
        """Send the pending steps of every map as columns."""
        if not self.pending:
            return
        steps, self.pending = self.pending, []
        n, b = len(steps), len(self.prefixes)
        import torch

        decoded = self.decode(torch.cat([s["x0"] for s in steps]))  # step-major: row i * b + k
        times = [rr.TimeColumn("diffusion_step", sequence=[s["step"] for s in steps]),
                 rr.TimeColumn("timestep", sequence=[s["t"] for s in steps])]
        latents = np.stack([s["latent"].numpy() for s in steps], axis=1)  # (B, n, C, H, W)
        for k, prefix in enumerate(self.prefixes):
            send = self.rec.send_columns
            send(f"{prefix}diffusion/latent", indexes=times, columns=tensor_columns(latents[k], LATENT_DIMS))
            mine = [decoded[i * b + k] for i in range(n)]
            self._send_lines(f"{prefix}diffusion/x0/lanes", times, [d["lines"] for d in mine], None, LANE_RADIUS_M)
            for state, colour in (("green", GREEN), ("red", RED)):
                self._send_lines(f"{prefix}diffusion/x0/lights/{state}", times, [d[state] for d in mine], colour,
                                 LIGHT_RADIUS_M)
            for key in ("cond", "uncond", "guided", "delta"):
                if key in steps[0]:
                    send(f"{prefix}diffusion/eps/{key}", indexes=times,
                         columns=rr.Scalars.columns(scalars=[float(s[key][k]) for s in steps]))
            for m in range(len(steps[0].get("heatmaps", []))):
                path = f"{prefix}control/residual/block_{m}"
                send(path, indexes=times, columns=tensor_columns(np.stack([s["heatmaps"][m][k] for s in steps]),
                                                                 HEATMAP_DIMS))
                send(f"{path}/norm", indexes=times,
                     columns=rr.Scalars.columns(scalars=[float(s["residual_norms"][m][k]) for s in steps]))
        self.last_flush = time.perf_counter()

    def _send_lines(self, path: str, times, per_step: list[np.ndarray], colour, radius: float) -> None:
        counts = [len(lines) for lines in per_step]
        nonempty = [np.asarray(lines, np.float32) for lines in per_step if len(lines)]
        strips = np.concatenate(nonempty) if nonempty else np.zeros((0, 2, 2), np.float32)
        colours = lane_colours(strips) if colour is None else np.tile(np.array(colour, np.uint8), (len(strips), 1))
        columns = rr.LineStrips2D.columns(colors=colours, radii=np.full(len(strips), radius, np.float32))
        columns = ComponentColumnList([*columns, strips_column(strips)])
        self.rec.send_columns(path, indexes=times, columns=columns.partition(counts))


def sample_view(prefix: str, name: str, blocks: int, truth: bool) -> rrb.Container:
    """One map's layout: SD | x0 lanes over the steps | final lanes (| ground truth) above
    latent | residual heatmaps | scalars."""
    root = "/" + prefix
    bounds = rrb.VisualBounds2D(x_range=[-32.0, 32.0], y_range=[-32.0, 32.0])

    def spatial(title: str, *paths: str) -> rrb.Spatial2DView:
        return rrb.Spatial2DView(origin=root or "/", name=title, visual_bounds=bounds,
                                 contents=[f"{root}{p}" for p in paths])

    top = [spatial("SD control", "control/sd"),
           spatial("x0 lanes over diffusion steps", "control/sd", "diffusion/x0/**"),
           spatial("generated", "control/sd", "hd/**")]
    if truth:
        top.append(spatial("ground truth", "control/sd", "truth/**"))
    grid = rrb.TensorSliceSelection(width=TensorDimensionSelection(2), height=TensorDimensionSelection(1),
                                    indices=[TensorDimensionIndexSelection(0, 0)], slider=[0])  # (channel, row, col)
    bottom = [rrb.TensorView(origin=f"{root}diffusion/latent", name="latent x_t, one channel", slice_selection=grid,
                             view_fit="Fill")]
    if blocks:
        bottom.append(rrb.Grid(*[rrb.TensorView(origin=f"{root}control/residual/block_{m}", contents="$origin",
                                                name=f"block {m}", view_fit="Fill") for m in range(blocks)],
                               grid_columns=3, name="control residuals"))
    legend = rrb.PlotLegend(corner="LeftTop")
    plots = [rrb.TimeSeriesView(name="noise prediction norms", origin=f"{root}diffusion/eps", plot_legend=legend)]
    if blocks:
        plots.append(rrb.TimeSeriesView(name="control residual norms", origin=f"{root}control/residual",
                                        plot_legend=legend))
    bottom.append(rrb.Vertical(*plots))
    return rrb.Vertical(rrb.Horizontal(*top), rrb.Horizontal(*bottom, column_shares=[1, 2, 2][:len(bottom)]),
                        row_shares=[1, 1], name=name)


def sampling_blueprint(prefixes: list[str], names: list[str], blocks: int, truth: bool) -> rrb.Blueprint:
    """Tabs with one :func:`sample_view` per map (the first ``MAX_TABS``; the others are in the
    entity tree), beside the run's info document."""
    views = [sample_view(p, n, blocks, truth) for p, n in zip(prefixes[:MAX_TABS], names)]
    body = views[0] if len(views) == 1 else rrb.Tabs(*views)
    return rrb.Blueprint(rrb.Horizontal(body, rrb.TextDocumentView(origin="/info", name="info"),
                                        column_shares=[6, 1]),
                         rrb.BlueprintPanel(expanded=False), rrb.SelectionPanel(expanded=False),
                         rrb.TimePanel(expanded=True, timeline="diffusion_step"))
