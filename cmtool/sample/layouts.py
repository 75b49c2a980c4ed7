"""Rule-based lane layouts (:mod:`cmtool.data.layouts`) of sampling inputs, each input's SD map cropped to its
frame as a scene: the maps of ``cmtool baseline``, what ``cmtool sample --init rules`` starts from and the
layout channels of a ControlMap that reads them."""

from __future__ import annotations

import math

from cmtool.core.errors import CmtoolError
from cmtool.data.layouts import LAYOUTS, cropped_layouts
from cmtool.data.scene import Pose, Scene
from cmtool.diffusion.settings import SamplingError
from cmtool.maps.hdmap import drives_on
from cmtool.sample.inputs import ControlInput

NO_INIT = "none"  # --init default: sampling starts from noise alone


def check_init(init: str, strength: float, prefix: str = "--") -> None:
    """Reject an --init that names no layout and a --strength outside (0, 1]."""
    if init not in (NO_INIT, *LAYOUTS):
        raise SamplingError(f"{prefix}init: choose {NO_INIT}, {', '.join(LAYOUTS)}, got {init!r}")
    if not (math.isfinite(strength) and 0 < strength <= 1):
        raise SamplingError(f"{prefix}strength: must be in (0, 1], got {strength}")


def layout_scenes(inputs: list[ControlInput], method: str, side: str | None = None) -> list[Scene]:
    """:func:`cropped_layouts` of sampling inputs; ``side``: the driving side [default: the input's city's]."""
    for item in inputs:
        if item.sd_map is None or item.pose is None:
            raise CmtoolError(f"{item.name}: {method} needs an SD map, and no roads could be traced in the picture: "
                              "give --osm or --from-hd")
    return cropped_layouts([(item.sd_map, Pose(*item.pose), side or drives_on(item.city)) for item in inputs],
                           method)
