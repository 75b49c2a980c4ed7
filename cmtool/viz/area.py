"""``area.rrd`` (``cmtool sample --area``): a whole area as it is assembled. On the ``tile`` timeline the tiles
appear one by one, each with its frame and the lanes it drew (area metres, north up, over the SD roads); at the
end they give way to the stitched map, its open seams ringed (magenta where an SD road goes on through them). On
the ``diffusion_step`` timeline the recorded tiles denoise in their places (``area/denoising/{k}``: each step's
predicted map, latent, noise norms and control residuals, as ``sample.rrd`` records a map's)."""

from __future__ import annotations

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from cmtool.core.geometry import from_frame
from cmtool.viz.recording import LANE_RADIUS_M, lane_colours

# x east, y north on a screen whose y points down; logged on ``area``, it acts in a view whose origin lies above it
# (a view shows its origin's own frame, in which the origin's transform does not act)
NORTH_UP = [[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, 1.0]]
SQUARE = np.array([[1.0, 1.0], [-1.0, 1.0], [-1.0, -1.0], [1.0, -1.0], [1.0, 1.0]])
SEAM_ON_ROAD, SEAM_OFF_ROAD = [255, 0, 255], [150, 150, 150]


def place_tile(rec: rr.RecordingStream, k: int, tile, centre) -> str:
    """Place tile ``k`` (a pose in the SD map's metres) in the area (``centre``: the SD map point at the area's
    origin): its frame's metres, as a tile's map and the steps of its denoising are logged, map into the area's.
    Returns the recording prefix of its denoising."""
    c, s = np.cos(tile.yaw), np.sin(tile.yaw)
    rec.log(f"area/denoising/{k}", rr.Transform3D(translation=[tile.x - centre[0], tile.y - centre[1], 0.0],
                                                  mat3x3=[[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]), static=True)
    return f"area/denoising/{k}/"


def log_area(rec: rr.RecordingStream, roads, tiles, tile_maps, graph, seams, on_road, centre,
             frame_m: float = 64.0) -> None:
    """Log the SD ``roads`` (area metres), each tile (a pose in the SD map's metres) with its lane graph
    ``tile_maps[k]`` (in its frame) at ``tile`` = k, and at the end the stitched ``graph`` (area metres) with its
    ``seams`` (``on_road``: whether an SD road goes on through each); ``centre``: the SD map point at the area's
    origin."""
    rec.log("area", rr.Transform3D(mat3x3=NORTH_UP), static=True)
    rec.log("area/sd", rr.LineStrips2D([np.asarray(r) for r in roads], radii=2.0, colors=[80, 80, 92],
                                       draw_order=-10.0), static=True)
    for k, (tile, lanes) in enumerate(zip(tiles, tile_maps)):
        rec.set_time("tile", sequence=k)
        rec.log(f"area/tiles/{k}/frame", rr.LineStrips2D([from_frame(SQUARE * frame_m / 2, tile.x, tile.y, tile.yaw)
                                                           - centre], radii=0.3, colors=[70, 110, 160]))
        lines = [from_frame(np.asarray(l, np.float64), tile.x, tile.y, tile.yaw) - centre for l in lanes.lanes]
        rec.log(f"area/tiles/{k}/lanes", rr.LineStrips2D(lines, radii=LANE_RADIUS_M, colors=lane_colours(lines)))
    rec.set_time("tile", sequence=len(tiles))
    rec.log("area/tiles", rr.Clear(recursive=True))
    lines = [np.asarray(l) for l in graph.lanes]
    rec.log("area/map/lanes", rr.LineStrips2D(lines, radii=LANE_RADIUS_M, colors=lane_colours(lines)))
    origins = np.array([lines[i][max(-3, -len(lines[i]))] for i, _ in graph.successors]).reshape(-1, 2)
    targets = np.array([lines[j][min(2, len(lines[j]) - 1)] for _, j in graph.successors]).reshape(-1, 2)
    rec.log("area/map/successors", rr.Arrows2D(origins=origins, vectors=targets - origins, radii=0.15,
                                               colors=[255, 255, 255]))
    rec.log("area/map/seams", rr.Points2D(np.array([s.point for s in seams]).reshape(-1, 2), radii=3.0,
                                          colors=[SEAM_ON_ROAD if r else SEAM_OFF_ROAD for r in on_road]))


def area_blueprint(placed: int) -> rrb.Blueprint:
    """The area's view (north up; the control residual heatmaps of the ``placed`` tiles, 0 to placed - 1, left out)
    beside the run's info, the ``tile`` timeline open at its end (the stitched map)."""
    area = rrb.Spatial2DView(origin="/", contents=["/area/**", *(f"- /area/denoising/{k}/control/**"
                                                                 for k in range(placed))],
                             name="area: tiles, then the stitched map")
    return rrb.Blueprint(rrb.Horizontal(area,
                                        rrb.TextDocumentView(origin="/info", name="info"), column_shares=[5, 1]),
                         rrb.BlueprintPanel(expanded=False), rrb.SelectionPanel(expanded=False),
                         rrb.TimePanel(expanded=True, timeline="tile", play_state="following"))
