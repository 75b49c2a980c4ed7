"""Rule-based lane layouts of sampling inputs: ours (:mod:`cmtool.data.rules`) and SUMO's ``netconvert``
(:mod:`cmtool.formats.sumo`), of each input's SD map, cropped to its frame as a scene; the maps of ``cmtool
baseline`` and what ``cmtool sample --init rules`` starts from."""

from __future__ import annotations

from cmtool.core.errors import CmtoolError
from cmtool.data.rules import rule_layout
from cmtool.data.scene import Pose, Scene, SceneCropper
from cmtool.formats.sumo import netconvert_layout
from cmtool.maps.hdmap import HDMap, drives_on
from cmtool.sample.inputs import ControlInput

LAYOUTS = {"rules": rule_layout, "netconvert": netconvert_layout}  # SD map, driving side -> HD map


def without_connectors(hd: HDMap) -> HDMap:
    """``hd`` without its connector lanes through junctions (in place), the road lanes' links to them dropped."""
    hd.lanes = {k: lane for k, lane in hd.lanes.items() if not lane.in_intersection}
    for lane in hd.lanes.values():
        lane.successors = [s for s in lane.successors if s in hd.lanes]
        lane.predecessors = [p for p in lane.predecessors if p in hd.lanes]
    return hd


def layout_scenes(inputs: list[ControlInput], method: str, side: str | None = None,
                  roads_only: bool = False) -> list[Scene]:
    """The ``method`` layout (one of ``LAYOUTS``) of each input's SD map, cropped to its frame (one layout per SD
    map); ``side``: the driving side [default: the input's city's]; ``roads_only``: without the connector lanes
    through junctions."""
    croppers: dict[int, SceneCropper] = {}
    scenes = []
    for item in inputs:
        if item.sd_map is None or item.pose is None:
            raise CmtoolError(f"{item.name}: {method} needs an SD map, not a picture: give --osm or --from-hd")
        if id(item.sd_map) not in croppers:
            hd = LAYOUTS[method](item.sd_map, side or drives_on(item.city))
            croppers[id(item.sd_map)] = SceneCropper(without_connectors(hd) if roads_only else hd)
        scenes.append(croppers[id(item.sd_map)].extract(Pose(*item.pose)))
    return scenes
