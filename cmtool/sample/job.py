"""What every step of ``cmtool sample`` works on: the run's settings (:class:`SampleSettings`), one map to make
(:class:`Job`) and one map made (:class:`SampledMap`). The driver (:mod:`cmtool.sample.run`) plans the jobs and
hands them to the steps (checks, files, pool, scores), which import only this module of the run's."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from cmtool.data.scene import Scene
from cmtool.diffusion.settings import SamplerSettings, SamplingError
from cmtool.maps.lanegraph import LaneGraph
from cmtool.sample import DEFAULT_COUNTS
from cmtool.sample.compose import check_counts
from cmtool.sample.inputs import ControlInput
from cmtool.sample.layouts import NO_INIT, check_init

AUTO = "auto"  # --city default: the source map's city when the checkpoint knows it, else none


@dataclass(kw_only=True)
class SampleSettings(SamplerSettings):
    """``cmtool sample``'s settings: the sampler's, and how many maps per input, the city label and its guidance."""

    num: int = 1
    eta: float = 0.0
    city: str = AUTO  # a label of the checkpoint, "none", or "auto"
    city_cfg: float = 1.0  # guidance on the city label (1: the label as trained)
    init: str = NO_INIT  # start from this rule-based layout of the input (cmtool.sample.layouts), encoded
    strength: float = 1.0  # with init: how far up the noise schedule the layout is noised before denoising
    guarantee: bool = True  # each map composed from its SD map (cmtool.sample.guarantee)
    lane_counts: str = DEFAULT_COUNTS  # where an untagged road's lane counts come from (cmtool.sample.compose)
    candidates: int = 1  # maps drawn per map asked for; the best (:func:`~cmtool.sample.scores.choose`) is kept

    def check(self, prefix: str = "--") -> None:
        super().check(prefix)
        check_init(self.init, self.strength, prefix)
        check_counts(self.lane_counts, prefix)
        if not (math.isfinite(self.city_cfg) and self.city_cfg >= 0):
            raise SamplingError(f"{prefix}city-cfg: guidance weight must be a finite number >= 0, got {self.city_cfg}")
        if self.num < 1:
            raise SamplingError(f"{prefix}num: must be at least 1, got {self.num}")
        if self.candidates < 1:
            raise SamplingError(f"{prefix}candidates: must be at least 1, got {self.candidates}")


@dataclass
class Job:
    """One map to generate: its name, input and label, and where it goes in the recording."""

    name: str
    source: ControlInput
    label: int
    index: int  # the map's number for this input (0 .. num-1)
    prefix: str = ""
    candidate: int = 0  # which of the --candidates drawn for this map (0 .. candidates-1)
    init: Scene | None = None  # the layout the map starts from (--init)
    layout: np.ndarray | None = None  # the layout raster the control branch reads (when it reads one)


@dataclass
class SampledMap:
    job: Job
    graph: LaneGraph
    seconds: float  # this map's share of the time its batch took (the maps' times add up to the run's)
