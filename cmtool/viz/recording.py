"""Rerun recordings of scenes (entity layout: README "Generating maps"), shared by ``data show`` and sampling.

Scene data is logged in ego-frame metres (x forward, y left) under ``<prefix>hd/...``; a transform
on ``<prefix>hd`` maps it to the 2D view's screen axes (forward up, left left), and the SD raster
at ``<prefix>control/sd`` is placed on the same 64 m square, so lanes draw over their control.
"""

from __future__ import annotations

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from cmtool.viz.draw import GREEN, RED, heading_colours, sd_panel

# ego (x forward, y left) -> screen (u right, v down): u = -y, v = -x
_EGO_TO_SCREEN = [[0.0, -1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]


def open_recording(path, application_id: str = "cmtool") -> rr.RecordingStream:
    """A recording stream that writes to ``path`` (an ``.rrd`` file)."""
    rec = rr.RecordingStream(application_id)
    rec.save(str(path))
    return rec


def log_ego_frame(rec: rr.RecordingStream, path: str) -> None:
    """Make ``path`` an ego-frame space: children log metres (x forward, y left), shown forward-up."""
    rec.log(path, rr.Transform3D(mat3x3=_EGO_TO_SCREEN), static=True)


def lane_colours(lines) -> np.ndarray:
    """One RGB colour per lane: the heading from its first to its last point."""
    mid = np.array([np.asarray(l)[-1] - np.asarray(l)[0] for l in lines]).reshape(-1, 2)
    return heading_colours(np.arctan2(mid[:, 1], mid[:, 0]))


def log_lanes(rec: rr.RecordingStream, prefix: str, lines, green=(), red=(), edges=(), static: bool = False) -> None:
    """Log lane polylines (heading-coloured), successor arrows and light lines under ``<prefix>hd``."""
    log_ego_frame(rec, f"{prefix}hd")
    lines = [np.asarray(l) for l in lines]
    rec.log(f"{prefix}hd/lanes", rr.LineStrips2D(lines, radii=0.25, colors=lane_colours(lines)), static=static)
    if len(edges):
        origins = np.array([lines[i][max(-3, -len(lines[i]))] for i, _ in edges]).reshape(-1, 2)
        targets = np.array([lines[j][min(2, len(lines[j]) - 1)] for _, j in edges]).reshape(-1, 2)
        rec.log(f"{prefix}hd/successors", rr.Arrows2D(origins=origins, vectors=targets - origins, radii=0.15,
                                                      colors=[255, 255, 255]), static=static)
    for state, colour, vecs in (("green", GREEN, green), ("red", RED, red)):
        rec.log(f"{prefix}hd/lights/{state}", rr.LineStrips2D([np.asarray(v) for v in vecs], radii=0.8,
                                                              colors=colour, draw_order=20.0), static=static)


def log_sd(rec: rr.RecordingStream, prefix: str, sd: np.ndarray, frame_m: float = 64.0, static: bool = False) -> None:
    """Log an SD raster (H, W, 3) as a readable image on the scene's square at ``<prefix>control/sd``."""
    size = sd.shape[0]
    half = frame_m / 2.0
    rec.log(f"{prefix}control/sd",
            rr.Image(sd_panel(sd, size), opacity=0.7, draw_order=-10.0, magnification_filter="Nearest"),
            rr.Transform3D(translation=[-half, -half, 0.0], scale=frame_m / size), static=static)


def log_scene(rec: rr.RecordingStream, prefix: str, scene) -> None:
    """Log a scene's lanes, successor arrows, light lines and SD raster under ``prefix``."""
    log_lanes(rec, prefix, scene.lines[scene.line_mask], scene.green[scene.green_mask], scene.red[scene.red_mask],
              scene.edges)
    if scene.sd is not None:
        log_sd(rec, prefix, scene.sd, scene.frame_m)


def scenes_blueprint(names: list[str], half: float = 32.0, info: bool = True) -> rrb.Blueprint:
    """A grid of 2D views, one per ``sample_{k}`` (titled by ``names``), plus the info text."""
    bounds = rrb.VisualBounds2D(x_range=[-half, half], y_range=[-half, half])
    views = [rrb.Spatial2DView(origin=f"/sample_{k}", name=name, visual_bounds=bounds) for k, name in enumerate(names)]
    grid = rrb.Grid(*views, grid_columns=int(np.ceil(np.sqrt(max(len(views), 1)))))
    if not info:
        return rrb.Blueprint(grid, collapse_panels=True)
    return rrb.Blueprint(rrb.Horizontal(grid, rrb.TextDocumentView(origin="/info", name="info"),
                                        column_shares=[5, 1]), collapse_panels=True)
