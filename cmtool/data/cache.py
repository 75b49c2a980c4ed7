"""The dataset cache: scene vectors + SD rasters, built from a recipe into sharded ``.npz`` files.

A build is a list of work units: one procedural city map ``(city, seed)`` or one real map file,
each cropped into ``scenes_per_map`` scenes. A unit's content depends only on the recipe and its
index, so builds are deterministic whatever the worker count, and resumable: every shard is
written atomically (temporary file, then rename) and a re-run skips the shards already there.
Splits are by city, as in the ControlMap paper (train LAV, PIT, SGP; test BOS); real maps go to
the split their recipe entry names.

Layout of ``out_dir``::

    manifest.json             format, recipe echo, units, city labels, splits -> shards, counts, line cap
                              cuts and the mix of frame kinds
    <split>/u00003_00.npz     scenes of unit 3, part 0 (at most shard_size scenes)
    <split>/u00003_sd.json    the SD map (cmtool.sdmap) its scenes' SD rasters were drawn from, as jittered

Shard arrays (S scenes; L lines, K lights, P points): ``lines`` float32 (S, L, P, 2),
``line_mask`` bool (S, L), ``edges`` int32 (E, 2) flat with ``edge_offsets`` int64 (S + 1,),
``green``/``red`` float32 (S, K, P, 2) with ``green_mask``/``red_mask`` bool (S, K), ``sd`` uint8
(S, 128, 128, 3), ``city`` and ``source`` strings (S,), ``pose`` float64 (S, 3) world x, y, yaw, ``cut``
int32 (S,) lane pieces dropped by the ``num_lines`` cap, ``kind`` and ``tags`` strings (S,) what the frame
shows (:mod:`cmtool.data.frames`); shards built before these three were stored read as 0 and "".
A split's ``line_cap`` in the manifest (and the build's summary) counts the scenes the cap cut and the
lane pieces it dropped, in all and per source (``"procedural LAV"``, or a real map's ``"av2:<file>"``);
its ``frames`` count the scenes per frame kind and tag.
HD rasters are not stored: :func:`cmtool.data.hd_raster.rasterize_scene` draws them on the fly
at the manifest's ``px_m``.
"""

from __future__ import annotations

import json
import os
import re
import time
import zipfile
from collections import Counter
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from cmtool.core.errors import CmtoolError
from cmtool.core.jsonio import atomic_open, read_json, write_json
from cmtool.core.progress import Progress
from cmtool.core.workers import pool
from cmtool.data.frames import label_order
from cmtool.data.recipe import DataRecipe
from cmtool.data.scene import Pose, Scene, SceneCropper
from cmtool.data.sd_raster import ENCODING
from cmtool.maps.sdmap import SDMap

FORMAT = "cmtool.dataset"
SD_SIZE = 128
_ARRAYS = ("lines", "line_mask", "edges", "edge_offsets", "green", "green_mask", "red", "red_mask",
           "sd", "city", "source", "pose", "cut", "kind", "tags")
_LATER = {"cut": 0, "kind": "", "tags": ""}  # arrays added after the first format, and their value in old shards


@dataclass(frozen=True)
class WorkUnit:
    """One map to crop scenes from: procedural (``fmt == "procedural"``) or a real map file."""

    index: int
    split: str
    fmt: str
    city: str | None
    seed: int
    path: str | None
    scenes: int

    def shard_files(self, shard_size: int) -> list[str]:
        parts = max(1, -(-self.scenes // shard_size))
        return [f"{self.split}/u{self.index:05d}_{p:02d}.npz" for p in range(parts)]

    def sd_file(self) -> str:
        return sd_file(self.split, self.index)


def sd_file(split: str, index: int) -> str:
    """The SD map file of unit ``index`` in ``split``."""
    return f"{split}/u{index:05d}_sd.json"


def plan_units(recipe) -> list[WorkUnit]:
    """The work units of a recipe, in a fixed order (train cities, test cities, real maps)."""
    data = recipe.data
    units: list[WorkUnit] = []
    for split, cities, per_city in (("train", data.train_cities, data.maps_per_city),
                                    ("test", data.test_cities, data.test_maps_per_city)):
        for city in cities:
            for m in range(per_city):
                units.append(WorkUnit(len(units), split, "procedural", city, data.seed * 100_000 + m, None,
                                      data.scenes_per_map))
    for rm, path in recipe.real_map_files():
        scenes = data.scenes_per_map if rm.scenes_per_map is None else rm.scenes_per_map
        units.append(WorkUnit(len(units), rm.split, rm.format, rm.city, data.seed, str(path.resolve()), scenes))
    return units


def unit_scenes(unit: WorkUnit, data: DataRecipe) -> tuple[list[Scene], SDMap]:
    """Make the map of ``unit`` and crop its scenes, framed on its derived SD map in the recipe's mix of
    frame kinds, each paired with the SD raster of that map made to look like OpenStreetMap; and that SD map."""
    from cmtool.data.sd_derive import derive_sd
    from cmtool.data.sd_raster import rasterize_sd

    if unit.fmt == "procedural":
        from cmtool.data.synth import generate_city

        hd = generate_city(unit.city, seed=unit.seed, extent=data.extent)
    elif unit.fmt == "hdmap":
        from cmtool.formats.mapfile import read_hd_map

        hd = read_hd_map(unit.path)
        hd.city = unit.city or hd.city
    else:
        from cmtool.formats.importers import import_hd_map

        hd = import_hd_map(unit.fmt, unit.path, city=unit.city)
    control, frames = framed(derive_sd(hd), data, unit.scenes, unit.seed * 10_000 + unit.index,
                             np.random.default_rng([data.seed, unit.index]))
    cropper = SceneCropper(hd)
    scenes = []
    for frame in frames:
        pose = frame.pose
        scene = cropper.extract(pose, data.num_lines, data.num_points, data.num_lights, data.frame_m, data.min_piece_m)
        scene.sd = rasterize_sd(control, pose.x, pose.y, pose.yaw, frame_m=data.frame_m, size=SD_SIZE)
        scene.kind, scene.tags = frame.label, ",".join(frame.tags)
        scenes.append(scene)
    return scenes, control


def framed(sd, data: DataRecipe, n: int, jitter_seed: int, rng: np.random.Generator) -> tuple:
    """The SD map the model sees (``sd`` jittered as the recipe says) and ``n`` frames on ``sd`` in the
    recipe's mix, none on a road the jitter dropped."""
    from cmtool.data.frames import FrameSampler
    from cmtool.data.sd_jitter import apply_jitter

    control = apply_jitter(sd, data.sd_jitter, jitter_seed) if data.sd_jitter.enabled else sd
    kept = {r.id for r in control.roads}
    roads = {k for k, r in enumerate(sd.roads) if r.id in kept}
    frames = FrameSampler(sd, data.frame_m).sample(n, rng, data.frame_mix.as_dict(), data.min_pose_spacing_m,
                                                   roads=roads)
    return control, frames


def pack_scenes(scenes: list[Scene]) -> dict[str, np.ndarray]:
    """Stack scenes into shard arrays (see the module docstring)."""
    counts = [len(s.edges) for s in scenes]
    return {
        "lines": np.stack([s.lines for s in scenes]).astype(np.float32),
        "line_mask": np.stack([s.line_mask for s in scenes]),
        "edges": np.concatenate([s.edges for s in scenes]).astype(np.int32).reshape(-1, 2),
        "edge_offsets": np.concatenate([[0], np.cumsum(counts)]).astype(np.int64),
        "green": np.stack([s.green for s in scenes]).astype(np.float32),
        "green_mask": np.stack([s.green_mask for s in scenes]),
        "red": np.stack([s.red for s in scenes]).astype(np.float32),
        "red_mask": np.stack([s.red_mask for s in scenes]),
        "sd": np.stack([s.sd for s in scenes]).astype(np.uint8),
        "city": np.array([s.city for s in scenes], dtype=str),
        "source": np.array([s.source for s in scenes], dtype=str),
        "pose": np.stack([s.pose.as_array() for s in scenes]),
        "cut": np.array([s.cut for s in scenes], np.int32),
        "kind": np.array([s.kind for s in scenes], dtype=str),
        "tags": np.array([s.tags for s in scenes], dtype=str),
    }


def _write_npz(path: Path, arrays: dict) -> None:
    with atomic_open(path, "wb") as fh:
        np.savez_compressed(fh, **arrays)


def _build_unit(job) -> tuple[int, int]:
    """Worker: write the missing shards of one unit; returns (unit index, scenes made)."""
    unit, data, out_dir = job
    scenes, control = unit_scenes(unit, data)
    if not scenes:
        raise CmtoolError(f"{unit.path or unit.city}: no roads to frame scenes on")
    for p, name in enumerate(unit.shard_files(data.shard_size)):
        path = out_dir / name
        if not path.exists():
            _write_npz(path, pack_scenes(scenes[p * data.shard_size:(p + 1) * data.shard_size]))
    control.save(out_dir / unit.sd_file())
    return unit.index, len(scenes)


def build_dataset(recipe, out_dir, workers: int | None = None, progress: bool = True) -> dict:
    """Build (or finish building) the dataset of a loaded recipe (:func:`cmtool.train.recipe.load_recipe`: its
    ``data`` section and real-map files) into ``out_dir``; returns a summary:
    ``{"splits": {split: {"scenes": n, "cities": {city: n}, "line_cap": cuts, "frames": mix}}, "num_lines",
    "units_built", "units_skipped", "scenes_built", "seconds"}`` with ``cuts`` and ``mix`` as :func:`_count`
    counts them."""
    start = time.perf_counter()
    data = recipe.data
    out_dir = Path(out_dir)
    units = plan_units(recipe)
    head = {
        "format": FORMAT, "version": 1, "recipe": _plain(asdict(data)),
        "px_m": data.px_m, "frame_m": data.frame_m, "sd_size": SD_SIZE, "sd_encoding": ENCODING,
        "units": [_plain(asdict(u)) | {"shards": u.shard_files(data.shard_size)} for u in units],
    }
    manifest_path = out_dir / "manifest.json"
    if manifest_path.exists():
        old = read_json(manifest_path)
        if not isinstance(old, dict) or any(old.get(k) != v for k, v in head.items()):
            raise CmtoolError(f"{out_dir}: holds a dataset built from a different recipe "
                              f"({old.get('recipe', {}).get('name', '?') if isinstance(old, dict) else '?'}); "
                              "choose another output folder")
    elif out_dir.exists() and any(out_dir.iterdir()):
        raise CmtoolError(f"{out_dir}: exists and is not a cmtool dataset; choose an empty or new folder")
    write_json(manifest_path, head | {"complete": False})
    for split in {u.split for u in units}:
        (out_dir / split).mkdir(parents=True, exist_ok=True)
        for stale in (out_dir / split).glob(".*.tmp"):
            stale.unlink()

    pending = [u for u in units if not all((out_dir / f).exists() for f in [*u.shard_files(data.shard_size),
                                                                             u.sd_file()])]
    jobs = [(u, data, out_dir) for u in pending]
    workers = min(2, os.cpu_count() or 1) if workers is None else max(1, workers)
    bar = Progress(sum(u.scenes for u in pending), label=f"build {data.name}", unit="scenes", enabled=progress)
    with bar:
        if workers == 1 or len(jobs) <= 1:
            for job in jobs:
                bar.update(_build_unit(job)[1])
        else:
            with pool(min(workers, len(jobs))) as processes:
                for _, n in processes.imap_unordered(_build_unit, jobs):
                    bar.update(n)

    splits, labels = _count(out_dir, units, data.shard_size)
    labels = list(dict.fromkeys(data.train_cities + data.test_cities + labels))
    write_json(manifest_path, head | {"complete": True, "cities": labels, "splits": splits})
    return {
        "splits": {s: {k: v[k] for k in ("scenes", "cities", "line_cap", "frames")} for s, v in splits.items()},
        "num_lines": data.num_lines, "units_built": len(pending), "units_skipped": len(units) - len(pending),
        "scenes_built": bar.done, "seconds": round(time.perf_counter() - start, 2),
    }


def _count(out_dir: Path, units: list[WorkUnit], shard_size: int) -> tuple[dict, list[str]]:
    """Per split: shard files with scene counts, scenes per city, the line cap's cuts (read from the
    shards): ``{"scenes_cut", "pieces_cut", "sources": {source: {"scenes", "scenes_cut", "pieces_cut"}}}``,
    and the frames' mix: ``{"kinds": {kind: n}, "tags": {tag: n}}``."""
    splits: dict = {}
    labels: list[str] = []
    for u in units:
        entry = splits.setdefault(u.split, {"scenes": 0, "cities": {}, "shards": [],
                                            "line_cap": {"scenes_cut": 0, "pieces_cut": 0, "sources": {}},
                                            "frames": {"kinds": {}, "tags": {}}})
        for name in u.shard_files(shard_size):
            try:
                with np.load(out_dir / name) as z:
                    cities, sources, cut = z["city"].tolist(), z["source"].tolist(), _array(z, "cut").tolist()
                    kinds, tags = _array(z, "kind").tolist(), _array(z, "tags").tolist()
            except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as e:
                raise CmtoolError(f"{out_dir / name}: unreadable shard ({e}); delete it and re-run the build") from None
            entry["shards"].append({"file": name, "scenes": len(cities)})
            entry["scenes"] += len(cities)
            for city, n in Counter(cities).items():
                entry["cities"][city] = entry["cities"].get(city, 0) + n
                labels.append(city)
            for city, source, pieces in zip(cities, sources, cut):
                _tally(entry["line_cap"], source_label(source, city), pieces)
            frames = entry["frames"]
            for kind, n in Counter(k or "unknown" for k in kinds).items():
                frames["kinds"][kind] = frames["kinds"].get(kind, 0) + n
            for tag, n in Counter(t for row in tags for t in row.split(",") if t).items():
                frames["tags"][tag] = frames["tags"].get(tag, 0) + n
    for entry in splits.values():
        for key, counts in entry["frames"].items():
            entry["frames"][key] = {k: counts[k] for k in sorted(counts, key=label_order)}
    return splits, labels


def _tally(cap: dict, source: str, pieces: int) -> None:
    """Count one scene of ``source`` that lost ``pieces`` lane pieces to the line cap (maybe 0)."""
    row = cap["sources"].setdefault(source, {"scenes": 0, "scenes_cut": 0, "pieces_cut": 0})
    row["scenes"] += 1
    for tally in (cap, row):
        tally["scenes_cut"] += int(pieces > 0)
        tally["pieces_cut"] += pieces


def source_label(source: str, city: str) -> str:
    """A scene's source as the build reports it: ``"procedural LAV"`` for any procedural LAV map, else the map's."""
    return f"procedural {city}" if source.startswith("procedural:") else source


def _array(z, key: str) -> np.ndarray:
    """Array ``key`` of an open shard; for an array added later, its old value in a shard built before."""
    if key in z.files or key not in _LATER:
        return z[key]
    return np.full(len(z["city"]), _LATER[key], dtype=np.int32 if key == "cut" else str)


def _plain(obj):
    """JSON round trip, so in-memory values compare equal to those read back from a manifest."""
    return json.loads(json.dumps(obj))


# ---------------------------------------------------------------- reading


def load_manifest(data_dir) -> dict:
    """The manifest of a finished dataset folder."""
    path = Path(data_dir) / "manifest.json"
    if not path.is_file():
        raise CmtoolError(f"{data_dir}: not a dataset folder (no manifest.json); build one with `cmtool data build`")
    manifest = read_json(path)
    if not isinstance(manifest, dict) or manifest.get("format") != FORMAT:
        raise CmtoolError(f"{path}: not a cmtool dataset manifest")
    if not manifest.get("complete"):
        raise CmtoolError(f"{data_dir}: dataset build did not finish; run the build again to complete it")
    _check_shards(manifest, path)
    return manifest


_SHARD = re.compile(r"[A-Za-z0-9_-]+/u\d{5}_\d{2}\.npz")  # SPLIT/uUNIT_PART.npz (WorkUnit.shard_files)


def _check_shards(manifest: dict, path: Path) -> None:
    """Refuse a manifest whose splits list shards the build does not name (a path out of the folder, a file of
    another layout, one that no unit makes, or one listed twice)."""
    try:
        made = {name for u in manifest["units"] for name in u["shards"]}
        listed = [(shard["file"], shard["scenes"]) for split in manifest["splits"].values()
                  for shard in split["shards"]]
    except (KeyError, TypeError, AttributeError) as e:
        raise CmtoolError(f"{path}: damaged manifest ({type(e).__name__}: {e})") from None
    seen: set[str] = set()
    for name, scenes in listed:
        if not (isinstance(name, str) and _SHARD.fullmatch(name) and name in made and name not in seen) \
                or not isinstance(scenes, int) or scenes < 0:
            raise CmtoolError(f"{path}: damaged manifest: shard {str(name)[:80]!r} is not one of the shards its units "
                              f"make (or is listed twice)")
        seen.add(name)


@dataclass
class SceneDataset:
    """The scenes of one split (or all), as arrays concatenated over shards (see module doc)."""

    arrays: dict[str, np.ndarray]
    cities: list[str]  # the manifest's city labels
    frame_m: float
    px_m: float

    def __len__(self) -> int:
        return len(self.arrays["lines"])

    def __getattr__(self, name):
        if name in _ARRAYS:
            return self.arrays[name]
        raise AttributeError(name)

    @property
    def city_index(self) -> np.ndarray:
        """Each scene's city as an index into :attr:`cities` (int64)."""
        lookup = {c: i for i, c in enumerate(self.cities)}
        return np.array([lookup[c] for c in self.arrays["city"].tolist()], np.int64)

    def scene(self, i: int) -> Scene:
        a = self.arrays
        e0, e1 = a["edge_offsets"][i], a["edge_offsets"][i + 1]
        return Scene(
            lines=a["lines"][i], line_mask=a["line_mask"][i], edges=a["edges"][e0:e1].astype(np.int64),
            green=a["green"][i], green_mask=a["green_mask"][i], red=a["red"][i], red_mask=a["red_mask"][i],
            city=str(a["city"][i]), source=str(a["source"][i]), pose=Pose(*map(float, a["pose"][i])),
            frame_m=self.frame_m, sd=a["sd"][i], cut=int(a["cut"][i]), kind=str(a["kind"][i]), tags=str(a["tags"][i]),
        )

    def __iter__(self):
        return (self.scene(i) for i in range(len(self)))


class MissingSDMaps(CmtoolError):
    """A dataset built before its SD maps were stored beside its shards."""


def scene_sd_maps(data_dir, split: str) -> list[SDMap]:
    """The SD map of each scene of ``split``, in :func:`load_dataset`'s order (scenes of one unit share one)."""
    manifest = load_manifest(data_dir)
    if split not in manifest["splits"]:
        raise CmtoolError(f"{data_dir}: no split {split!r} (has {', '.join(manifest['splits'])})")
    unit_of = {name: u["index"] for u in manifest["units"] for name in u["shards"]}
    maps: dict[str, SDMap] = {}
    out = []
    for shard in manifest["splits"][split]["shards"]:
        name = sd_file(split, unit_of[shard["file"]])
        if name not in maps:
            path = Path(data_dir) / name
            if not path.is_file():
                raise MissingSDMaps(f"{path}: no SD map; this dataset was built before they were stored: run "
                                  "`cmtool data build` on it again to add them")
            maps[name] = SDMap.load(path)
        out += [maps[name]] * shard["scenes"]
    return out


def shard_paths(data_dir, split: str | None = None) -> list[Path]:
    """Shard files of a split (all splits when None), in manifest order."""
    return _shard_paths(load_manifest(data_dir), data_dir, split)


def _shard_paths(manifest: dict, data_dir, split: str | None) -> list[Path]:
    splits = manifest["splits"]
    if split is not None and split not in splits:
        raise CmtoolError(f"{data_dir}: no split {split!r} (has {', '.join(splits)})")
    names = [s for name in ([split] if split else splits) for s in splits[name]["shards"]]
    return [Path(data_dir) / s["file"] for s in names]


def load_dataset(data_dir, split: str | None = None) -> SceneDataset:
    """Load all scenes of ``split`` (all splits when None) into memory."""
    manifest = load_manifest(data_dir)
    parts = []
    for path in _shard_paths(manifest, data_dir, split):
        try:
            with np.load(path) as z:
                parts.append({k: _array(z, k) for k in _ARRAYS})
        except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as e:
            raise CmtoolError(f"{path}: unreadable shard ({e}); delete it and re-run the build") from None
    if not parts:
        raise CmtoolError(f"{data_dir}: split {split!r} has no scenes")
    arrays = {k: np.concatenate([p[k] for p in parts]) for k in _ARRAYS if k != "edge_offsets"}
    sizes = np.array([len(p["edges"]) for p in parts])
    shift = np.repeat(np.concatenate([[0], np.cumsum(sizes)[:-1]]), [len(p["lines"]) for p in parts])
    arrays["edge_offsets"] = np.concatenate(
        [np.concatenate([p["edge_offsets"][:-1] for p in parts]) + shift, [sizes.sum()]]).astype(np.int64)
    return SceneDataset(arrays, manifest["cities"], manifest["frame_m"], manifest["px_m"])
