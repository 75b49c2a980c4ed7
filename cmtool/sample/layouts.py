"""Rule-based lane layouts of sampling inputs: ours (:mod:`cmtool.data.rules`) and SUMO's ``netconvert``
(:mod:`cmtool.formats.sumo`), of each input's SD map, cropped to its frame as a scene; the maps of ``cmtool
baseline`` and what ``cmtool sample --init rules`` starts from."""

from __future__ import annotations

import math

from cmtool.core.errors import CmtoolError
from cmtool.data.rules import rule_layout
from cmtool.diffusion.settings import SamplingError
from cmtool.data.scene import Pose, Scene, SceneCropper
from cmtool.formats.sumo import netconvert_layout
from cmtool.maps.hdmap import HDMap, drives_on
from cmtool.sample.inputs import ControlInput

LAYOUTS = {"rules": rule_layout, "netconvert": netconvert_layout}  # SD map, driving side -> HD map
NO_INIT = "none"  # --init default: sampling starts from noise alone


def check_init(init: str, strength: float, prefix: str = "--") -> None:
    """Reject an --init that names no layout and a --strength outside (0, 1]."""
    if init not in (NO_INIT, *LAYOUTS):
        raise SamplingError(f"{prefix}init: choose {NO_INIT}, {', '.join(LAYOUTS)}, got {init!r}")
    if not (math.isfinite(strength) and 0 < strength <= 1):
        raise SamplingError(f"{prefix}strength: must be in (0, 1], got {strength}")


def without_connectors(hd: HDMap) -> HDMap:
    """``hd`` without its connector lanes through junctions (in place), the road lanes' links to them dropped."""
    hd.lanes = {k: lane for k, lane in hd.lanes.items() if not lane.in_intersection}
    for lane in hd.lanes.values():
        lane.successors = [s for s in lane.successors if s in hd.lanes]
        lane.predecessors = [p for p in lane.predecessors if p in hd.lanes]
    return hd


def cropped_layouts(frames, method: str, roads_only: bool = False, **crop) -> list[Scene]:
    """The ``method`` layout (one of ``LAYOUTS``) of each frame's SD map, cropped to the frame: ``frames`` are
    (SD map, pose, driving side); one layout per SD map; ``roads_only``: without the connector lanes through
    junctions; ``crop``: :meth:`SceneCropper.extract`'s sizes."""
    croppers: dict[int, SceneCropper] = {}
    scenes = []
    for sd_map, pose, side in frames:
        if id(sd_map) not in croppers:
            hd = LAYOUTS[method](sd_map, side)
            croppers[id(sd_map)] = SceneCropper(without_connectors(hd) if roads_only else hd)
        scenes.append(croppers[id(sd_map)].extract(pose, **crop))
    return scenes


def layout_scenes(inputs: list[ControlInput], method: str, side: str | None = None,
                  roads_only: bool = False) -> list[Scene]:
    """:func:`cropped_layouts` of sampling inputs; ``side``: the driving side [default: the input's city's]."""
    for item in inputs:
        if item.sd_map is None or item.pose is None:
            raise CmtoolError(f"{item.name}: {method} needs an SD map, not a picture: give --osm or --from-hd")
    return cropped_layouts([(item.sd_map, Pose(*item.pose), side or drives_on(item.city)) for item in inputs],
                           method, roads_only)
