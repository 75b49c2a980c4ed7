"""Rule-based lane layouts of SD maps, cropped into frames: ours (:mod:`cmtool.data.rules`) and SUMO's
``netconvert`` (:mod:`cmtool.formats.sumo`). They are the baselines of every evaluation, what ``cmtool sample
--init rules`` starts from and, drawn as :func:`layout_raster`, the layout channels of a ControlMap whose
``control.layout`` is set."""

from __future__ import annotations

import numpy as np

from cmtool.data.cache import load_manifest, scene_sd_maps
from cmtool.data.hd_raster import draw_direction_lines
from cmtool.data.rules import rule_layout
from cmtool.data.scene import Scene, SceneCropper
from cmtool.formats.sumo import netconvert_layout
from cmtool.maps.hdmap import drives_on

LAYOUTS = {"rules": rule_layout, "netconvert": netconvert_layout}  # SD map, driving side -> HD map
LAYOUT_CHANNELS = 2  # the layout's lanes as the HD raster draws them: 0.5 (cos h, sin h) + 0.5, background 0


def cropped_layouts(frames, method: str, **crop) -> list[Scene]:
    """The ``method`` layout (one of ``LAYOUTS``) of each frame's SD map, cropped to the frame: ``frames`` are
    (SD map, pose, driving side); one layout per SD map; ``crop``: :meth:`SceneCropper.extract`'s sizes."""
    croppers: dict[int, SceneCropper] = {}
    scenes = []
    for sd_map, pose, side in frames:
        if id(sd_map) not in croppers:
            croppers[id(sd_map)] = SceneCropper(LAYOUTS[method](sd_map, side))
        scenes.append(croppers[id(sd_map)].extract(pose, **crop))
    return scenes


def scene_layouts(data_dir, split: str, scenes, method: str, side: str | None = None) -> list[Scene]:
    """The ``method`` layout of each of the first scenes of a dataset split (in order) from the SD map its SD raster
    was drawn from, cropped as the dataset cropped the scene; ``side``: drive on this side [default: the scene's
    city's]."""
    recipe = load_manifest(data_dir)["recipe"]
    crop = {k: recipe[k] for k in ("num_lines", "num_points", "num_lights", "frame_m", "min_piece_m")}
    frames = [(sd_map, s.pose, side or drives_on(s.city))
              for s, sd_map in zip(scenes, scene_sd_maps(data_dir, split))]
    return cropped_layouts(frames, method, **crop)


def layout_raster(scene: Scene, size: int = 128, width_m: float = 1.0) -> np.ndarray:
    """The lanes of a layout's scene as ``(size, size, LAYOUT_CHANNELS)`` uint8 over its frame: each lane pixel
    holds its heading h as ``255 * (0.5 (cos h, sin h) + 0.5)``, the background 0 (the HD raster's lane
    channels, quantised). The channels a ControlMap with ``control.layout`` reads after the SD raster's."""
    canvas = np.zeros((size, size, LAYOUT_CHANNELS), np.float32)
    px_m = scene.frame_m / size
    draw_direction_lines(canvas, scene.lines[scene.line_mask.astype(bool)], px_m, scene.frame_m,
                         max(1, round(width_m / px_m)))
    return np.round(canvas * 255.0).astype(np.uint8)


def scene_layout_rasters(data_dir, split: str, scenes, method: str, side: str | None = None) -> list[np.ndarray]:
    """:func:`layout_raster` of each scene's :func:`scene_layouts`."""
    return [layout_raster(lay, s.sd.shape[0]) for lay, s in
            zip(scene_layouts(data_dir, split, scenes, method, side=side), scenes)]


def control_raster(sd: np.ndarray, layout: np.ndarray | None) -> np.ndarray:
    """A ControlMap's control image: the SD raster (H, W, 3) with the layout's channels after it (zeros for no
    layout, as for an SD picture, which has no map to lay lanes out on)."""
    if layout is None:
        layout = np.zeros((*sd.shape[:2], LAYOUT_CHANNELS), np.uint8)
    return np.concatenate([sd, layout], axis=-1)
