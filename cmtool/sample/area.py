"""``cmtool sample --area``: one HD map of a whole area of an SD map, not one per 64 m frame.

The area's roads are covered with tiles (:func:`cmtool.data.tiles.cover`: frames on the roads, facing along
them, as the model was trained on); each tile is one sampling input (the SD raster of its frame, the guarantee's
rule lanes of its frame), generated in batches as ``cmtool sample`` generates any list of inputs; the tiles' lane
graphs are stitched into one (:func:`cmtool.maps.stitch.stitch`). The result is judged over 64 m windows (the
tiles' frames: validity, legal one-way share, SD road covered) and by its open seams: lane ends cut between two
tiles that the other tile's lanes do not continue, counted apart where an SD road goes on through them.
"""

from __future__ import annotations

import hashlib
import json
import math
import shutil
import sys
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import cv2
import numpy as np
import rerun as rr
import shapely

from cmtool.core import dist as D
from cmtool.core.errors import CmtoolError
from cmtool.core.geo import LocalProjection, wrap_lon
from cmtool.core.geometry import CV_SHIFT, ego_to_pixel, to_frame
from cmtool.core.jsonio import OutputSet, json_text, write_text_atomic
from cmtool.core.progress import Progress
from cmtool.data.rules import rule_layout
from cmtool.data.scene import Pose, SceneCropper
from cmtool.data.sd_raster import rasterize_sd
from cmtool.data.tiles import cover
from cmtool.maps.hdmap import drives_on
from cmtool.maps.lanegraph import LaneGraph, read_jsonl, write_jsonl
from cmtool.maps.patch import complete, open_ends, prune, trim
from cmtool.maps.sdmap import SDMap
from cmtool.maps.stitch import Seam, stitch
from cmtool.metrics.connectivity import END_M, routed_share, sd_end_pairs, unrouted
from cmtool.metrics.geometric import legal_oneway, sd_adherence
from cmtool.metrics.lanes import distance_to_polylines
from cmtool.metrics.validity import check
from cmtool.model import checkpoint as ckpt
from cmtool.sample.generator import MapGenerator
from cmtool.sample.inputs import ControlInput
from cmtool.sample.job import SampleSettings
from cmtool.sample.layouts import NO_INIT
from cmtool.sample.pool import pipelined
from cmtool.sample.run import batch_maps, denoiser, plan
from cmtool.viz.area import area_blueprint, log_area, place_tile
from cmtool.viz.draw import lanes_image, legend, sd_panel, title_strip
from cmtool.viz.recording import close_recording, open_recording
from cmtool.viz.show import write_png

EDGE_M = 10.0  # --area all: the roads' extent and this much around it (the lanes beside the outermost roads)
ON_ROAD_M = 8.0  # an open seam this close to an SD road is one where the road goes on
ON_SCREEN_M = 40.0  # the recording shows the SD roads this far around the box
NEAR_M = 100.0  # roads this near the box take part in the rule layouts (tile frames reach 32 m beyond it)
WINDOWS = 256  # at most this many 64 m windows are scored
CHECKS = 2  # at most this many times the unrouted SD road-end pairs are followed and their stuck traffic lent lanes
RECORDED_TILES = 128  # area.rrd records the denoising of the batches of tiles that start before this one


@dataclass
class AreaMap:
    graph: LaneGraph  # area metres east/north of ``centre``, placed by meta.geo
    seams: list[Seam]  # lane ends cut between two tiles that the map still leaves open
    disagreed: list[Seam]  # the seams the stitching left open, where neighbouring tiles drew different lanes
    recorded: int  # tiles whose denoising is recorded
    tiles: list  # the tiles' poses (the SD map's metres)
    tile_maps: list[LaneGraph]  # each tile's map, in its frame
    seconds: float  # generating, stitching and the guarantee


def area_box(sd_map: SDMap, spec: str, latlon: bool = True) -> tuple[float, float, float, float]:
    """The area of ``--area SPEC`` in the SD map's metres: "all" (the extent of its roads and ``EDGE_M`` around), or
    two opposite corners, "LAT0,LON0,LAT1,LON1" (``latlon``: :func:`_latlon_box`, the short way round the globe
    unless only the long way holds a road) or "X0,Y0,X1,Y1" (metres). An area that no road crosses is refused."""
    every = np.concatenate([r.polyline for r in sd_map.roads])
    extent = (*(every.min(axis=0) - EDGE_M), *(every.max(axis=0) + EDGE_M))
    if spec == "all":
        return tuple(map(float, extent))
    want = "LAT0,LON0,LAT1,LON1" if latlon else "X0,Y0,X1,Y1 (metres)"
    try:
        a, b, c, d = (float(v) for v in spec.split(","))
    except ValueError:
        raise CmtoolError(f"--area {spec!r}: expected all or {want}, two opposite corners") from None
    if not all(math.isfinite(v) for v in (a, b, c, d)):
        raise CmtoolError(f"--area {spec!r}: expected finite numbers")
    if latlon:
        if not (-90 <= min(a, c) and max(a, c) <= 90 and -180 <= min(b, d) and max(b, d) <= 180):
            raise CmtoolError(f"--area {spec!r}: latitudes must be in [-90, 90] and longitudes in [-180, 180]")
        proj = LocalProjection(sd_map.meta["lat0"], sd_map.meta["lon0"])
        boxes = [_latlon_box(proj, (a, b, c, d), extent, short) for short in (True, False)]  # the way round with roads
    else:
        boxes = [(a, b, c, d)]
    lines = [shapely.LineString(r.polyline) for r in sd_map.roads]
    for a, b, c, d in boxes:
        box = (float(min(a, c)), float(min(b, d)), float(max(a, c)), float(max(b, d)))
        if not shapely.intersects(shapely.box(*box), lines).any():
            continue
        if box[2] - box[0] < 1.0 or box[3] - box[1] < 1.0:
            raise CmtoolError(f"--area {spec!r}: the corners must lie at least a metre apart each way")
        return box
    raise CmtoolError(f"--area {spec!r}: no road of the map lies in the area")


def _latlon_box(proj: LocalProjection, corners, extent, short: bool = True) -> tuple[float, float, float, float]:
    """Two opposite corners (lat, lon, lat, lon) as metres (x, y, x, y) of ``proj``: the longitudes span the short way
    round (across 180 where they lie more than 180 apart, unless not ``short``; -180 to 180 all the way), and the box
    is cut to the map's
    ``extent`` (metres) before it is projected, so that a box far larger than the map does not fold back through the
    projection, and after (a box beside the map comes out of no width)."""
    lat0, lon0, lat1, lon1 = corners
    west, east = min(lon0, lon1), max(lon0, lon1)
    if 180 < east - west < 360 and short:
        west, east = east, west + 360
    turn = 360.0 * round((0.5 * (west + east) - proj.lon0) / 360.0)  # the box's turn of the globe nearest the map
    x0, y0, x1, y1 = extent
    near = proj.to_latlon(np.array([[x0, y0], [x0, y1], [x1, y0], [x1, y1]]))
    lats, lons = near[:, 0], wrap_lon(near[:, 1], proj.lon0)
    south, north = max(min(lat0, lat1), lats.min()), min(max(lat0, lat1), lats.max())
    west, east = max(west - turn, lons.min()), min(east - turn, lons.max())
    (a, b), (c, d) = proj.to_metres(np.array([south, max(south, north)]), np.array([west, max(west, east)]))
    return max(a, x0), max(b, y0), min(c, x1), min(d, y1)


def generate_area(gen: MapGenerator, sd_map: SDMap, box, settings: SampleSettings, name: str,
                  progress: bool = True, cache: Path | None = None, info: D.DistInfo = D.SINGLE,
                  rec: rr.RecordingStream | None = None, workers: int = 1) -> AreaMap | None:
    """Cover the roads in ``box`` with tiles, generate a map for each and stitch them into one (the SD map's roads
    farther than ``NEAR_M`` from the box are left out of the rule layouts the tiles start from and borrow from).
    ``cache``: a folder that keeps finished batches of tiles, so that a killed run goes on where it stopped; under
    ``torchrun`` (``info``) the processes share the batches and the main process stitches (the others get None).
    ``rec``: gets the layout (:func:`cmtool.viz.area.area_blueprint`) and records the denoising of the tiles of the
    batches that start before ``RECORDED_TILES`` and that this process generates, each tile in its place in the area
    (:func:`cmtool.viz.area.place_tile`). ``workers``: processes that check the tiles' maps beside the denoising
    (:mod:`cmtool.sample.pool`)."""
    began = time.perf_counter()
    sd_map = _near(sd_map, box, NEAR_M)
    tiles = cover(sd_map, box)
    if not tiles:
        raise CmtoolError(f"{name}: no road in the area to stand a tile on")
    inputs = [ControlInput(f"{name}_t{k}", rasterize_sd(sd_map, t.x, t.y, t.yaw), f"tile {k} of {name}",
                           city=sd_map.city, sd_map=sd_map, pose=(t.x, t.y, t.yaw)) for k, t in enumerate(tiles)]
    centre = 0.5 * np.array([box[0] + box[2], box[1] + box[3]])
    jobs = plan(gen, inputs, settings)
    if rec is not None:  # the batches that start before RECORDED_TILES
        upto = next((b for b in range(0, len(jobs), settings.batch) if b >= RECORDED_TILES), len(jobs))
        for k, job in enumerate(jobs[:upto]):
            job.prefix = place_tile(rec, k, tiles[k], centre)
        rec.send_blueprint(area_blueprint(upto))
    maps, recorded = _tile_maps(gen, jobs, settings, tiles, cache, progress, info, rec, workers)
    if maps is None:
        return None
    graph, disagreed = stitch(maps, tiles, box, centre)
    seams, changed = disagreed, {}
    if settings.guarantee:
        graph, changed = area_guarantee(graph, sd_map, box, centre, disagreed)
        still = open_ends(graph, np.array([s.point for s in disagreed]).reshape(-1, 2))
        seams = [s for s in disagreed if len(still) and np.min(np.linalg.norm(still - s.point, axis=1)) < 0.01]
    graph.meta = {"source": f"area of {sd_map.source or name}", "checkpoint": ckpt.shown(gen.path),
                  "seed": settings.seed, "cfg": settings.cfg, "steps": settings.steps, "sampler": settings.sampler,
                  "precision": gen.precision, "guarantee": settings.guarantee, "area_guarantee": changed,
                  **({"init": settings.init, "strength": settings.strength} if settings.init != NO_INIT else {})}
    if "lat0" in sd_map.meta:
        lat, lon = LocalProjection(sd_map.meta["lat0"], sd_map.meta["lon0"]).to_latlon(centre)
        graph.meta["geo"] = {"lat": round(float(lat), 8), "lon": round(float(lon), 8), "heading": 90.0}
    return AreaMap(graph, seams, disagreed, recorded, tiles, maps, time.perf_counter() - began)


def _tile_maps(gen: MapGenerator, jobs, settings: SampleSettings, tiles, cache: Path | None, progress: bool,
               info: D.DistInfo, rec: rr.RecordingStream | None = None,
               workers: int = 1) -> tuple[list[LaneGraph] | None, int]:
    """The tiles' lane graphs, ``settings.batch`` at a time (a batch's noise depends on the seed and its first tile
    alone): batches that ``cache`` holds from a run with the same tiles and settings are read back, the others
    generated (their steps recorded to ``rec`` up to ``RECORDED_TILES``; checked by ``workers`` beside the
    denoising, :func:`cmtool.sample.pool.pipelined`, or dealt among the processes of a torchrun), and written there
    as they finish (by the main process, which returns them all; the others return None); and how
    many tiles' steps were recorded."""
    sizes = {b: len(jobs[b:b + settings.batch]) for b in range(0, len(jobs), settings.batch)}
    done, recorded = {}, 0
    if cache is not None and info.main:
        done = _cached_batches(cache, sizes, _run_key(gen, settings, tiles))
        if done and progress:
            print(f"resuming: {sum(map(len, done.values()))} of {len(jobs)} tiles already made ({cache})",
                  file=sys.stderr)
    todo = D.broadcast([b for b in sizes if b not in done], info)  # the main process read the cache
    with Progress(sum(sizes[b] for b in todo), "area", "tiles",
                  enabled=progress and info.main) as bar:

        def finished(b: int, graphs: list[LaneGraph], seconds: float | None = None) -> None:
            done[b] = [LaneGraph.from_json(g.to_json()) for g in graphs]  # rounded as the cache keeps them
            if cache is not None:
                write_jsonl(cache / f"b{b:07d}.jsonl", graphs)
            bar.update(len(graphs))

        if info.world == 1:
            denoise = denoiser(gen, settings, rec, ego=False, recorded=lambda b: b < RECORDED_TILES)
            pipelined(jobs, settings, denoise, None, workers, finished, starts=todo)
            recorded = sum(sizes[b] for b in todo if b < RECORDED_TILES) if rec is not None else 0
        else:
            def make(b: int) -> tuple[int, list[LaneGraph]]:
                nonlocal recorded
                recorded += len(jobs[b:b + settings.batch]) if rec is not None and b < RECORDED_TILES else 0
                return b, [g for g, _ in batch_maps(gen, jobs[b:b + settings.batch], b, settings,
                                                    rec if b < RECORDED_TILES else None, placed=True)]

            for b, graphs in D.dealt(todo, info, make):
                finished(b, graphs)
    return ([g for b in sizes for g in done[b]] if info.main else None), recorded


def _run_key(gen: MapGenerator, settings: SampleSettings, tiles) -> str:
    """What makes a cached batch reusable: the checkpoint, the settings and the tiles."""
    what = json.dumps({"checkpoint": str(gen.path), "precision": gen.precision, "smooth": gen.smooth,
                       "encoder": str(gen.encoder_path), "settings": asdict(settings),
                       "tiles": [[round(t.x, 3), round(t.y, 3), round(t.yaw, 6)] for t in tiles]}, sort_keys=True)
    return hashlib.sha256(what.encode()).hexdigest()


def _cached_batches(cache: Path, sizes: dict[int, int], key: str) -> dict[int, list[LaneGraph]]:
    """The whole batches (``sizes``: tiles per batch start) a killed run with ``key`` left in ``cache``; a batch
    that is damaged or holds another number of tiles is made again, a cache of another run is emptied."""
    cache.mkdir(parents=True, exist_ok=True)
    stamp = cache / "run.key"
    if not stamp.is_file() or stamp.read_text().strip() != key:
        for old in cache.glob("b*.jsonl"):
            old.unlink()
        write_text_atomic(stamp, key + "\n")
        return {}
    done = {}
    for b, n in sizes.items():
        try:
            graphs = read_jsonl(cache / f"b{b:07d}.jsonl")
        except CmtoolError:  # missing, cut short or damaged
            continue
        if len(graphs) == n:
            done[b] = graphs
    return done


def area_guarantee(graph: LaneGraph, sd_map: SDMap, box, centre, seams: list[Seam]) -> tuple[LaneGraph, dict]:
    """The stitched map made to agree with its SD map as a whole (:mod:`cmtool.maps.patch`): lanes cut where they run
    on past the SD map's dead ends; lanes dropped whose every way on (or in) ends at an open seam, where the tiles
    disagree; then, wherever the rule layout of the SD map lets traffic go on and the map does not, the rule layout's
    lanes lent and joined to the map's. Last, the SD road-end pairs (:mod:`cmtool.metrics.connectivity`) the map
    still does not route are followed along the rule layout from their first end, and each rule lane where that
    traffic gets stuck is lent from there on (:func:`cmtool.maps.patch.stranded`). Returns the map and what each
    step changed, with the pairs left unrouted before that last step."""
    graph, trimmed = trim(graph, sd_map, centre)
    graph, pruned = prune(graph, np.array([s.point for s in seams]).reshape(-1, 2))
    rules, checked = rule_layout(sd_map, drives_on(sd_map.city)), 0
    graph, lent = complete(graph, rules, box, centre)
    ends, pairs = sd_end_pairs(sd_map, box)
    unrouted_before = None
    for _ in range(CHECKS):
        missing = unrouted(graph, ends - centre, pairs)
        unrouted_before = len(missing) if unrouted_before is None else unrouted_before
        if not missing:
            break
        graph, more = complete(graph, rules, box, centre, entries=(ends[sorted({a for a, _ in missing})] - centre,
                                                                   END_M))
        checked += more
        if not more:
            break
    return graph, {"trimmed": trimmed, "pruned": pruned, "lent": lent, "pairs": len(pairs),
                   "unrouted_before_check": unrouted_before, "lent_where_traffic_was_stuck": checked}


def _near(sd_map: SDMap, box, margin: float) -> SDMap:
    """``sd_map`` with only the roads that come within ``margin`` of ``box``."""
    area = shapely.box(box[0] - margin, box[1] - margin, box[2] + margin, box[3] + margin)
    roads = [r for r in sd_map.roads if shapely.intersects(area, shapely.LineString(r.polyline))]
    return replace(sd_map, roads=roads) if len(roads) < len(sd_map.roads) else sd_map


def _clipped_roads(sd_map: SDMap, box, margin: float, centre) -> list[np.ndarray]:
    """The SD roads' pieces within ``margin`` of ``box``, in area metres."""
    area = shapely.box(box[0] - margin, box[1] - margin, box[2] + margin, box[3] + margin)
    pieces = shapely.intersection(np.array([shapely.LineString(r.polyline) for r in sd_map.roads]), area)
    return [shapely.get_coordinates(p) - centre for piece in pieces for p in getattr(piece, "geoms", [piece])
            if not p.is_empty and isinstance(p, shapely.LineString)]


def area_scores(area: AreaMap, sd_map: SDMap, box) -> dict:
    """The area map judged as a whole: lanes, successors, open seams (all, and where an SD road goes on through
    them), the share of the SD map's connected road-end pairs its lanes route (:mod:`cmtool.metrics.connectivity`)
    and, over up to ``WINDOWS`` of its tiles' 64 m frames, the mean validity, legal one-way share (weighted by
    the length judged) and SD road covered (of the SD roads inside ``box``)."""
    centre = 0.5 * np.array([box[0] + box[2], box[1] + box[3]])
    graph = area.graph
    roads = [r.polyline - centre for r in sd_map.roads]
    points = np.array([s.point for s in area.seams]).reshape(-1, 2)
    on_road = int((distance_to_polylines(points, roads) <= ON_ROAD_M).sum()) if len(points) else 0
    cropper = SceneCropper(graph.to_hd())
    picked = np.unique(np.linspace(0, len(area.tiles) - 1, min(WINDOWS, len(area.tiles))).round().astype(int))
    validity, legal, judged, covered = [], [], [], []
    for k in picked:
        t = area.tiles[k]
        x, y = t.x - centre[0], t.y - centre[1]
        window = cropper.extract(Pose(float(x), float(y), t.yaw), num_lines=300, num_lights=50).to_lanegraph()
        sd = rasterize_sd(sd_map, t.x, t.y, t.yaw) * _inside(box, t)[..., None]
        validity.append(check(window, routes=False).score)
        share, metres = legal_oneway(window.lanes, sd)
        if not math.isnan(share):
            legal.append(share * metres)
            judged.append(metres)
        c = sd_adherence(window.lanes, sd)["sd_coverage"]
        if not math.isnan(c):
            covered.append(c)
    ends, pairs = sd_end_pairs(sd_map, box)
    routed = routed_share(graph, ends - centre, pairs)
    return {"lanes": len(graph.lanes), "successors": len(graph.successors), "tiles": len(area.tiles),
            "seams_disagreed": len(area.disagreed), "open_seams": len(area.seams), "open_seams_on_roads": on_road,
            "sd_end_pairs": len(pairs), "sd_end_pairs_routed": None if math.isnan(routed) else round(routed, 4),
            "windows": len(picked),
            "validity": round(float(np.mean(validity)), 4),
            "legal_oneway": round(float(sum(legal) / sum(judged)), 4) if judged else None,
            "sd_coverage": round(float(np.mean(covered)), 4) if covered else None,
            "seconds": round(area.seconds, 1)}


def run_area(gen: MapGenerator, sd_map: SDMap, box, settings: SampleSettings, out: Path, name: str,
             progress: bool = True, info: D.DistInfo = D.SINGLE, rrd: Path | None = None,
             command: str = "", workers: int = 1) -> tuple[AreaMap, dict] | None:
    """Generate the area map of ``box``, score it and write ``OUT/NAME_area.json`` (the lane graph; its meta holds
    the scores and the open seams), ``OUT/NAME_area.png`` (SD map | area map) and, unless ``rrd`` is None, the
    recording of its assembly (:mod:`cmtool.viz.area`) as one set. Finished batches of tiles wait in
    ``OUT/.NAME_area.tiles`` until then: run the same command again after a kill to go on. Under ``torchrun`` only
    the main process returns (the others None); ``workers``: as :func:`generate_area`'s."""
    cache = out / f".{name}_area.tiles"
    rec = open_recording("area") if rrd is not None and info.main else None
    area = generate_area(gen, sd_map, box, settings, name, progress, cache, info, rec, workers)
    if area is None:
        return None
    centre = 0.5 * np.array([box[0] + box[2], box[1] + box[3]])
    scores = area_scores(area, sd_map, box)
    timeless = {k: v for k, v in scores.items() if k != "seconds"}  # a resumed run's map is the unbroken run's
    area.graph.meta["area"] = {"box_m": [round(v - c, 3) for v, c in zip(box, (*centre, *centre))], **timeless,
                               "seams": [{"point": s.point, "tiles": [s.tile, s.other], "leaving": s.leaving}
                                         for s in area.seams],
                               "seams_disagreed_at": [s.point for s in area.disagreed]}
    outputs = OutputSet()
    try:
        outputs.write_text(out / f"{name}_area.json", json_text(area.graph.to_json()))
        write_png(out / f"{name}_area.png", area_picture(area, sd_map, box), outputs)
        if rec is not None:
            rec.log("info", rr.TextDocument(_info(command, name, scores, area.recorded), media_type="text/markdown"),
                    static=True)
            roads = _clipped_roads(sd_map, box, ON_SCREEN_M, centre)
            points = np.array([s.point for s in area.seams]).reshape(-1, 2)
            on_road = distance_to_polylines(points, roads) <= ON_ROAD_M if len(points) else []
            log_area(rec, roads, area.tiles, area.tile_maps, area.graph, area.seams, on_road, centre)
            close_recording(rec, rrd, outputs)
        outputs.commit()
    except BaseException:
        outputs.discard()
        raise
    shutil.rmtree(cache, ignore_errors=True)
    return area, scores


def _info(command: str, name: str, scores: dict, recorded: int) -> str:
    lines = [f"# {name}: one map of an area\n", f"`{command}`\n" if command else "",
             f"Timeline `tile`: the tiles appear, then the stitched map. Timeline `diffusion_step`: {recorded} tiles "
             "denoise in their places (`area/denoising/k`).\n" if recorded else "", "| score | value |", "|---|---|"]
    return "\n".join(lines + [f"| {k} | {v} |" for k, v in scores.items()])


def area_picture(area: AreaMap, sd_map: SDMap, box, size: int = 1024) -> np.ndarray:
    """SD map | area map over ``box``, north up; open seams ringed (magenta where an SD road goes on through them)."""
    graph = area.graph
    centre = 0.5 * np.array([box[0] + box[2], box[1] + box[3]])
    extent = max(box[2] - box[0], box[3] - box[1]) + 8.0
    north = math.pi / 2.0
    sd = rasterize_sd(sd_map, float(centre[0]), float(centre[1]), north, frame_m=extent, size=size)
    up = lambda p: to_frame(np.asarray(p, np.float64), 0.0, 0.0, north)  # noqa: E731
    img = lanes_image([up(l) for l in graph.lanes], [up(l) for l in graph.green_lights],
                      [up(l) for l in graph.red_lights], graph.successors, extent, size, ego=False)
    roads = [r.polyline - centre for r in sd_map.roads]
    for seam in area.seams:
        at = tuple(int(v) for v in ego_to_pixel(up(np.array(seam.point)), extent / size, extent))
        on_road = distance_to_polylines(np.array([seam.point]), roads)[0] <= ON_ROAD_M
        cv2.circle(img, at, 6 << CV_SHIFT, (255, 0, 255) if on_road else (150, 150, 150), 2, cv2.LINE_AA, CV_SHIFT)
    titles = ["SD map", f"generated: {len(graph.lanes)} lanes from {len(area.tiles)} tiles, {len(area.seams)} open "
                        f"seams (ringed)"]
    panels = [np.concatenate([title_strip(t, size), p], axis=0) for t, p in zip(titles, (sd_panel(sd, size), img))]
    body = np.concatenate([panels[0], np.full((panels[0].shape[0], 6, 3), 12, np.uint8), panels[1]], axis=1)
    return np.concatenate([body, legend(body.shape[1])], axis=0)


def _inside(box, tile, size: int = 128, frame_m: float = 64.0) -> np.ndarray:
    """(size, size) bool: which pixels of the tile's raster (the raster convention: row 0 in front, column 0 on the
    left) lie inside ``box``."""
    centres = (np.arange(size) + 0.5) * frame_m / size - frame_m / 2.0
    ahead, left = np.meshgrid(-centres, -centres, indexing="ij")  # row r: x = half - (r + 0.5) px; column c: y
    c, s = math.cos(tile.yaw), math.sin(tile.yaw)
    x, y = tile.x + c * ahead - s * left, tile.y + s * ahead + c * left
    return (x >= box[0]) & (x <= box[2]) & (y >= box[1]) & (y <= box[3])
