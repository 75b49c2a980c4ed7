"""The ``[data]`` section of a recipe: which maps a dataset is built from, how many scenes, and the
scene and raster geometry (read with the rest of a recipe by :func:`cmtool.train.recipe.load_recipe`)."""

from __future__ import annotations

import glob
import math
from dataclasses import dataclass, field
from pathlib import Path

from cmtool.core.errors import CmtoolError
from cmtool.core.memory import check_fits
from cmtool.data.frames import KINDS, FrameMix
from cmtool.data.sd_jitter import SDJitter
from cmtool.data.sd_raster import SIZE as SD_SIZE
from cmtool.formats.importers import FORMATS as IMPORT_FORMATS

REAL_MAP_FORMATS = (*IMPORT_FORMATS, "hdmap")  # hdmap: cmtool's own HD map JSON (`data import`, `data synth`)


MAX_EXTENT_M = 20_000.0  # the side of the largest procedural city (`data synth --extent` allows as much)

@dataclass
class RealMapsRecipe:
    """Real HD maps to import: every file matching ``path`` becomes one work unit."""

    format: str  # one of REAL_MAP_FORMATS
    path: str  # file or glob, relative to the recipe's folder (or the current folder)
    split: str = "train"
    city: str | None = None  # city label; None keeps the importer's
    scenes_per_map: int | None = None  # None: the data recipe's scenes_per_map


@dataclass
class DataRecipe:
    """The scene data set: which maps, how many scenes, and the scene/raster geometry."""

    name: str = "data"
    seed: int = 0
    train_cities: list[str] = field(default_factory=lambda: ["LAV", "PIT", "SGP"])
    test_cities: list[str] = field(default_factory=lambda: ["BOS"])
    maps_per_city: int = 4  # procedural maps per train city
    test_maps_per_city: int = 1  # procedural maps per test city
    scenes_per_map: int = 250
    extent: float = 800.0  # side of each procedural city (m)
    px_m: float = 0.5  # HD raster pixel size (m): 0.5 -> 128 px, 0.25 -> 256 px
    frame_m: float = 64.0  # scene square side (m)
    num_lines: int = 50  # lane pieces kept per scene, nearest first (SLEDGE: 50); the build counts those cut
    num_points: int = 20
    num_lights: int = 10  # per light state (green, red)
    min_piece_m: float = 2.0  # clipped lane pieces shorter than this are dropped
    min_pose_spacing_m: float = 16.0  # ego poses of one map are kept this far apart when possible
    shard_size: int = 250  # scenes per shard file
    frame_mix: FrameMix = field(default_factory=FrameMix)  # shares of the frame kinds (cmtool.data.frames)
    sd_jitter: SDJitter = field(default_factory=SDJitter)  # OSM-like imperfections of the SD maps (default: off)
    real_maps: list[RealMapsRecipe] = field(default_factory=list)

    def check(self, where: str) -> None:
        """Reject values that are well-typed but meaningless."""
        positive = ("extent", "px_m", "frame_m", "num_lines", "num_points", "shard_size")
        for key in positive:
            if getattr(self, key) <= 0:
                raise CmtoolError(f"{where}: data.{key}: must be positive, got {getattr(self, key)}")
        for key in ("maps_per_city", "test_maps_per_city", "scenes_per_map", "num_lights", "min_piece_m"):
            if getattr(self, key) < 0:
                raise CmtoolError(f"{where}: data.{key}: must not be negative, got {getattr(self, key)}")
        if not 100 <= self.extent <= MAX_EXTENT_M:
            raise CmtoolError(f"{where}: data.extent: must be within [100, {MAX_EXTENT_M:.0f}] m, got {self.extent}")
        per_scene = 4 * 2 * self.num_points * (self.num_lines + 2 * self.num_lights) + 3 * SD_SIZE**2
        check_fits(3 * per_scene * max(self.scenes_per_map, 1),
                   f"{where}: data: {self.scenes_per_map} scenes per map of {self.num_lines} lines and "
                   f"{2 * self.num_lights} light lines of {self.num_points} points each")
        if (self.frame_m / self.px_m) % 1:
            raise CmtoolError(f"{where}: data.px_m: frame_m / px_m must be a whole number of pixels")
        both = sorted(set(self.train_cities) & set(self.test_cities))
        if both:
            raise CmtoolError(f"{where}: data.test_cities: {both} also in train_cities (splits are by city)")
        for problem in self.sd_jitter.problems():
            raise CmtoolError(f"{where}: data.sd_jitter.{problem}")
        shares = self.frame_mix.as_dict()
        bad = [k for k, v in shares.items() if not (math.isfinite(v) and v >= 0)]
        if bad or sum(shares.values()) <= 0:
            raise CmtoolError(f"{where}: data.frame_mix: shares of {', '.join(KINDS)} must be finite, >= 0 and not "
                              "all 0" + (f" ({bad[0]} = {shares[bad[0]]})" if bad else ""))
        for i, rm in enumerate(self.real_maps):
            if rm.format not in REAL_MAP_FORMATS:
                raise CmtoolError(f"{where}: data.real_maps[{i}].format: expected one of {REAL_MAP_FORMATS}, "
                                  f"got {rm.format!r}")

    def real_map_files(self, recipe_path: Path | None = None) -> list[tuple[RealMapsRecipe, Path]]:
        """Every real-map file of ``real_maps`` (sorted within each entry): paths relative to the folder of the
        recipe file ``recipe_path``, else to the current folder."""
        bases = ([recipe_path.parent] if recipe_path else []) + [Path.cwd()]
        out = []
        for i, rm in enumerate(self.real_maps):
            for base in bases:
                hits = sorted(glob.glob(str(base / rm.path)))
                if hits:
                    out += [(rm, Path(h)) for h in hits]
                    break
            else:
                raise CmtoolError(f"{recipe_path or 'recipe'}: data.real_maps[{i}].path: no file matches {rm.path!r}")
        return out
