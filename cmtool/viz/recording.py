"""Rerun recordings of scenes (entity layout: docs/sampling.md), shared by ``data show`` and sampling.

Scene data is logged in ego-frame metres (x forward, y left) under ``<prefix>hd/...``; a transform
on ``<prefix>hd`` maps it to the 2D view's screen axes (forward up, left left), and the SD raster
at ``<prefix>control/sd`` is placed on the same 64 m square, so lanes draw over their control.
"""

from __future__ import annotations

import socket
import subprocess
import sys
import uuid
import weakref
from pathlib import Path

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from cmtool.core.errors import CmtoolError
from cmtool.core.jsonio import OutputSet, atomic_open
from cmtool.viz.draw import GREEN, LIGHT_BAR_RADIUS_M, RED, heading_colours, light_bars, sd_panel

# ego (x forward, y left) -> screen (u right, v down): u = -y, v = -x
_EGO_TO_SCREEN = [[0.0, -1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]
# one application id per kind of recording: a viewer keeps a layout per application id, so a second kind of
# recording opened in a running viewer shows its own layout, not the first one's
APP_IDS = {kind: f"cmtool_{kind}" for kind in ("data", "train", "sample", "eval", "ablate", "area")}
LANE_RADIUS_M = 0.2  # thin enough to see the junction through
LIGHT_RADIUS_M, LIGHT_DRAW_ORDER = LIGHT_BAR_RADIUS_M, 25.0  # a light's bar across its lane, over the lanes (20)
DECODED = [150, 150, 150]  # the decoded lanes under the final map
DROPPED = [255, 255, 255]  # the decoded lanes the final map leaves out (no SD road explains them): no heading's hue
GRPC_PORT, WEB_PORT = 9876, 9090  # where --serve serves a recording and Rerun's web viewer


def open_recording(kind: str, recording_id: str | None = None) -> rr.RecordingStream:
    """A recording stream of one ``kind`` (a key of :data:`APP_IDS`), kept in memory until :func:`close_recording`
    writes it to its file. (Rerun's own file writer blocks for ever when a write fails, as on a full disk; written
    by cmtool, such a file is an error that names it.)"""
    rec = rr.RecordingStream(APP_IDS[kind], recording_id=recording_id)
    _MEMORY[rec] = rec.memory_recording()
    return rec


def in_memory(rec: rr.RecordingStream) -> bool:
    """Whether ``rec`` is a recording of :func:`open_recording` (written at the end, no live viewer)."""
    return rec in _MEMORY


def close_recording(rec: rr.RecordingStream, path, outputs: OutputSet | None = None) -> None:
    """Close a recording of :func:`open_recording` and write it to ``path`` (an ``.rrd`` file), atomically or, with
    ``outputs``, staged with the other files of the command."""
    data = _drained(rec)
    if outputs is not None:
        outputs.write_bytes(path, data)
    else:
        with atomic_open(path, "wb") as f:
            f.write(data)


def _drained(rec: rr.RecordingStream) -> bytes:
    """Close a recording of :func:`open_recording`; returns it as the bytes of an ``.rrd`` file."""
    memory = _MEMORY.pop(rec)
    rec.flush()
    data = memory.drain_as_bytes()
    rec.disconnect()
    return data


class ReplayRecording:
    """A recording of one ``kind`` that keeps what is logged to it (``set_time`` and ``log`` calls) since its last
    :meth:`write`, as a long run does between checkpoints. A write makes those calls a Rerun stream of their own and
    merges it into ``path`` (``rerun rrd merge``), so memory holds one checkpoint's calls, never the whole run's
    (Rerun's own file writer blocks for ever when a write fails). ``live``: also stream it to this sink
    (``--serve``)."""

    def __init__(self, kind: str, path, live: rr.GrpcServerSink | None = None):
        self.kind, self.path, self.calls, self.blueprint = kind, Path(path), [], None
        self.part = self.path.with_name(f".{self.path.name}.part")
        self.recording_id = str(uuid.uuid4())
        self.time = None  # the last set_time call: the next part starts at that time
        self.written = False
        self.live = None
        if live is not None:
            self.live = rr.RecordingStream(APP_IDS[kind], recording_id=self.recording_id)
            self.live.set_sinks(live)

    def send_blueprint(self, blueprint: rrb.Blueprint) -> None:
        self.blueprint = blueprint
        if self.live is not None:
            self.live.send_blueprint(blueprint)

    def set_time(self, *args, **kwargs) -> None:
        self._call("set_time", args, kwargs)

    def log(self, *args, **kwargs) -> None:
        self._call("log", args, kwargs)

    def _call(self, name: str, args, kwargs) -> None:
        self.calls.append((name, args, kwargs))
        if self.live is not None:
            getattr(self.live, name)(*args, **kwargs)

    def write(self) -> None:
        """Add what was logged since the last write to ``path`` (atomically)."""
        rec = open_recording(self.kind, self.recording_id)
        if self.blueprint is not None and not self.written:
            rec.send_blueprint(self.blueprint)
        for name, args, kwargs in ([("set_time", *self.time)] if self.time else []) + self.calls:
            getattr(rec, name)(*args, **kwargs)
            if name == "set_time":
                self.time = (args, kwargs)
        with atomic_open(self.part, "wb") as f:
            f.write(_drained(rec))
        try:
            with atomic_open(self.path, "wb") as f:
                done = subprocess.run([sys.executable, "-m", "rerun", "rrd", "merge",
                                       *([str(self.path)] if self.written else []), str(self.part)], stdout=f,
                                      stderr=subprocess.PIPE, text=True)
                if done.returncode:
                    why = (done.stderr.strip().splitlines() or ["no message"])[-1]
                    raise CmtoolError(f"{self.path}: could not add to the recording ({why})")
        finally:
            self.part.unlink(missing_ok=True)
        self.calls, self.written = [], True

    def close(self) -> None:
        """Stop streaming (which frees the served port); the file is as the last :meth:`write` left it."""
        if self.live is not None:
            self.live.flush()
            self.live.disconnect()


_MEMORY: weakref.WeakKeyDictionary[rr.RecordingStream, rr.MemoryRecording] = weakref.WeakKeyDictionary()


def served(port: int = GRPC_PORT) -> rr.GrpcServerSink:
    """A sink that serves a recording over gRPC from this process, keeping it for viewers that connect late."""
    _check_free(port)
    return rr.GrpcServerSink(port=port)


def serve_web_viewer(grpc_port: int = GRPC_PORT, web_port: int = WEB_PORT) -> str:
    """Serve Rerun's web viewer from this process, pointed at the gRPC server on ``grpc_port``; returns what to
    tell the user: the address to open, also through an SSH tunnel from a laptop."""
    _check_free(grpc_port)  # both at once, before any work: the gRPC server starts later
    _check_free(web_port)
    rr.serve_web_viewer(web_port=web_port, open_browser=False, connect_to=f"rerun+http://localhost:{grpc_port}/proxy")
    host = socket.gethostname()
    return (f"serving the recording: open http://{host}:{web_port}/?url=rerun%2Bhttp://{host}:{grpc_port}/proxy "
            f"in a browser, or from a laptop: ssh -L {web_port}:localhost:{web_port} -L {grpc_port}:localhost:"
            f"{grpc_port} {host}, then http://localhost:{web_port}/?url=rerun%2Bhttp://localhost:{grpc_port}/proxy "
            f"(or a native viewer: rerun rerun+http://localhost:{grpc_port}/proxy)")


def _check_free(port: int) -> None:
    """Refuse at once a port that another process holds (listening or only bound), which Rerun would wait on."""
    with socket.socket() as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind(("0.0.0.0", port))
        except OSError:
            raise CmtoolError(f"--serve: port {port} is in use (another cmtool --serve or a Rerun viewer?)") from None


def log_ego_frame(rec: rr.RecordingStream, path: str) -> None:
    """Make ``path`` an ego-frame space: children log metres (x forward, y left), shown forward-up."""
    rec.log(path, rr.Transform3D(mat3x3=_EGO_TO_SCREEN), static=True)


def lane_colours(lines) -> np.ndarray:
    """One RGB colour per lane: the heading from its first to its last point."""
    mid = np.array([np.asarray(l)[-1] - np.asarray(l)[0] for l in lines]).reshape(-1, 2)
    return heading_colours(np.arctan2(mid[:, 1], mid[:, 0]))


def log_lanes(rec: rr.RecordingStream, prefix: str, lines, green=(), red=(), edges=(), static: bool = False) -> None:
    """Log lane polylines (heading-coloured), successor arrows and lights (:func:`light_strips`) under
    ``<prefix>hd``."""
    log_ego_frame(rec, f"{prefix}hd")
    lines = [np.asarray(l) for l in lines]
    rec.log(f"{prefix}hd/lanes", rr.LineStrips2D(lines, radii=LANE_RADIUS_M, colors=lane_colours(lines)),
            static=static)
    # logged even when empty, so that a scene without successors on a timeline does not keep the last one's
    origins = np.array([lines[i][max(-3, -len(lines[i]))] for i, _ in edges]).reshape(-1, 2)
    targets = np.array([lines[j][min(2, len(lines[j]) - 1)] for _, j in edges]).reshape(-1, 2)
    rec.log(f"{prefix}hd/successors", rr.Arrows2D(origins=origins, vectors=targets - origins, radii=0.15,
                                                  colors=[255, 255, 255]), static=static)
    for state, colour, vecs in (("green", GREEN, green), ("red", RED, red)):
        rec.log(f"{prefix}hd/lights/{state}", light_strips(vecs, colour), static=static)


def light_strips(lights, colour) -> rr.LineStrips2D:
    """Lights as the viewer draws them: each a short bar of ``colour`` across its lane at its stop line (where its
    light line starts: :func:`~cmtool.viz.draw.light_bars`), over the lanes."""
    return rr.LineStrips2D(light_bars(lights), radii=LIGHT_RADIUS_M, colors=colour, draw_order=LIGHT_DRAW_ORDER)


def log_decoded(rec: rr.RecordingStream, prefix: str, lines, dropped=()) -> None:
    """Log a map's lanes as the model decoded them, thin, under ``<prefix>decoded``: grey, and white those of
    ``dropped`` (indices): beside the final map (``<prefix>hd``) it shows what the guarantee made of the model's map
    (lanes laid on the SD roads, lanes no SD road explains left out)."""
    dropped = set(dropped)
    colors = [DROPPED if k in dropped else DECODED for k in range(len(lines))]
    rec.log(f"{prefix}decoded/lanes", rr.LineStrips2D([np.asarray(l) for l in lines], radii=LANE_RADIUS_M / 2,
                                                      colors=colors, draw_order=-5.0), static=True)


def log_sd(rec: rr.RecordingStream, prefix: str, sd: np.ndarray, frame_m: float = 64.0, static: bool = False) -> None:
    """Log an SD raster (H, W, 3) as a readable image on the scene's square at ``<prefix>control/sd``."""
    size = sd.shape[0]
    half = frame_m / 2.0
    rec.log(f"{prefix}control/sd",
            rr.Image(sd_panel(sd, size), opacity=0.7, draw_order=-10.0, magnification_filter="Nearest"),
            rr.Transform3D(translation=[-half, -half, 0.0], scale=frame_m / size), static=static)


def log_layout(rec: rr.RecordingStream, prefix: str, layout: np.ndarray, frame_m: float = 64.0) -> None:
    """Log the layout channels a control branch reads (:func:`cmtool.data.layouts.layout_raster`) at
    ``<prefix>control/layout``: each lane pixel in the hue of its heading, the rest transparent."""
    size = layout.shape[0]
    half = frame_m / 2.0
    c, s = (layout.astype(np.float64) / 255.0 * 2.0 - 1.0).transpose(2, 0, 1)
    drawn = layout.any(-1)
    image = np.zeros((size, size, 4), np.uint8)
    image[drawn, :3] = heading_colours(np.arctan2(s[drawn], c[drawn]))
    image[drawn, 3] = 200
    rec.log(f"{prefix}control/layout", rr.Image(image, draw_order=-5.0, magnification_filter="Nearest"),
            rr.Transform3D(translation=[-half, -half, 0.0], scale=frame_m / size), static=True)


def log_scene(rec: rr.RecordingStream, prefix: str, scene) -> None:
    """Log a scene's lanes, successor arrows, lights and SD raster under ``prefix``, static (shown at any
    time)."""
    log_lanes(rec, prefix, scene.lines[scene.line_mask], scene.green[scene.green_mask], scene.red[scene.red_mask],
              scene.edges, static=True)
    if scene.sd is not None:
        log_sd(rec, prefix, scene.sd, scene.frame_m, static=True)


def grid_rows(count: int) -> list[int]:
    """How many of ``count`` views go in each row of a near-square layout with no empty cell: as many rows as the
    square root rounded, the longer rows first (13: 4, 3, 3, 3)."""
    rows = max(1, round(np.sqrt(count)))
    return [count // rows + (r < count % rows) for r in range(rows)]


def scenes_blueprint(names: list[str], half: float = 32.0, info: bool = True) -> rrb.Blueprint:
    """2D views in rows (:func:`grid_rows`), one per ``sample_{k}`` (titled by ``names``), plus the info text."""
    bounds = rrb.VisualBounds2D(x_range=[-half, half], y_range=[-half, half])
    views = [rrb.Spatial2DView(origin=f"/sample_{k}", name=name, visual_bounds=bounds) for k, name in enumerate(names)]
    rows = grid_rows(len(views))
    grid = rrb.Vertical(*[rrb.Horizontal(*views[first:first + n]) for first, n in zip(np.cumsum([0, *rows]), rows)])
    if not info:
        return rrb.Blueprint(grid, collapse_panels=True)
    return rrb.Blueprint(rrb.Horizontal(grid, rrb.TextDocumentView(origin="/info", name="info"),
                                        column_shares=[5, 1]), collapse_panels=True)


def training_blueprint(stage: str, previews: list[tuple[str, str, list[str]]]) -> rrb.Blueprint:
    """Loss, learning rate, gradient norm and the stage's other scores over ``train_step``, above the
    decoded previews (``previews``: (title, origin, contents) under ``train/preview``). A plot of one series has no
    legend (its title names it; Rerun's legend, inside the plot, covered the curve's end or start)."""
    plots = [rrb.TimeSeriesView(origin=f"/train/{key}", name=f"{stage}: {title}",
                                plot_legend=rrb.PlotLegend(visible=False))
             for key, title in (("loss", "loss"), ("lr", "learning rate"), ("grad_norm", "gradient norm"))]
    plots.append(rrb.TimeSeriesView(origin="/train", name=f"{stage}: other scores", contents=[
        "/train/**", "- /train/loss", "- /train/lr", "- /train/grad_norm", "- /train/preview/**"]))
    bounds = rrb.VisualBounds2D(x_range=[-32.0, 32.0], y_range=[-32.0, 32.0])
    views = [rrb.Spatial2DView(origin=f"/train/preview/{origin}", name=title, visual_bounds=bounds,
                               contents=[f"/train/preview/{origin}/{c}" for c in contents])
             for title, origin, contents in previews]
    rows = [rrb.Grid(*plots, grid_columns=4)] + ([rrb.Grid(*views, grid_columns=4)] if views else [])
    return rrb.Blueprint(rrb.Vertical(*rows), rrb.BlueprintPanel(expanded=False),
                         rrb.SelectionPanel(expanded=False), rrb.TimePanel(expanded=True, timeline="train_step"))
