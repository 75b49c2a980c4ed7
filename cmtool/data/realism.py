"""How close the SD maps the models train on come to real OpenStreetMap: per-frame statistics of map
files and of a data recipe's derived maps, side by side (``cmtool data frames``).

A map file (OpenStreetMap, SD or HD map JSON) is framed as ``cmtool data poses`` frames it. A recipe
gives one column per city style: its procedural maps, framed and made to look like OpenStreetMap
exactly as ``cmtool data build`` does (poses on the derived SD map in the recipe's mix of frame
kinds, statistics on the jittered SD map the model sees), plus ``derived``, all of them together.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cmtool.core.errors import CmtoolError
from cmtool.data.cache import framed
from cmtool.data.frames import SHARE_ROWS, STAT_ROWS, Frame, FrameSampler, frame_stats, read_sd_source
from cmtool.data.recipe import DataRecipe
from cmtool.data.sd_derive import derive_sd
from cmtool.data.sd_raster import rasterize_sd
from cmtool.maps.sdmap import SDMap


@dataclass
class Column:
    """Frames of one source: the SD maps as the model sees them and the frames on each."""

    name: str
    maps: list[SDMap]
    frames: list[list[Frame]]

    def stats(self, frame_m: float = 64.0) -> dict:
        return merge_stats([frame_stats(sd, [f.pose for f in frames], frame_m=frame_m)
                            for sd, frames in zip(self.maps, self.frames)])

    def rasters(self, k: int, frame_m: float = 64.0) -> list[tuple[np.ndarray, str]]:
        """The SD rasters of ``k`` frames, taken in turn from each map, with their labels."""
        longest = max(map(len, self.frames), default=0)
        rows = [(sd, frames[d]) for d in range(longest) for sd, frames in zip(self.maps, self.frames)
                if d < len(frames)]
        return [(rasterize_sd(sd, f.pose.x, f.pose.y, f.pose.yaw, frame_m=frame_m), f.label) for sd, f in rows[:k]]


def file_column(path, n: int, seed: int = 0) -> Column:
    """``n`` frames of a map file, as ``cmtool data poses`` picks them."""
    sd = read_sd_source(path)
    if not sd.roads:
        raise CmtoolError(f"{path}: no drivable roads in the map")
    frames = FrameSampler(sd).sample(n, np.random.default_rng(seed))
    return Column(Path(path).name.split(".")[0], [sd], [frames])


def recipe_columns(data: DataRecipe, maps: int, seed: int = 0, where: str = "recipe") -> list[Column]:
    """Per city style of a recipe's ``data`` section (read from ``where``), ``maps`` of its procedural maps with
    the recipe's scenes per map, framed and jittered as the dataset build does; then all of them as ``derived``."""
    from cmtool.data.synth import generate_city

    cities = list(dict.fromkeys(data.train_cities + data.test_cities))
    if not cities:
        raise CmtoolError(f"{where}: the recipe has no procedural city styles")
    columns = []
    for c, city in enumerate(cities):
        col = Column(city, [], [])
        for m in range(maps):
            map_seed = data.seed * 100_000 + m
            sd = derive_sd(generate_city(city, seed=map_seed, extent=data.extent))
            control, frames = framed(sd, data, data.scenes_per_map, map_seed * 10_000 + c,
                                     np.random.default_rng([seed, c, m]))
            col.frames.append(frames)
            col.maps.append(control)
        columns.append(col)
    columns.append(Column("derived", [sd for col in columns for sd in col.maps],
                          [f for col in columns for f in col.frames]))
    return columns


def merge_stats(parts: list[dict]) -> dict:
    """Statistics of several :func:`frame_stats` results taken together (counts per frame weighted by
    frames, shares by road length)."""
    frames = np.array([p["frames"] for p in parts], float)
    metres = frames * np.array([p["road_m"] for p in parts])
    out = {"frames": int(frames.sum())}
    for key in STAT_ROWS:
        weights = metres if key in SHARE_ROWS else frames
        out[key] = float(np.average([p[key] for p in parts], weights=weights)) if weights.sum() > 0 else 0.0
    return out


def stats_table(columns: dict[str, dict]) -> str:
    """Rows of :data:`STAT_ROWS` (and frames), one column per source, as aligned text."""
    names = list(columns)
    width = max(len(k) for k in STAT_ROWS)
    lines = [f"{'per 64 m frame':<{width}}  " + "  ".join(f"{n:>12}" for n in names)]
    lines.append(f"{'frames':<{width}}  " + "  ".join(f"{columns[n]['frames']:>12d}" for n in names))
    for key in STAT_ROWS:
        lines.append(f"{key:<{width}}  " + "  ".join(f"{columns[n][key]:>12.3f}" for n in names))
    return "\n".join(lines)
