"""docs/own-data.md works as written: every ```sh block of the page runs, in order, in a fresh folder laid out as the
repository root, and makes the files it should.

The small case that stands in for the user's (the page calls these paths examples):

- ``my_maps/``: the files the page names, made here. Argoverse 2 JSON, Apollo binary protobuf and two Lanelet2 OSM
  maps written from procedural cities (the Lanelet2 ones by cmtool's exporter), the nuPlan GeoPackage of
  ``tests/nuplan_fixture.py``, and ``sample_data/town_bos.osm`` as the OpenStreetMap file. No ``../shared/data``.
- ``recipes/``: a copy of the repository's, shrunk by :data:`SMALL` (a few scenes per map, 2 training steps at batch
  4, 4 evaluation scenes) and :data:`TINY_CHAIN` (tiny models for the from-scratch chain; the control branch trained
  further keeps the shipped sizes, which it starts from).
- ``cmtool/weights``: a copy of the shipped weights, and ``cmtool`` on ``PATH`` a launcher that makes it the
  package's weights folder (``cmtool.model.release.BUNDLED``), so the page's ``cmtool pack`` without ``--out`` and
  its ``rm -r cmtool/weights`` change the copy, never the package.

Everything else runs as a user would type it (``bash -e``, one block at a time), each command on one thread
(``OMP_NUM_THREADS=1``: on 2 busy cores the whole test then takes a third less CPU time and about half the time).
"""

import json
import os
import re
import shutil
import stat
import subprocess
import sys
from pathlib import Path

import numpy as np

from tests.conftest import REPO

PAGE = REPO / "docs" / "own-data.md"
BLOCK = re.compile(r"^```(\w*)\n(.*?)^```", re.MULTILINE | re.DOTALL)

# recipe keys set small in the copy (`key = number` lines; every recipe file)
SMALL = {"maps_per_city": "1", "test_maps_per_city": "1", "scenes_per_map": "4", "extent": "300.0", "steps": "2",
         "batch_size": "4", "warmup_steps": "1", "ckpt_every": "2", "preview_every": "0", "workers": "0", "n": "4"}
# the models of the from-scratch chain (recipes/tiny-cpu/pipeline/*.toml), as tests/test_train.py sizes them
TINY_CHAIN = {"d_model": "32", "decoder_layers": "1", "heads": "2", "ffn": "64", "num_blocks": "2", "groups": "4",
              "widths": "[8, 8, 16, 16]"}

# per ```sh block of the page, in order: files (in the stand-in checkout) that must exist after it
MAKES = [
    ["runs/own/av2.json", "runs/own/town.json", "runs/own/nuplan.json", "runs/own/apollo.json",
     "runs/own/area_sd.json"],
    ["runs/own/data/manifest.json", "runs/own/own_test.png"],
    ["runs/own/controlnet/checkpoints/step_00000002/config.json", "runs/own/controlnet/train.rrd"],
    ["runs/own/chain/pipeline.json", "runs/own/chain/weights/controlmap/config.json",
     "runs/own/chain/eval/summary.md"],
    ["runs/own/eval-shipped/summary.md", "runs/own/eval-shipped/metrics.json", "runs/own/eval/summary.md",
     "runs/own/eval/gallery.png"],
    ["runs/own/weights/MANIFEST.json", "runs/own/poses.jsonl", "runs/own/maps/area_0.json"],
    ["runs/own/weights-shipped/MANIFEST.json", "cmtool/weights/MANIFEST.json"],
    ["cmtool/weights/rvae/config.json"],
    ["cmtool/weights/MANIFEST.json"],
]


def sh_blocks() -> list[str]:
    return [body for lang, body in BLOCK.findall(PAGE.read_text()) if lang == "sh"]


def test_every_command_of_the_page_is_in_a_block_this_test_runs():
    blocks = BLOCK.findall(PAGE.read_text())
    assert [lang for lang, _ in blocks] == ["sh"] * len(MAKES), "a new block: add what it makes to MAKES"
    for body in sh_blocks():
        for line in body.splitlines():
            assert line.startswith(("cmtool ", "cp ", "rm ")), f"a command this test does not expect: {line}"


def test_own_data_recipes_name_the_pages_files():
    """The recipes hold what the page says: a block per HD format under my_maps/, the held-out maps in own_test."""
    from cmtool.core.tables import read_toml

    blocks = read_toml(REPO / "recipes" / "own-data" / "data.toml")["data"]["real_maps"]
    assert {b["format"] for b in blocks} == {"av2", "lanelet2", "nuplan", "apollo"}
    assert all(b["path"].startswith("my_maps/") for b in blocks)
    assert [b["split"] for b in blocks if b.get("split", "train") != "train"] == ["own_test"]
    pipeline = read_toml(REPO / "recipes" / "own-data" / "pipeline.toml")["pipeline"]
    assert pipeline["data"] == "data.toml" and pipeline["eval"]["split"] == "own_test"


def _shrink(recipes: Path) -> None:
    key = re.compile(r"^(\w+)(\s*=\s*)([-+0-9.e]+|\[[^\]]*\])", re.MULTILINE)
    for path in recipes.rglob("*.toml"):
        small = dict(SMALL, **TINY_CHAIN) if path.parent == recipes / "tiny-cpu" / "pipeline" else SMALL
        text = key.sub(lambda m, small=small: m[1] + m[2] + small.get(m[1], m[3]), path.read_text())
        if path.parent == recipes / "tiny-cpu" / "pipeline":
            text = text.replace('size = "tiny"', 'size = "tiny"\ndepth = 2\nhidden = 32\nheads = 2')
        path.write_text(text)


def _offset(line: np.ndarray, d: float) -> np.ndarray:
    """``line`` moved ``d`` metres to its left."""
    seg = np.diff(line, axis=0)
    tangent = np.vstack([seg[:1], seg[:-1] + seg[1:], seg[-1:]])
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    return line + d * np.stack([-tangent[:, 1], tangent[:, 0]], 1)


def _write_av2(hd, path: Path) -> None:
    def points(line):
        return [{"x": float(x), "y": float(y), "z": 0.0} for x, y in line]

    segments = {lid: {"id": lid, "lane_type": "VEHICLE", "is_intersection": lane.is_intersection,
                      "left_lane_boundary": points(_offset(lane.centerline, lane.width / 2)),
                      "right_lane_boundary": points(_offset(lane.centerline, -lane.width / 2)),
                      "successors": lane.successors, "predecessors": lane.predecessors,
                      "left_neighbor_id": lane.left_neighbor, "right_neighbor_id": lane.right_neighbor}
                for lid, lane in hd.lanes.items()}
    path.write_text(json.dumps({"lane_segments": segments, "pedestrian_crossings": {}, "drivable_areas": {}}))


def _write_apollo(hd, path: Path) -> None:
    """Binary protobuf, as Apollo's base_map.bin: the lanes in UTM-like metres, no projection in the header."""
    from google.protobuf import text_format

    from cmtool.formats.importers.apollo import _map_class

    lanes = []
    for lid, lane in hd.lanes.items():
        curve = " ".join(f"point {{ x: {x + 5e5:.3f} y: {y + 4e6:.3f} }}" for x, y in lane.centerline)
        links = " ".join([f'successor_id {{ id: "{s}" }}' for s in lane.successors]
                         + [f'predecessor_id {{ id: "{p}" }}' for p in lane.predecessors])
        half = lane.width / 2
        lanes.append(f'lane {{ id {{ id: "{lid}" }} central_curve {{ segment {{ line_segment {{ {curve} }} }} }} '
                     f'type: CITY_DRIVING {links} left_sample {{ width: {half} }} '
                     f'right_sample {{ width: {half} }} }}')
    message = text_format.Parse("\n".join(lanes), _map_class()())
    path.write_bytes(message.SerializeToString())


def _write_lanelet2(hd, path: Path, lat0: float, lon0: float) -> None:
    from cmtool.formats.lanelet2_export import write_lanelet2
    from cmtool.maps.lanegraph import LaneGraph

    write_lanelet2(LaneGraph.from_hd(hd), path, lat0, lon0)


def _maps(root: Path) -> None:
    """The files under my_maps/ that the page and recipes/own-data/data.toml name."""
    from nuplan_fixture import build_gpkg

    from cmtool.data.synth import generate_city

    folders = {name: root / "my_maps" / name for name in ("av2", "lanelet2", "nuplan", "apollo", "osm", "held_out")}
    for folder in folders.values():
        folder.mkdir(parents=True)
    lav = generate_city("LAV", seed=1, extent=300)
    _write_av2(lav, folders["av2"] / "log_map_archive_0001____PIT_city_1.json")
    _write_apollo(lav, folders["apollo"] / "base_map.bin")
    _write_lanelet2(generate_city("PIT", seed=1, extent=300), folders["lanelet2"] / "town.osm", 40.44, -79.99)
    _write_lanelet2(generate_city("SGP", seed=2, extent=300), folders["held_out"] / "junctions.osm", 1.30, 103.8)
    build_gpkg(folders["nuplan"] / "map.gpkg")
    shutil.copy(REPO / "sample_data" / "town_bos.osm", folders["osm"] / "area.osm")


LAUNCHER = """\
import importlib.util, os, pathlib, sys


class Weights:
    \"\"\"Sets cmtool.model.release.BUNDLED when that module is imported (importing it here would import torch in
    every command, a second or two each).\"\"\"

    def find_spec(self, name, path, target=None):
        if name != "cmtool.model.release":
            return None
        sys.meta_path.remove(self)
        spec = importlib.util.find_spec(name)
        run = spec.loader.exec_module

        def exec_module(module):
            run(module)
            module.BUNDLED = pathlib.Path(os.environ["CMTOOL_OWN_DATA_WEIGHTS"])

        spec.loader.exec_module = exec_module
        return spec


sys.meta_path.insert(0, Weights())
if __name__ == "__main__":
    from cmtool.cli import main

    main()
"""


def _launcher(root: Path) -> Path:
    """bin/cmtool: the cmtool command with $CMTOOL_OWN_DATA_WEIGHTS as the package's weights folder."""
    bin_dir = root / "bin"
    bin_dir.mkdir()
    launcher = bin_dir / "cmtool"
    launcher.write_text(f"#!{sys.executable}\n" + LAUNCHER)
    launcher.chmod(launcher.stat().st_mode | stat.S_IXUSR)
    return bin_dir


def test_page_runs_on_a_small_case(tmp_path):
    root = tmp_path / "checkout"
    root.mkdir()
    shutil.copytree(REPO / "recipes", root / "recipes")
    _shrink(root / "recipes")
    shutil.copytree(REPO / "cmtool" / "weights", root / "cmtool" / "weights")
    _maps(root)
    env = dict(os.environ, PATH=f"{_launcher(tmp_path)}{os.pathsep}{os.environ['PATH']}",
               CMTOOL_OWN_DATA_WEIGHTS=str(root / "cmtool" / "weights"), OMP_NUM_THREADS="1")
    shipped = json.loads((REPO / "cmtool" / "weights" / "MANIFEST.json").read_text())

    blocks = sh_blocks()
    assert len(blocks) == len(MAKES)
    for k, (block, makes) in enumerate(zip(blocks, MAKES)):
        result = subprocess.run(["bash", "-e", "-c", block], cwd=root, env=env, capture_output=True, text=True,
                                timeout=600, check=False)
        assert result.returncode == 0, f"block {k + 1}:\n{block}\n{result.stdout[-3000:]}\n{result.stderr[-3000:]}"
        missing = [f for f in makes if not (root / f).exists()]
        assert not missing, f"block {k + 1} did not make {missing}:\n{block}"
        if k == 0:  # the imports and the validation of one
            assert "1 scenes, mean validity score" in result.stdout and "SD map" in result.stdout
        if k == 1:  # the held-out maps in their own split
            manifest = json.loads((root / "runs/own/data/manifest.json").read_text())
            assert manifest["splits"]["own_test"]["scenes"] > 0
            assert {"av2", "lanelet2", "nuplan", "apollo"} <= {u["fmt"] for u in manifest["units"]}
        if k == 5:
            assert len((root / "runs/own/poses.jsonl").read_text().splitlines()) == 4
        if k == 6:  # the package's folder now holds the trained branch, the shipped encoder kept
            manifest = json.loads((root / "cmtool/weights/MANIFEST.json").read_text())
            assert manifest["controlmap"].startswith("runs/own/controlnet/checkpoints/")
            assert "encoder" in manifest and "packed from   runs/own/controlnet" in result.stdout
            assert (manifest["files"]["rvae/model.safetensors"]["sha256"]
                    == shipped["files"]["rvae/model.safetensors"]["sha256"])
        if k == 7:  # or the chain's, with its own encoder
            manifest = json.loads((root / "cmtool/weights/MANIFEST.json").read_text())
            assert manifest["controlmap"].startswith("runs/own/chain/controlnet/checkpoints/")
            assert manifest["encoder"].startswith("runs/own/chain/rvae/checkpoints/")
            # the run of 4a, whose RVAE folder now holds the chain's, is refused, as the page says
            old = subprocess.run(["cmtool", "sample", "--ckpt", "runs/own/controlnet", "--sd",
                                  str(REPO / "sample_data" / "sd_lav.png"), "--steps", "2", "--no-log", "--quiet",
                                  "--out", "runs/own/old"], cwd=root, env=env, capture_output=True, text=True,
                                 timeout=600, check=False)
            assert old.returncode == 1 and "now holds others" in old.stderr, old.stderr
        if k == 8:  # and the shipped set back
            assert json.loads((root / "cmtool/weights/MANIFEST.json").read_text()) == shipped
    assert json.loads((REPO / "cmtool" / "weights" / "MANIFEST.json").read_text()) == shipped
