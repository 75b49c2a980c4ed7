"""Fault injection: every user-caused failure of every subcommand is one ``Error: ...`` line and a non-zero exit, never a
traceback, and leaves what was there before byte-identical.

Each case is a command line run in this process; ``{name}`` in it is a path of the workspace below (good inputs, bad
inputs, outputs that cannot be written). Output faults: a file in the way of a folder, a folder nobody may write
(``/sys``, refused even to root), and a full disk (``RLIMIT_FSIZE`` of 16 bytes for the run).
"""

from __future__ import annotations

import contextlib
import io
import json
import pickle
import resource
import shutil
import zipfile
from pathlib import Path

import numpy as np
import pytest

from tests.conftest import REPO, SHARED_DATA, interrupted_at

pytestmark = pytest.mark.usefixtures("one_thread")

AV2 = next(iter(sorted((SHARED_DATA / "av2").rglob("log_map_archive_*.json"))), None)
LANELET2 = next(iter(sorted((SHARED_DATA / "lanelet2").rglob("*.osm"))), None)
SD_PNG = REPO / "sample_data" / "sd_bos.png"
TOWN = REPO / "sample_data" / "town_bos.osm"
UNWRITABLE = "/sys/cmtool-test"  # mkdir and open fail with EACCES here, even for root
FULL_DISK = 16  # bytes a run may write per file


def cli(*args) -> tuple[int, str]:
    """Run ``cmtool ARGS`` in this process; (exit code, stderr). An exception other than SystemExit escapes."""
    from cmtool.cli import main

    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        try:
            main([str(a) for a in args])
            code = 0
        except SystemExit as e:
            code = e.code
    return code, err.getvalue()


@contextlib.contextmanager
def full_disk():
    """Files written inside may not grow past FULL_DISK bytes (writes fail with EFBIG, as on a full disk)."""
    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    resource.setrlimit(resource.RLIMIT_FSIZE, (FULL_DISK, hard))
    try:
        yield
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))


def snapshot(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def ws(tmp_path_factory, tiny_data):
    """The workspace: good inputs made by the CLI, and bad ones made from them."""
    root = tmp_path_factory.mktemp("faults")
    p = {"root": root, "data": tiny_data}

    def ok(*args):
        code, err = cli(*args)
        assert code == 0, err

    p["hd"] = root / "hd.json"
    ok("data", "synth", "--city", "BOS", "--seed", 1, "--extent", 300, "--out", p["hd"])
    p["sd"] = root / "sd.json"
    ok("data", "sd", p["hd"], "--out", p["sd"])
    ok("sample", "--from-hd", p["hd"], "--num", 2, "--steps", 2, "--no-log", "--quiet", "--out", root / "s")
    p["lg"] = root / "s" / "hd_s0.json"
    p["lgl"] = root / "maps.jsonl"
    p["lgl"].write_text("".join(json.dumps(json.loads((root / "s" / f"hd_s{k}.json").read_text())) + "\n"
                                for k in range(2)))
    p["gtl"] = root / "gt.jsonl"
    p["gtl"].write_text("".join(json.dumps(json.loads((root / "s" / f"hd_s{k}.gt.json").read_text())) + "\n"
                                for k in range(2)))
    p["afile"] = root / "afile"
    p["afile"].write_text("in the way\n")
    p["missing"] = root / "no-such-file.json"

    # unreadable text
    p["latin1"] = root / "latin1.jsonl"
    p["latin1"].write_bytes(p["lgl"].read_bytes()[:40] + b"\xe9\xff\xfe" + p["lgl"].read_bytes()[40:])
    p["truncated"] = root / "truncated.json"
    pretty = json.dumps(json.loads(p["lg"].read_text()), indent=2)
    p["truncated"].write_text(pretty[: len(pretty) // 2])
    p["truncated_hd"] = root / "truncated_hd.json"
    p["truncated_hd"].write_text(p["hd"].read_text()[:1000])
    p["empty"] = root / "empty.json"
    p["empty"].write_text("")
    p["binary"] = root / "binary.json"
    p["binary"].write_bytes(bytes(range(256)) * 4)

    # numbers out of range
    graph = json.loads(p["lg"].read_text())
    big = json.loads(p["lg"].read_text())
    p["bigint"] = root / "bigint.json"
    p["bigint"].write_text(json.dumps(big).replace(str(big["lanes"][0][0][0]), "9" * 400, 1))
    huge = json.loads(p["lg"].read_text())
    huge["lanes"] = [[[x * 1e300, y * 1e300] for x, y in lane] for lane in huge["lanes"]]
    p["huge"] = root / "huge.json"
    p["huge"].write_text(json.dumps(huge))
    p["hugel"] = root / "huge.jsonl"
    p["hugel"].write_text(json.dumps(huge) + "\n" + json.dumps(huge) + "\n")
    p["nanmap"] = root / "nan.json"
    p["nanmap"].write_text(json.dumps(graph).replace(str(graph["lanes"][0][0][0]), "NaN", 1))
    hd = json.loads(p["hd"].read_text())
    p["hd_bigint"] = root / "hd_bigint.json"
    p["hd_bigint"].write_text(p["hd"].read_text().replace(json.dumps(hd["lanes"][0]["centerline"][0][0]), "9" * 400,
                                                           1))
    hd_huge = json.loads(p["hd"].read_text())
    for lane in hd_huge["lanes"]:
        lane["centerline"] = [[x * 1e300, y * 1e300] for x, y in lane["centerline"]]
    p["hd_huge"] = root / "hd_huge.json"
    p["hd_huge"].write_text(json.dumps(hd_huge))
    sd = json.loads(p["sd"].read_text())
    for road in sd["roads"]:
        road["polyline"] = [[x * 1e300, y * 1e300] for x, y in road["polyline"]]
    p["sd_huge"] = root / "sd_huge.json"
    p["sd_huge"].write_text(json.dumps(sd))
    p["center_bigint"] = root / "center_bigint.jsonl"
    p["center_bigint"].write_text('{"lat": ' + "9" * 400 + ', "lon": 24.9, "heading": 0}\n')
    p["center_latin1"] = root / "center_latin1.jsonl"
    p["center_latin1"].write_bytes(b'{"lat": 60.1, "lon": 24.9, "heading": "\xe9"}\n')
    p["pose_nan"] = root / "pose_nan.jsonl"
    p["pose_nan"].write_text('{"x": NaN, "y": 0, "yaw": 0}\n')

    # wrong types in maps
    wrong = json.loads(p["lg"].read_text())
    wrong["successors"] = "nope"
    p["lg_wrongtype"] = root / "wrongtype.json"
    p["lg_wrongtype"].write_text(json.dumps(wrong))
    p["notalist"] = root / "notalist.json"
    p["notalist"].write_text(json.dumps({"format": "cmtool.lanegraph", "lanes": 5}))
    p["array"] = root / "array.json"
    p["array"].write_text("[1, 2, 3]")

    av2 = json.loads(AV2.read_text())
    first = next(iter(av2["lane_segments"].values()))
    first["successors"] = "nope"
    p["av2_badsucc"] = root / AV2.name  # the city comes from the file name
    p["av2_badsucc"].write_text(json.dumps(av2))

    # hostile XML
    p["bomb"] = root / "bomb.osm"
    p["bomb"].write_text('<?xml version="1.0"?>\n<!DOCTYPE osm [<!ENTITY a "aaaaaaaaaa">'
                         + "".join(f'<!ENTITY {c} "' + f"&{p_};" * 10 + '">' for p_, c in zip("abcdefgh", "bcdefghi"))
                         + ']>\n<osm version="0.6"><node id="1" lat="0" lon="0"><tag k="name" v="&i;"/></node></osm>\n')
    p["xxe"] = root / "xxe.osm"
    p["xxe"].write_text('<?xml version="1.0"?>\n<!DOCTYPE osm [<!ENTITY x SYSTEM "file:///etc/passwd">]>\n'
                        '<osm version="0.6"><node id="1" lat="0" lon="0"><tag k="name" v="&x;"/></node></osm>\n')
    p["notxml"] = root / "notxml.osm"
    p["notxml"].write_text("this is not XML <<<")
    p["lanelet2_as_osm"] = LANELET2

    # checkpoints: the shipped ControlMap with one config field broken
    from cmtool.model.release import bundled_checkpoint

    shipped = bundled_checkpoint()
    p["ckpt"] = shipped

    def broken_ckpt(name):
        """A copy of the shipped weights (ControlMap and decoder) without their manifest; returns its ControlMap."""
        shutil.copytree(shipped.parent, root / "ckpt" / name, ignore=shutil.ignore_patterns("MANIFEST.json"))
        return root / "ckpt" / name / shipped.name

    for name, (section, key, value) in {
            "cities_int": (None, "cities", 3), "scale_str": (None, "latent_scale", "big"),
            "scale_nan": (None, "latent_scale", float("nan")), "rvae_int": (None, "rvae", 5),
            "huge_model": ("model", "hidden", 2 ** 20), "depth_neg": ("model", "depth", -3),
            "kind_bad": (None, "kind", "toaster")}.items():
        dest = broken_ckpt(name)
        config = json.loads((dest / "config.json").read_text())
        (config[section] if section else config)[key] = value
        (dest / "config.json").write_text(json.dumps(config))
        p[f"ckpt_{name}"] = dest
    p["ckpt_noconfig"] = broken_ckpt("noconfig")
    (p["ckpt_noconfig"] / "config.json").unlink()
    p["ckpt_badweights"] = broken_ckpt("badweights")
    for w in p["ckpt_badweights"].glob("*.safetensors"):
        w.write_bytes(w.read_bytes()[:1000])
    p["ckpt_notjson"] = broken_ckpt("notjson")
    (p["ckpt_notjson"] / "config.json").write_bytes(b"\xff\xfe not json")

    # datasets: a truncated shard, a shard that needs pickle, a manifest that is not JSON
    for name in ("data_truncated", "data_pickle", "data_badmanifest"):
        shutil.copytree(tiny_data, root / name)
        p[name] = root / name
    shard = sorted((p["data_truncated"]).rglob("*.npz"))[0]
    shard.write_bytes(shard.read_bytes()[: shard.stat().st_size // 3])
    shard = sorted((p["data_pickle"]).rglob("*.npz"))[0]
    with np.load(shard) as z:
        arrays = dict(z)
    arrays[next(iter(arrays))] = np.array([{"evil": 1}], dtype=object)
    np.savez(shard, **arrays)
    (p["data_badmanifest"] / "manifest.json").write_text("{not json")
    assert zipfile.is_zipfile(sorted(tiny_data.rglob("*.npz"))[0])

    # recipes
    def recipe(name, text):
        (root / name).write_text(text)
        p[name.replace(".toml", "").replace("-", "_")] = root / name

    from tests.test_train import write_recipe

    p["rvae_recipe"] = write_recipe(root / "rvae.toml", "rvae", 2, data=str(tiny_data))
    recipe("lr-nan.toml", f'[data]\npath = "{tiny_data}"\n[train]\nsteps = 2\nbatch_size = 2\nlr = nan\n')
    recipe("lr-neg.toml", f'[data]\npath = "{tiny_data}"\n[train]\nsteps = 2\nbatch_size = 2\nlr = -1.0\n')
    recipe("steps-huge.toml", f'[data]\npath = "{tiny_data}"\n[train]\nsteps = {10 ** 30}\nbatch_size = 2\n')
    recipe("notoml.toml", "this = is = not toml\n")
    recipe("empty.toml", "")
    recipe("data-nan.toml", "[data]\nscenes_per_city = nan\n")
    recipe("unknown-key.toml", f'[data]\npath = "{tiny_data}"\n[train]\nstepz = 2\n')
    (root / "out").mkdir()
    return p


def case(id_, *args, fragment=None, full=False):
    """A command line (``{name}`` placeholders), what the error must say (a fragment, case-insensitive), and whether
    it runs on a full disk."""
    return pytest.param(args, fragment, full, id=id_)


OUT_FAULTS = {"file-in-way": "{afile}/x", "unwritable": UNWRITABLE + "/x", "full-disk": "{out}/x"}

# commands that write, with the output as {dest} (a file) or {dest_dir} (a folder)
WRITERS = {
    "synth": ("data", "synth", "--city", "PIT", "--seed", "0", "--extent", "300", "--out", "{dest}.json"),
    "sd": ("data", "sd", "{hd}", "--out", "{dest}.json"),
    "sd-osm": ("data", "sd", "{hd}", "--out", "{dest}.osm", "--origin", "42.35,-71.06"),
    "raster": ("data", "raster", "{sd}", "--png", "{dest}.png"),
    "poses": ("data", "poses", "{hd}", "--n", "3", "--out", "{dest}.jsonl"),
    "frames-json": ("data", "frames", "{sd}", "--n", "20", "--json", "{dest}.json"),
    "frames-png": ("data", "frames", "{sd}", "--n", "20", "--png", "{dest}.png"),
    "import-lanelet2": ("data", "import", "--format", "lanelet2", str(LANELET2), "--out", "{dest}.json"),
    "build": ("data", "build", "--recipe", str(REPO / "recipes" / "data_tiny.toml"), "--out", "{dest}"),
    "show-png": ("data", "show", "{data}", "--n", "2", "--png", "{dest}.png"),
    "show-rrd": ("data", "show", "{data}", "--n", "2", "--rrd", "{dest}.rrd"),
    "sample-out": ("sample", "--sd", str(SD_PNG), "--steps", "2", "--no-log", "--quiet", "--out", "{dest}"),
    "sample-grid": ("sample", "--sd", str(SD_PNG), "--steps", "2", "--no-log", "--quiet", "--out", "{out}/s",
                    "--grid", "{dest}.png"),
    "sample-rrd": ("sample", "--sd", str(SD_PNG), "--steps", "2", "--quiet", "--out", "{out}/s2", "--rrd",
                   "{dest}.rrd"),
    "metrics-json": ("metrics", "--generated", "{lgl}", "--reference", "{gtl}", "--no-features", "--json",
                     "{dest}.json"),
    "validate-json": ("validate", "{lgl}", "--json", "{dest}.json"),
    "validate-repair": ("validate", "{lgl}", "--repair", "--out", "{dest}.jsonl"),
    "export-lanelet2": ("export", "--format", "lanelet2", "{lg}", "--out", "{dest}.osm"),
    "export-opendrive": ("export", "--format", "opendrive", "{lg}", "--out", "{dest}.xodr"),
    "export-geojson": ("export", "--format", "geojson", "{lg}", "--out", "{dest}.geojson"),
    "eval": ("eval", "--data", "{data}", "--n", "2", "--steps", "2", "--no-features", "--quiet", "--out", "{dest}"),
    "ablate-cfg": ("ablate", "cfg", "--data", "{data}", "--n", "2", "--w", "0,1", "--seeds", "1", "--steps", "2",
                   "--no-features", "--quiet", "--out", "{dest}"),
    "pack": ("pack", "--ckpt", "{ckpt}", "--out", "{dest}"),
    "train": ("train", "rvae", "--recipe", "{rvae_recipe}", "--quiet", "--out", "{dest}"),
}

OUTPUT_CASES = [case(f"{name}-{fault}", *(a.replace("{dest}", dest) for a in args), full=fault == "full-disk")
                for name, args in WRITERS.items() for fault, dest in OUT_FAULTS.items()
                if not (fault == "full-disk" and name in ("pack",))]  # pack's files are checked by size first

INPUT_CASES = [
    # files that are missing, empty, not text, cut short, or not what the command reads
    *[case(f"{cmd}-{bad}", *args.replace("BAD", "{" + bad + "}").split())
      for bad in ("missing", "empty", "binary", "truncated", "latin1", "array", "afile")
      for cmd, args in {"validate": "validate BAD", "export": "export --format lanelet2 BAD --out {out}/x.osm",
                        "metrics-gen": "metrics --generated BAD --reference {gtl} --no-features",
                        "metrics-ref": "metrics --generated {lgl} --reference BAD --no-features",
                        "sample-from-hd": "sample --from-hd BAD --steps 2 --no-log --quiet --out {out}/fh",
                        "data-sd": "data sd BAD --out {out}/sd.json",
                        "data-poses": "data poses BAD"}.items()],
    case("raster-truncated-sd", "data", "raster", "{truncated}", "--png", "{out}/r.png"),
    case("stats-truncated-hd", "data", "stats", "{truncated_hd}"),
    case("frames-latin1", "data", "frames", "{latin1}", "--n", "5"),
    case("center-latin1", "sample", "--osm", str(SHARED_DATA / "osm" / "finland_test.osm.pbf"), "--center",
         "{center_latin1}", "--steps", "2", "--no-log", "--out", "{out}/c"),
    case("center-bigint", "sample", "--osm", str(SHARED_DATA / "osm" / "finland_test.osm.pbf"), "--center",
         "{center_bigint}", "--steps", "2", "--no-log", "--out", "{out}/c"),
    case("pose-nan", "sample", "--from-hd", "{hd}", "--pose", "{pose_nan}", "--steps", "2", "--no-log", "--out",
         "{out}/p"),
    case("sd-png-missing", "sample", "--sd", "{missing}", "--steps", "2", "--no-log", "--out", "{out}/m"),
    case("sd-png-text", "sample", "--sd", "{afile}", "--steps", "2", "--no-log", "--out", "{out}/m"),
    case("metrics-control-missing", "metrics", "--generated", "{lgl}", "--reference", "{gtl}", "--control",
         "{missing}"),
    case("bench-train-run-missing", "bench", "train", "--recipe", str(REPO / "recipes/tiny-cpu/pipeline.toml"), "--run",
         "{missing}", fragment="does not exist"),
    case("bench-train-run-stage", "bench", "train", "--recipe", str(REPO / "recipes/tiny-cpu/rvae.toml"), "--run",
         "{out}", fragment="goes with a pipeline recipe"),
    # numbers out of range in files
    *[case(f"{cmd}-{bad}", *args.replace("BAD", "{" + bad + "}").split())
      for bad in ("bigint", "huge", "nanmap")
      for cmd, args in {"validate": "validate BAD", "export-l2": "export --format lanelet2 BAD --out {out}/x.osm",
                        "export-xodr": "export --format opendrive BAD --out {out}/x.xodr",
                        "export-geojson": "export --format geojson BAD --out {out}/x.geojson",
                        "metrics": "metrics --generated BAD --reference BAD --no-features"}.items()],
    case("sd-hd-bigint", "data", "sd", "{hd_bigint}", "--out", "{out}/sd.json"),
    case("sd-hd-huge", "data", "sd", "{hd_huge}", "--out", "{out}/sd.json"),
    case("raster-sd-huge", "data", "raster", "{sd_huge}", "--png", "{out}/r.png"),
    case("poses-hd-huge", "data", "poses", "{hd_huge}"),
    case("sample-hd-huge", "sample", "--from-hd", "{hd_huge}", "--steps", "2", "--no-log", "--out", "{out}/hh"),
    case("stats-hd-huge", "data", "stats", "{hd_huge}"),
    # wrong types
    case("validate-wrongtype", "validate", "{lg_wrongtype}", fragment="successors"),
    case("export-wrongtype", "export", "--format", "lanelet2", "{lg_wrongtype}", "--out", "{out}/w.osm"),
    case("validate-notalist", "validate", "{notalist}"),
    # numbers out of range in options
    case("sample-heading-inf", "sample", "--osm", str(SHARED_DATA / "osm" / "finland_test.osm.pbf"), "--center",
         "60.53,26.97", "--heading", "inf", "--steps", "2", "--no-log", "--out", "{out}/h", fragment="heading"),
    case("sample-heading-nan", "sample", "--osm", str(SHARED_DATA / "osm" / "finland_test.osm.pbf"), "--center",
         "60.53,26.97", "--heading", "nan", "--steps", "2", "--no-log", "--out", "{out}/h", fragment="heading"),
    case("sample-seed-huge", "sample", "--sd", str(SD_PNG), "--seed", str(2 ** 70), "--steps", "2", "--no-log",
         "--out", "{out}/sh", fragment="seed"),
    case("sample-seed-neg", "sample", "--sd", str(SD_PNG), "--seed", "-1", "--steps", "2", "--no-log", "--out",
         "{out}/sn", fragment="seed"),
    case("synth-seed-huge", "data", "synth", "--city", "BOS", "--seed", str(2 ** 70), "--out", "{out}/sy.json",
         fragment="seed"),
    case("synth-seed-neg", "data", "synth", "--city", "BOS", "--seed", "-1", "--out", "{out}/sy.json",
         fragment="seed"),
    case("synth-extent-nan", "data", "synth", "--city", "BOS", "--extent", "nan", "--out", "{out}/sy.json"),
    case("synth-extent-inf", "data", "synth", "--city", "BOS", "--extent", "inf", "--out", "{out}/sy.json"),
    case("poses-seed-huge", "data", "poses", "{hd}", "--seed", str(2 ** 70), fragment="seed"),
    case("sd-seed-huge", "data", "sd", "{hd}", "--seed", str(2 ** 70), "--out", "{out}/sd.json", fragment="seed"),
    case("eval-seed-huge", "eval", "--data", "{data}", "--n", "2", "--seed", str(2 ** 70), "--out", "{out}/e",
         fragment="seed"),
    case("show-seed-neg", "data", "show", "{data}", "--seed", "-5", "--png", "{out}/g.png", fragment="seed"),
    case("sample-cfg-nan", "sample", "--sd", str(SD_PNG), "--cfg", "nan", "--steps", "2", "--no-log", "--out",
         "{out}/cf", fragment="cfg"),
    case("sample-cfg-neg", "sample", "--sd", str(SD_PNG), "--cfg", "-1", "--steps", "2", "--no-log", "--out",
         "{out}/cf", fragment="cfg"),
    case("sample-cfg-inf", "sample", "--sd", str(SD_PNG), "--cfg", "inf", "--steps", "2", "--no-log", "--out",
         "{out}/cf", fragment="cfg"),
    case("sample-city-cfg-nan", "sample", "--sd", str(SD_PNG), "--city-cfg", "nan", "--steps", "2", "--no-log",
         "--out", "{out}/cc", fragment="city-cfg"),
    case("sample-eta-nan", "sample", "--sd", str(SD_PNG), "--sampler", "ddim", "--eta", "nan", "--steps", "2",
         "--no-log", "--out", "{out}/et", fragment="eta"),
    case("sample-pose-nan", "sample", "--from-hd", "{hd}", "--pose", "nan,0,0", "--steps", "2", "--no-log", "--out",
         "{out}/pn"),
    case("sample-pose-inf-yaw", "sample", "--from-hd", "{hd}", "--pose", "0,0,inf", "--steps", "2", "--no-log",
         "--out", "{out}/pn"),
    case("sample-center-nan", "sample", "--osm", str(SHARED_DATA / "osm" / "finland_test.osm.pbf"), "--center",
         "nan,26.97", "--steps", "2", "--no-log", "--out", "{out}/cn"),
    case("sample-device-bogus", "sample", "--sd", str(SD_PNG), "--device", "bogus", "--steps", "2", "--no-log",
         "--out", "{out}/db", fragment="device"),
    case("eval-device-bogus", "eval", "--data", "{data}", "--n", "2", "--device", "bogus", "--out", "{out}/ed",
         fragment="device"),
    case("eval-cfg-nan", "eval", "--data", "{data}", "--n", "2", "--cfg", "nan", "--out", "{out}/ec",
         fragment="cfg"),
    case("ablate-w-nan", "ablate", "cfg", "--data", "{data}", "--n", "2", "--w", "0,nan", "--out", "{out}/aw"),
    case("ablate-w-neg", "ablate", "cfg", "--data", "{data}", "--n", "2", "--w", "0,-1", "--out", "{out}/aw"),
    case("sd-offset-inf", "data", "sd", "{hd}", "--offset", "inf", "--out", "{out}/sd.json", fragment="offset"),
    case("sd-offset-nan", "data", "sd", "{hd}", "--offset", "nan", "--out", "{out}/sd.json", fragment="offset"),
    case("sd-rotation-nan", "data", "sd", "{hd}", "--rotation", "nan", "--out", "{out}/sd.json",
         fragment="rotation"),
    case("sd-drop-minor-2", "data", "sd", "{hd}", "--drop-minor", "2", "--out", "{out}/sd.json",
         fragment="drop-minor"),
    case("raster-yaw-nan", "data", "raster", "{sd}", "--yaw", "nan", "--png", "{out}/r.png", fragment="yaw"),
    case("raster-x-inf", "data", "raster", "{sd}", "--x", "inf", "--png", "{out}/r.png", fragment="--x"),
    case("export-heading-nan", "export", "--format", "lanelet2", "{lg}", "--origin", "60,25", "--heading", "nan",
         "--out", "{out}/h.osm", fragment="heading"),
    case("export-heading-inf", "export", "--format", "opendrive", "{lg}", "--origin", "60,25", "--heading", "inf",
         "--out", "{out}/h.xodr", fragment="heading"),
    case("export-origin-nan", "export", "--format", "lanelet2", "{lg}", "--origin", "nan,25", "--out",
         "{out}/o.osm", fragment="origin"),
    case("export-lane-width-nan", "export", "--format", "lanelet2", "{lg}", "--origin", "60,25", "--lane-width", "nan",
         "--out",
         "{out}/w.osm", fragment="lane-width"),
    case("rvae-tol-nan", "ablate", "rvae", "--data", "{data}", "--tol", "nan", "--out", "{out}/t", fragment="tol"),
    case("poses-near-junction-nan", "data", "poses", "{hd}", "--near-junction", "nan", fragment="near-junction"),
    # checkpoints
    *[case(f"{cmd}-{bad}", *args.replace("BAD", "{ckpt_" + bad + "}").split())
      for bad in ("cities_int", "scale_str", "scale_nan", "rvae_int", "huge_model", "depth_neg", "kind_bad",
                  "noconfig", "badweights", "notjson")
      for cmd, args in {"info": "info BAD",
                        "sample": "sample --ckpt BAD --sd " + str(SD_PNG) + " --steps 2 --no-log --out {out}/k",
                        "pack": "pack --ckpt BAD --out {out}/pk"}.items()],
    case("eval-ckpt-missing", "eval", "--ckpt", "{missing}", "--data", "{data}", "--n", "2", "--out", "{out}/em"),
    # datasets
    *[case(f"{cmd}-{bad}", *args.replace("BAD", "{" + bad + "}").split())
      for bad in ("data_truncated", "data_pickle", "data_badmanifest", "afile", "missing")
      for cmd, args in {"show": "data show BAD --n 40 --png {out}/g.png",
                        "eval": "eval --data BAD --n 8 --steps 2 --no-features --quiet --out {out}/ev",
                        "ablate-rvae": "ablate rvae --data BAD --n 2 --out {out}/ar"}.items()],
    case("train-data-truncated", "train", "rvae", "--recipe", "{lr_nan}", "--data", "{data_truncated}", "--out",
         "{out}/tr"),
    # hostile or wrong XML
    case("import-bomb", "data", "import", "--format", "osm", "{bomb}", "--out", "{out}/b.json"),
    case("import-xxe", "data", "import", "--format", "osm", "{xxe}", "--out", "{out}/x.json"),
    case("import-notxml", "data", "import", "--format", "osm", "{notxml}", "--out", "{out}/n.json"),
    case("import-lanelet2-bomb", "data", "import", "--format", "lanelet2", "{bomb}", "--out", "{out}/b.json"),
    case("import-lanelet2-as-osm", "data", "import", "--format", "osm", "{lanelet2_as_osm}", "--out",
         "{out}/l.json"),
    case("sample-osm-bomb", "sample", "--osm", "{bomb}", "--center", "0,0", "--steps", "2", "--no-log", "--out",
         "{out}/ob"),
    case("import-av2-hd", "data", "import", "--format", "av2", "{hd}", "--out", "{out}/a.json"),
    case("import-av2-successors-not-a-list", "data", "import", "--format", "av2", "{av2_badsucc}", "--out",
         "{out}/a.json", fragment="successors"),
    case("import-av2-latin1", "data", "import", "--format", "av2", "{latin1}", "--out", "{out}/a.json"),
    # recipes
    *[case(f"train-{name}", "train", "rvae", "--recipe", "{" + name + "}", "--out", "{out}/t-" + name)
      for name in ("lr_nan", "lr_neg", "steps_huge", "notoml", "unknown_key")],
    case("build-empty-recipe", "data", "build", "--recipe", "{empty}", "--out", "{out}/eb"),
    case("build-nan-recipe", "data", "build", "--recipe", "{data_nan}", "--out", "{out}/nb"),
    case("build-notoml", "data", "build", "--recipe", "{notoml}", "--out", "{out}/tb"),
    case("info-notoml", "info", "{notoml}"),
]


def resolve(args, ws, out: Path) -> list[str]:
    names = {k: str(v) for k, v in ws.items()} | {"out": str(out)}
    return [a.format(**names) for a in args]


def check(code, err, fragment):
    assert "Traceback" not in err, err
    assert code not in (0, None), f"exit {code}, stderr: {err}"
    errors = [line for line in err.splitlines() if line.startswith("Error: ")]
    assert len(errors) == 1 and err.rstrip().splitlines()[-1] == errors[0], f"not one Error line: {err!r}"
    if fragment:
        assert fragment.lower() in errors[0].lower(), errors[0]


@pytest.mark.parametrize("args, fragment, full", OUTPUT_CASES + INPUT_CASES)
def test_user_fault_is_one_line(ws, tmp_path, args, fragment, full):
    out = tmp_path / "out"
    out.mkdir()
    argv = resolve(args, ws, out)
    earlier = snapshot(ws["root"] / "s")
    if full:
        with full_disk():
            code, err = cli(*argv)
    else:
        code, err = cli(*argv)
    check(code, err, fragment)
    assert snapshot(ws["root"] / "s") == earlier


def test_suite_is_large_enough():
    assert len(OUTPUT_CASES) + len(INPUT_CASES) >= 150


@pytest.mark.parametrize("fault", ["grid-under-a-file", "full-disk", "bad-seed"])
def test_a_failed_sample_leaves_the_earlier_outputs_as_they_were(ws, tmp_path, fault):
    """The issue's lost outputs: `sample --out` once, then again failing; the first run's files stay byte-identical."""
    out = tmp_path / "s"
    args = ["sample", "--from-hd", ws["hd"], "--steps", 2, "--out", out, "--quiet"]
    code, err = cli(*args)
    assert code == 0, err
    before = snapshot(out)
    assert {"hd.json", "hd.gt.json", "hd.png", "sample.rrd"} <= set(before)
    if fault == "full-disk":
        with full_disk():
            code, err = cli(*args)
    else:
        code, err = cli(*args, *(("--grid", ws["afile"] / "g.png") if fault == "grid-under-a-file" else
                                 ("--seed", -1)))
    check(code, err, None)
    assert snapshot(out) == before
    assert not [p for p in out.iterdir() if p.name.startswith(".")], "temporary files left behind"


@pytest.mark.parametrize("sig", ["SIGKILL", "SIGTERM"])
def test_eval_killed_midway_resumes_to_the_same_numbers(ws, tmp_path, sig):
    """kill -9 (or SIGTERM, which ends it with exit 143) while `cmtool eval` generates maps, then the same command
    again: it continues from its cache and ends with the metrics of a run never interrupted."""
    import os
    import signal
    import subprocess
    import sys
    import time

    args = ["eval", "--data", str(ws["data"]), "--n", "8", "--batch", "1", "--steps", "3", "--no-features",
            "--quiet"]
    whole, killed = tmp_path / "whole", tmp_path / "killed"
    code, err = cli(*args, "--out", whole)
    assert code == 0, err
    proc = subprocess.Popen([sys.executable, "-m", "cmtool", *args, "--out", str(killed)], cwd=REPO,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            env=os.environ | {"OMP_NUM_THREADS": "1"})  # one thread, as this module's runs: the
    # same sums in the same order (on some CPUs two threads change the last digits)
    cache = killed / "cache" / "controlmap.jsonl"
    deadline = time.monotonic() + 300
    while not (cache.is_file() and len(cache.read_text().splitlines()) >= 2):
        assert proc.poll() is None and time.monotonic() < deadline, "eval ended before it could be killed"
        time.sleep(0.05)
    os.kill(proc.pid, getattr(signal, sig))
    assert proc.wait(timeout=60) == (-9 if sig == "SIGKILL" else 143)
    assert not (killed / "metrics.json").exists()
    code, err = cli(*args, "--out", killed)
    assert code == 0, err
    numbers = [json.loads((run / "metrics.json").read_text()) for run in (killed, whole)]
    for result in numbers:
        for method in result["methods"].values():
            method.pop("seconds")  # timings differ
    assert numbers[0] == numbers[1]


# --- Reliability 3: hostile inputs of new kinds, outputs onto inputs, special files, locks, signals ---------------

def _osm(nodes: dict, ways: dict) -> str:
    lines = ['<?xml version="1.0"?>', '<osm version="0.6">']
    lines += [f' <node id="{i}" lat="{lat}" lon="{lon}"/>' for i, (lat, lon) in nodes.items()]
    lines += [f' <way id="{w}">' + "".join(f'<nd ref="{i}"/>' for i in ids) + '<tag k="highway" v="residential"/></way>'
              for w, ids in ways.items()]
    return "\n".join(lines + ["</osm>"]) + "\n"


def _safetensors_header(path: Path) -> tuple[dict, bytes]:
    raw = path.read_bytes()
    n = int.from_bytes(raw[:8], "little")
    return json.loads(raw[8:8 + n]), raw[8 + n:]


def _write_safetensors(path: Path, header_text: str, data: bytes) -> None:
    head = header_text.encode()
    path.write_bytes(len(head).to_bytes(8, "little") + head + data)


@pytest.fixture(scope="module")
def hostile(ws, tmp_path_factory):
    """The workspace of the module, and inputs a hostile user would give."""
    root = tmp_path_factory.mktemp("hostile")
    p = dict(ws)

    def put(name, text):
        p[name.replace(".", "_").replace("-", "_")] = root / name
        (root / name).write_text(text)

    # coordinates off the globe, one id at two places
    road = {2: (60.0, 24.91), 3: (60.001, 24.92)}
    put("lat91.osm", _osm({1: (91, 24.9), **road}, {10: [1, 2, 3]}))
    put("nan.osm", _osm({1: ("nan", 24.9), **road}, {10: [1, 2, 3]}))
    put("inf.osm", _osm({1: (60.0, "inf"), **road}, {10: [1, 2, 3]}))
    put("twice.osm", _osm({1: (60.0, 24.9), **road}, {10: [1, 2, 3]}).replace(
        " <way", ' <node id="2" lat="20.0" lon="-10.0"/>\n <way', 1))
    lanelet2 = LANELET2.read_text()
    first = lanelet2.index("lat='") + len("lat='")
    put("lanelet2_nan.osm", lanelet2[:first] + "nan" + lanelet2[lanelet2.index("'", first):])
    # Argoverse 2: one lane segment id twice, no lane segments
    av2 = json.loads(AV2.read_text())
    ids = list(av2["lane_segments"])
    av2["lane_segments"][ids[1]]["id"] = av2["lane_segments"][ids[0]]["id"]
    (root / "dup").mkdir()
    p["av2_dup"] = root / "dup" / AV2.name
    p["av2_dup"].write_text(json.dumps(av2))
    (root / "empty").mkdir()
    p["av2_empty"] = root / "empty" / AV2.name
    p["av2_empty"].write_text(json.dumps(json.loads(AV2.read_text()) | {"lane_segments": {}}))
    # nesting thousands of levels deep
    deep = "[" * 5000 + "]" * 5000
    put("deep.json", '{"format": "cmtool.lanegraph", "version": 1, "lanes": ' + deep + "}")
    put("deep.jsonl", '{"format": "cmtool.lanegraph", "version": 1, "lanes": ' + deep + "}\n")
    put("deep_hd.json", '{"format": "cmtool.hdmap", "version": 1, "lanes": ' + deep + "}")
    put("deep.toml", "x = " + "[" * 5000 + "]" * 5000 + "\n")
    # memory asked for by a number
    ihdr = (60000).to_bytes(4, "big") * 2 + bytes([8, 2, 0, 0, 0])
    p["huge_png"] = root / "huge.png"
    p["huge_png"].write_bytes(b"\x89PNG\r\n\x1a\n" + (13).to_bytes(4, "big") + b"IHDR" + ihdr + bytes(4))
    np.save(root / "objects.npy", np.array([{"a": 1}], dtype=object), allow_pickle=True)
    p["objects_npy"] = root / "objects.npy"
    recipe = (REPO / "recipes" / "data_tiny.toml").read_text()
    put("lines-huge.toml", recipe.replace("num_lines = 50", "num_lines = 1000000").replace("num_points = 20",
                                                                                             "num_points = 10000"))
    put("extent-huge.toml", recipe.replace("extent = 400.0", "extent = 1e9"))
    # checkpoints: a header naming a tensor twice, tensors overlapping, an index out of its folder or of thousands
    from cmtool.model.release import bundled_checkpoint

    shipped = bundled_checkpoint()

    def ckpt_copy(name):
        dest = root / "ckpt" / name
        shutil.copytree(shipped.parent, dest, ignore=shutil.ignore_patterns("MANIFEST.json"))
        return dest / shipped.name

    shard = sorted(shipped.glob("model-*.safetensors"))[0].name
    header, data = _safetensors_header(shipped / shard)
    names = [k for k in header if k != "__metadata__"]
    text = json.dumps(header)
    p["ckpt_twice"] = ckpt_copy("twice")
    entry = json.dumps({names[0]: header[names[0]]})[1:-1]
    _write_safetensors(p["ckpt_twice"] / shard, text[:-1] + ", " + entry + "}", data)
    sizes = {}
    for k in names:  # two tensors of one size, the second moved onto the first
        span = header[k]["data_offsets"]
        sizes.setdefault(span[1] - span[0], []).append(k)
    a, b = next(v for v in sizes.values() if len(v) > 1)[:2]
    overlap = json.loads(text)
    overlap[b]["data_offsets"] = overlap[a]["data_offsets"]
    p["ckpt_overlap"] = ckpt_copy("overlap")
    _write_safetensors(p["ckpt_overlap"] / shard, json.dumps(overlap), data)
    p["ckpt_garbage"] = ckpt_copy("garbage")  # a header of the right length that is not JSON
    _write_safetensors(p["ckpt_garbage"] / shard, "x" * len(text), data)
    p["ckpt_pickle"] = ckpt_copy("pickle")  # a pickle named .safetensors
    (p["ckpt_pickle"] / shard).write_bytes(pickle.dumps({k: list(range(10)) for k in names}))
    index = json.loads((shipped / "model.safetensors.index.json").read_text())
    p["ckpt_escape"] = ckpt_copy("escape")
    escape = dict(index, weight_map={k: "../../../" + v for k, v in index["weight_map"].items()})
    (p["ckpt_escape"] / "model.safetensors.index.json").write_text(json.dumps(escape))
    p["ckpt_bogus"] = ckpt_copy("bogus")
    bogus = dict(index, weight_map=index["weight_map"] | {f"w{i}": f"model-{i:05d}-of-99999.safetensors"
                                                         for i in range(5000)})
    (p["ckpt_bogus"] / "model.safetensors.index.json").write_text(json.dumps(bogus))
    p["ckpt_deep"] = ckpt_copy("deep")
    (p["ckpt_deep"] / "config.json").write_text('{"format": "cmtool.checkpoint", "x": ' + deep + "}")
    # datasets whose manifest lists shards out of the folder, or thousands that no unit makes
    for name, shards in (("data_escape", lambda s: [{"file": "../" * 6 + "etc/passwd", "scenes": 8}]),
                         ("data_bogus", lambda s: s + [{"file": f"train/u{i:05d}_00.npz", "scenes": 8}
                                                       for i in range(900, 20000)])):
        shutil.copytree(ws["data"], root / name)
        manifest = json.loads((root / name / "manifest.json").read_text())
        split = next(iter(manifest["splits"].values()))
        split["shards"] = shards(split["shards"])
        (root / name / "manifest.json").write_text(json.dumps(manifest))
        p[name] = root / name
    # training recipes of models far beyond any machine's memory
    from tests.test_train import write_recipe

    tiny = write_recipe(root / "rvae-tiny.toml", "rvae", 2, data=str(ws["data"])).read_text()
    put("rvae-deep.toml", tiny.replace("decoder_layers = 1", "decoder_layers = 100000"))
    put("rvae-huge.toml", tiny.replace("d_model = 32", "d_model = 16384").replace("decoder_layers = 1",
                                                                                 "decoder_layers = 64")
        .replace("ffn = 64", "ffn = 65536"))
    # a pipeline recipe that names itself as a stage
    for stage in ("rvae", "dit", "controlnet"):
        (root / f"{stage}.toml").write_text(f'[train]\nstage = "{stage}"\n')
    put("self.toml", '[pipeline]\ndata = "self.toml"\nrvae = "self.toml"\ndit = "dit.toml"\n'
                     'controlnet = "controlnet.toml"\n')
    return p


SD_ARGS = ("--sd", str(SD_PNG), "--steps", "1", "--no-log", "--quiet")
HOSTILE_CASES = [
    case("import-osm-lat91", "data", "import", "--format", "osm", "{lat91_osm}", "--out", "{out}/o.json",
         fragment="off the globe"),
    case("import-osm-nan", "data", "import", "--format", "osm", "{nan_osm}", "--out", "{out}/o.json",
         fragment="off the globe"),
    case("import-osm-inf", "data", "import", "--format", "osm", "{inf_osm}", "--out", "{out}/o.json",
         fragment="off the globe"),
    case("import-osm-id-twice", "data", "import", "--format", "osm", "{twice_osm}", "--out", "{out}/o.json",
         fragment="twice"),
    case("sample-osm-nan", "sample", "--osm", "{nan_osm}", "--center", "60.0,24.91", "--steps", "1", "--no-log",
         "--out", "{out}/s", fragment="off the globe"),
    case("import-lanelet2-nan", "data", "import", "--format", "lanelet2", "{lanelet2_nan_osm}", "--out",
         "{out}/l.json", fragment="off the globe"),
    case("import-av2-id-twice", "data", "import", "--format", "av2", "{av2_dup}", "--out", "{out}/a.json",
         fragment="earlier lane segment"),
    case("import-av2-no-lanes", "data", "import", "--format", "av2", "{av2_empty}", "--out", "{out}/a.json",
         fragment="no lane segments"),
    *[case(f"{cmd}-deep-json", *args.split(), fragment="nested")
      for cmd, args in {"validate": "validate {deep_json}", "validate-jsonl": "validate {deep_jsonl}",
                        "metrics": "metrics --generated {deep_jsonl} --reference {gtl} --no-features",
                        "export": "export --format geojson {deep_json} --origin 60,25 --out {out}/d.geojson",
                        "data-sd": "data sd {deep_hd_json} --out {out}/d.json",
                        "info-ckpt": "info {ckpt_deep}",
                        "sample-ckpt": "sample --ckpt {ckpt_deep} --sd " + str(SD_PNG) + " --no-log --out {out}/d"
                        }.items()],
    *[case(f"{cmd}-deep-toml", *args.split(), fragment="nested")
      for cmd, args in {"train": "train rvae --recipe {deep_toml} --out {out}/t",
                        "build": "data build --recipe {deep_toml} --out {out}/b", "info": "info {deep_toml}"}.items()],
    case("frames-n-huge", "data", "frames", "{sd}", "--n", str(10 ** 8), fragment="--n"),
    case("poses-n-huge", "data", "poses", "{hd}", "--n", str(10 ** 8), fragment="--n"),
    case("sample-picture-huge", "sample", "--sd", "{huge_png}", "--steps", "1", "--no-log", "--out", "{out}/p",
         fragment="60000 x 60000"),
    case("metrics-control-objects", "metrics", "--generated", "{lgl}", "--reference", "{gtl}", "--no-features",
         "--control", "{objects_npy}", fragment="objects.npy"),
    case("build-recipe-memory", "data", "build", "--recipe", "{lines_huge_toml}", "--out", "{out}/b",
         fragment="GiB"),
    case("build-recipe-extent", "data", "build", "--recipe", "{extent_huge_toml}", "--out", "{out}/b",
         fragment="extent"),
    *[case(f"sample-ckpt-{bad}", "sample", "--ckpt", "{ckpt_" + bad + "}", *SD_ARGS, "--out", "{out}/k",
           fragment=fragment)
      for bad, fragment in (("twice", "twice"), ("overlap", "overlapping"), ("escape", "index"),
                            ("bogus", "index"))],
    case("eval-manifest-escape", "eval", "--data", "{data_escape}", "--n", "2", "--steps", "1", "--out", "{out}/e",
         fragment="manifest"),
    case("eval-manifest-bogus", "eval", "--data", "{data_bogus}", "--n", "2", "--steps", "1", "--out", "{out}/e",
         fragment="manifest"),
    case("train-model-deep", "train", "rvae", "--recipe", "{rvae_deep_toml}", "--out", "{out}/t",
         fragment="decoder_layers"),
    case("train-model-huge", "train", "rvae", "--recipe", "{rvae_huge_toml}", "--out", "{out}/t",
         fragment="billion parameters"),
    case("pipeline-names-itself", "train", "pipeline", "--recipe", "{self_toml}", "--out", "{out}/p",
         fragment="pipeline recipe"),
    # issue 57: frame options --area does not take, checkpoints info never read the weights of, frames off the map
    case("area-heading", "sample", "--osm", str(TOWN), "--area", "all", "--heading", "30", *SD_ARGS[2:], "--out",
         "{out}/a", fragment="--heading"),
    *[case(f"info-ckpt-{bad}", "info", "{ckpt_" + bad + "}", fragment="not a valid safetensors file")
      for bad in ("overlap", "garbage", "pickle")],
    case("raster-x-far", "data", "raster", "{sd}", "--x", "1e300", "--png", "{out}/r.png", fragment="--x"),
    *[case(f"connect-{name}", "sample", *SD_ARGS[:-2], "--quiet", "--out", "{out}/c", "--connect", url,
           fragment="--connect")
      for name, url in (("port-70000", "rerun+http://127.0.0.1:70000/proxy"), ("port-abc", "rerun+http://127.0.0.1:abc"),
                        ("port-negative", "rerun+http://127.0.0.1:-1/proxy"), ("not-a-url", "abc"),
                        ("http-scheme", "http://127.0.0.1:9876/proxy"))],
]


@pytest.mark.parametrize("args, fragment, full", HOSTILE_CASES)
def test_hostile_input_is_one_line(hostile, tmp_path, args, fragment, full):
    out = tmp_path / "out"
    out.mkdir()
    check(*cli(*resolve(args, hostile, out)), fragment)
    assert not any(out.iterdir()), "a refused command wrote files"


SAME_FILE = {  # commands whose output is given as one of their inputs: (command line, the input)
    "data-sd": (("data", "sd", "{f}", "--out", "{f}"), "hd"),
    "export": (("export", "--format", "geojson", "{f}", "--origin", "60,25", "--out", "{f}"), "lgl"),
    "repair": (("validate", "{f}", "--repair", "--out", "{f}"), "lgl"),
    "import-osm": (("data", "import", "--format", "osm", "{f}", "--out", "{f}"), "lat91_osm"),
    "metrics-json": (("metrics", "--generated", "{f}", "--reference", "{gtl}", "--no-features", "--json", "{f}"),
                     "lgl"),
    "metrics-json-ref": (("metrics", "--generated", "{lgl}", "--reference", "{f}", "--no-features", "--json", "{f}"),
                         "gtl"),
}


@pytest.mark.parametrize("how", ["same-path", "hard-link", "symbolic-link"])
@pytest.mark.parametrize("name", SAME_FILE)
def test_an_output_never_replaces_an_input(hostile, tmp_path, name, how):
    """The output named as the input itself, a hard link to it or a symbolic link to it: refused in one line
    before any work, the input byte-identical."""
    args, source = SAME_FILE[name]
    f = tmp_path / Path(hostile[source]).name
    shutil.copy(hostile[source], f)
    before = f.read_bytes()
    dest = f if how == "same-path" else tmp_path / ("alias" + f.suffix)
    if how == "hard-link":
        dest.hardlink_to(f)
    elif how == "symbolic-link":
        dest.symlink_to(f)
    first = args.index("{f}")  # the input; the later {f}: the output
    argv = [str(f) if i == first else str(dest) if a == "{f}" else a for i, a in enumerate(args)]
    check(*cli(*resolve(argv, hostile, tmp_path)), "input")
    assert f.read_bytes() == before


def test_sample_into_the_folder_of_its_sd_picture_keeps_the_picture(tmp_path):
    picture = tmp_path / "sd.png"
    shutil.copy(SD_PNG, picture)
    before = picture.read_bytes()
    check(*cli("sample", "--sd", picture, "--steps", 1, "--no-log", "--quiet", "--out", tmp_path), "sd.png")
    assert picture.read_bytes() == before and sorted(p.name for p in tmp_path.iterdir()) == ["sd.png"]


def test_special_files_are_never_replaced(ws, tmp_path):
    """A FIFO, a link to a FIFO (as /dev/stdout may be) and, as root, a character device (as /dev/null) are refused as
    outputs and stay what they were; a link to a regular file is written through and stays a link."""
    import os
    import stat

    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    link = tmp_path / "stdout"
    link.symlink_to(fifo)
    specials = [fifo, link]
    if os.geteuid() == 0:
        device = tmp_path / "null"
        os.mknod(device, 0o666 | stat.S_IFCHR, os.makedev(1, 3))
        specials.append(device)
    for path in specials:
        for args in (("export", "--format", "geojson", ws["lg"], "--origin", "60,25", "--out", path),
                     ("data", "sd", ws["hd"], "--out", path), ("validate", ws["lgl"], "--json", path)):
            check(*cli(*args), "not a regular file")
    assert stat.S_ISFIFO(os.stat(fifo).st_mode) and link.is_symlink()
    assert os.geteuid() != 0 or stat.S_ISCHR(os.stat(tmp_path / "null").st_mode)
    target = tmp_path / "real.geojson"
    target.write_text("old")
    alias = tmp_path / "alias.geojson"
    alias.symlink_to(target)
    code, err = cli("export", "--format", "geojson", ws["lg"], "--origin", "60,25", "--out", alias)
    assert code == 0, err
    assert alias.is_symlink() and json.loads(target.read_text())["type"] == "FeatureCollection"


def test_nesting_is_measured_outside_strings():
    """The JSON depth check agrees with a recursive count on random documents, brackets inside strings, escaped
    quotes and chunk borders included."""
    import random

    from cmtool.core.jsonio import nesting

    def depth(o):
        if not isinstance(o, (list, dict)):
            return 0
        return 1 + max((depth(v) for v in (o.values() if isinstance(o, dict) else o)), default=0)

    def gen(rng, d):
        r = rng.random()
        if d > 6 or r < 0.3:
            return rng.choice(["[{", 'x]"]', 1, 2.5, 'a\\"[', None, "}}"])
        if r < 0.65:
            return [gen(rng, d + 1) for _ in range(rng.randint(0, 3))]
        return {rng.choice(["k[", "}", "z"]) + str(i): gen(rng, d + 1) for i in range(rng.randint(0, 3))}

    rng = random.Random(0)
    for _ in range(500):
        doc = gen(rng, 0)
        text = json.dumps(doc)
        assert {nesting(text, chunk) for chunk in (1, 3, 7, 1 << 22)} == {depth(doc)}, text


@pytest.fixture(scope="module")
def run(ws, tmp_path_factory):
    """An RVAE run of 2 steps (one checkpoint with its training state), and its recipe."""
    from tests.test_train import write_recipe

    root = tmp_path_factory.mktemp("run")
    recipe = write_recipe(root / "rvae.toml", "rvae", 2, data=str(ws["data"]))
    code, err = cli("train", "rvae", "--recipe", recipe, "--quiet", "--out", root / "run")
    assert code == 0, err
    return root


def _longer(run: Path, dest: Path, steps: int) -> Path:
    """The run's recipe with ``steps`` training steps."""
    import re

    dest.write_text(re.sub(r"(?m)^(steps|preview_every) = 2$", rf"\1 = {steps}", (run / "rvae.toml").read_text()))
    return dest


@pytest.mark.parametrize("damage", ["no-param-groups", "empty-param-groups", "groups-not-a-list"])
def test_damaged_optimizer_state_is_named(run, tmp_path, damage):
    shutil.copytree(run / "run", tmp_path / "run")
    meta = next((tmp_path / "run" / "checkpoints").glob("step_*")) / "train_state.json"
    meta.write_text(json.dumps({} if damage == "no-param-groups" else
                               {"param_groups": [] if damage == "empty-param-groups" else 5}))
    check(*cli("train", "rvae", "--recipe", _longer(run, tmp_path / "rvae.toml", 4), "--quiet", "--resume", "--out",
               tmp_path / "run"), "damaged training state")


def test_full_disk_while_training_keeps_the_last_checkpoint(run, tmp_path):
    """Resuming onto a full disk fails in one line; the checkpoint before is intact, no temporary folder stays."""
    shutil.copytree(run / "run", tmp_path / "run")
    before = snapshot(tmp_path / "run" / "checkpoints")
    recipe = _longer(run, tmp_path / "rvae.toml", 4)
    with full_disk():
        code, err = cli("train", "rvae", "--recipe", recipe, "--quiet", "--resume", "--out", tmp_path / "run")
    check(code, err, "cannot write")
    assert snapshot(tmp_path / "run" / "checkpoints") == before
    assert not list((tmp_path / "run" / "checkpoints").glob(".*"))


def test_full_disk_while_packing_keeps_the_earlier_set(ws, tmp_path):
    """pack over an earlier set with room for part of the new one: the earlier set stays whole."""
    out = tmp_path / "weights"
    code, err = cli("pack", "--ckpt", ws["ckpt"], "--out", out)
    assert code == 0, err
    before = snapshot(out)
    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    resource.setrlimit(resource.RLIMIT_FSIZE, (12 * 2**20, hard))  # the first weight file fits, the second not
    try:
        code, err = cli("pack", "--ckpt", ws["ckpt"], "--out", out)
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))
    check(code, err, "cannot write")
    assert snapshot(out) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["weights"]


def test_a_viewer_that_never_answers_is_refused(tmp_path):
    import socket
    import threading

    server = socket.socket()
    server.bind(("127.0.0.1", 0))
    server.listen()
    accepted = []
    threading.Thread(target=lambda: accepted.append(server.accept()), daemon=True).start()
    try:
        check(*cli("sample", *SD_ARGS[:-2], "--out", tmp_path / "s", "--connect",
                   f"rerun+http://127.0.0.1:{server.getsockname()[1]}/proxy"), "does not answer")
    finally:
        server.close()
    assert accepted and not (tmp_path / "s").exists()


def test_a_live_recording_onto_a_full_disk_is_one_line(tmp_path):
    """--connect to a running viewer with --rrd onto a full disk: one line (Rerun's own file writer fails), no partial
    recording left."""
    import socket
    import subprocess
    import sys

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    viewer = subprocess.Popen([sys.executable, "-c", "import rerun as rr, time\nrr.init('viewer')\n"
                               f"rr.serve_grpc(grpc_port={port})\nprint('up', flush=True)\ntime.sleep(600)"],
                              stdout=subprocess.PIPE, text=True)
    try:
        assert viewer.stdout.readline().strip() == "up"
        with full_disk():
            code, err = cli("sample", *SD_ARGS[:-2], "--quiet", "--out", tmp_path / "s", "--rrd", tmp_path / "x.rrd",
                            "--connect", f"rerun+http://127.0.0.1:{port}/proxy")
    finally:
        viewer.kill()
        viewer.wait()
    check(code, err, "cannot write")
    assert sorted(p.name for p in tmp_path.iterdir()) == []


def test_serve_on_a_busy_port_is_one_line(tmp_path):
    import socket

    from cmtool.viz.recording import GRPC_PORT

    held = socket.socket()
    try:
        held.bind(("0.0.0.0", GRPC_PORT))  # bound, not listening: a connection test would find it free
    except OSError:
        pass  # something else holds it: busy all the same
    try:
        check(*cli("sample", "--sd", SD_PNG, "--steps", 1, "--quiet", "--out", tmp_path / "s", "--serve"),
              f"port {GRPC_PORT}")
    finally:
        held.close()


def _python(script: str):
    """``python -c script`` in the repository root, its output captured (two minutes at most)."""
    import subprocess
    import sys

    return subprocess.run([sys.executable, "-c", script], cwd=REPO, capture_output=True, text=True, timeout=120)


def _subprocess(*args, **kwargs):
    import os
    import subprocess
    import sys

    return subprocess.Popen([sys.executable, "-m", "cmtool", *map(str, args)], cwd=REPO, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True, env=os.environ | {"OMP_NUM_THREADS": "1"}, **kwargs)


def test_a_second_run_on_one_output_folder_fails_at_once(ws, tmp_path):
    """While one run holds its output folder, a second run on it fails in one line (and leaves it alone); once the
    first has ended, the folder is free."""
    import subprocess
    import sys

    out = tmp_path / "eval"
    holder = subprocess.Popen([sys.executable, "-c", "import sys, time\nfrom cmtool.core.outputs import claim_folder\n"
                               f"claim_folder({str(out)!r})\nprint('held', flush=True)\ntime.sleep(600)"],
                              cwd=REPO, stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        for args in (("eval", "--data", ws["data"], "--n", 2, "--steps", 1, "--no-features", "--quiet", "--out", out),
                     ("sample", *SD_ARGS, "--out", out), ("data", "build", "--recipe",
                                                         REPO / "recipes" / "data_tiny.toml", "--out", out)):
            check(*cli(*args), "another cmtool run")
        assert not any(out.iterdir())
    finally:
        holder.kill()
        holder.wait()
    code, err = cli("sample", *SD_ARGS, "--out", out)
    assert code == 0, err


def _children(pid: int) -> list[int]:
    """The processes whose parent is ``pid`` (from /proc)."""
    found = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == pid:
            found.append(int(stat.parent.name))
    return found


def _running_with(text: str) -> list[int]:
    """The live (not zombie) processes whose command line holds ``text``."""
    found = []
    for proc in Path("/proc").glob("[0-9]*"):
        try:
            if text in (proc / "cmdline").read_bytes().decode(errors="replace") and \
                    (proc / "stat").read_text().rsplit(")", 1)[1].split()[0] != "Z":
                found.append(int(proc.name))
        except OSError:
            continue
    return found


@pytest.mark.parametrize("sig", ["SIGTERM", "SIGINT"])
def test_a_signal_stops_a_build_and_its_workers(tmp_path, sig):
    """SIGTERM to `data build` (or Ctrl-C, which reaches its whole process group) stops it and its worker processes
    with a clean exit status and no temporary file; the same command then finishes the dataset."""
    import os
    import signal
    import time

    recipe = tmp_path / "data.toml"
    recipe.write_text((REPO / "recipes" / "data_tiny.toml").read_text().replace(
        "maps_per_city = 1 ", "maps_per_city = 4 ").replace("scenes_per_map = 8 ", "scenes_per_map = 100 "))
    out = tmp_path / "data"
    proc = _subprocess("data", "build", "--recipe", recipe, "--out", out, "--workers", 2, start_new_session=True)
    deadline = time.monotonic() + 120
    while not list(out.rglob("*.npz")):
        assert proc.poll() is None and time.monotonic() < deadline, proc.stderr.read()
        time.sleep(0.05)
    workers = _children(proc.pid)
    assert workers, "no worker processes"
    if sig == "SIGTERM":
        proc.send_signal(signal.SIGTERM)
    else:
        os.killpg(proc.pid, signal.SIGINT)
    code = proc.wait(timeout=60)
    deadline = time.monotonic() + 15
    while _running_with(str(out)) and time.monotonic() < deadline:
        time.sleep(0.1)
    alive = _running_with(str(out))  # the workers seen, and any the pool started while it stopped
    assert not alive, f"workers {alive} outlived the command"
    err = proc.stderr.read()  # every writer of the pipe has ended
    assert code == (143 if sig == "SIGTERM" else 130) and "Traceback" not in err, err
    assert not [p for p in out.rglob(".*") if p.is_file()], "temporary files left behind"
    code, err = cli("data", "build", "--recipe", recipe, "--out", out)
    assert code == 0, err
    assert json.loads((out / "manifest.json").read_text())["complete"]


@pytest.mark.parametrize("sig", ["SIGTERM", "SIGINT"])
def test_a_signal_during_sample_leaves_the_earlier_maps(tmp_path, sig):
    import signal
    import time

    out = tmp_path / "s"
    code, err = cli("sample", "--sd", SD_PNG, "--steps", 2, "--quiet", "--out", out)
    assert code == 0, err
    before = snapshot(out)
    proc = _subprocess("sample", "--sd", SD_PNG, "--num", 64, "--steps", 50, "--out", out)
    time.sleep(8)  # the model loaded, the maps being denoised
    assert proc.poll() is None, proc.stderr.read()
    proc.send_signal(getattr(signal, sig))
    err = proc.communicate(timeout=60)[1]
    assert proc.returncode == (143 if sig == "SIGTERM" else 130) and "Traceback" not in err, err
    assert snapshot(out) == before
    assert not [p for p in out.iterdir() if p.name.startswith(".")], "temporary files left behind"


@pytest.mark.parametrize("sig", ["SIGTERM", "SIGINT"])
def test_a_stop_inside_a_constructor_ends_quietly(sig):
    """A stop that lands inside a constructor leaves a half-made object whose finalizer fails (a Rerun stream without
    its ``inner``: the suite saw it as SIGTERM reached `train rvae`): the command ends with the stop's exit code,
    and nothing is printed but the one line."""
    script = ("import os, signal\nfrom cmtool.cli import cli, main\n"
              "class Half:\n"
              f"    def __init__(self):\n        os.kill(os.getpid(), signal.{sig})\n        self.inner = 1\n"
              "    def __del__(self):\n        self.inner\n"
              "@cli.command('work')\ndef work():\n    Half()\n"
              "main(['work'])\n")
    done = _python(script)
    assert done.returncode == (143 if sig == "SIGTERM" else 130), done.stderr
    assert done.stderr.strip() == ("Terminated." if sig == "SIGTERM" else "Aborted."), done.stderr


def test_sigterm_during_training_resumes(run, tmp_path):
    """SIGTERM while a run trains: a clean exit; the checkpoints it has are whole, and --resume finishes it."""
    import signal
    import time

    out = tmp_path / "run"
    proc = _subprocess("train", "rvae", "--recipe", _longer(run, tmp_path / "long.toml", 400), "--quiet", "--out", out)
    deadline = time.monotonic() + 300
    while not list(out.glob("checkpoints/step_*")):
        assert proc.poll() is None and time.monotonic() < deadline, proc.stderr.read()
        time.sleep(0.1)
    proc.send_signal(signal.SIGTERM)
    err = proc.communicate(timeout=120)[1]
    assert proc.returncode == 143 and "Traceback" not in err, err
    assert not list(out.glob("checkpoints/.*")), "a half-written checkpoint folder"
    last = max(int(p.name.split("_")[1]) for p in out.glob("checkpoints/step_*"))
    code, err = cli("train", "rvae", "--recipe", _longer(run, tmp_path / "more.toml", last + 2), "--quiet", "--resume",
                    "--out", out)
    assert code == 0, err
    assert (out / "checkpoints" / f"step_{last + 2:08d}").is_dir()


def test_a_stop_waits_at_most_the_grace_period():
    """SIGTERM while the command is inside one long call into C (where Python cannot run its handler): the process
    still ends, with exit 143, within the grace period."""
    import signal
    import subprocess
    import sys
    import time

    from cmtool.cli import _Watchdog

    busy = ("import numpy as np\nfrom cmtool.cli import cli, main\n@cli.command('busy')\ndef busy():\n"
            "    print('busy', flush=True)\n    np.linalg.svd(np.random.default_rng(0).random((4000, 4000)))\n"
            "main(['busy'])\n")
    proc = subprocess.Popen([sys.executable, "-c", busy], cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    assert proc.stdout.readline().strip() == "busy"
    time.sleep(0.5)
    began = time.monotonic()
    proc.send_signal(signal.SIGTERM)
    err = proc.communicate(timeout=120)[1]
    assert proc.returncode == 143 and "Traceback" not in err, err
    assert time.monotonic() - began < _Watchdog.GRACE_S + 5


def test_a_stopped_pooled_sample_run_leaves_nothing_and_runs_again_to_the_same_files(sampling_ckpt, tmp_path):
    """SIGTERM to `sample` while its worker processes check the maps: exit 143 with no traceback, no worker left, no
    file and no temporary in OUT; the same command then writes the files of a run never stopped."""
    import json
    import signal
    import time

    from cmtool.maps.hdmap import HDMap

    hd = tmp_path / "sgp.json"
    assert cli("data", "synth", "--city", "SGP", "--seed", 2, "--extent", 300, "--out", hd)[0] == 0
    poses = tmp_path / "poses.jsonl"
    poses.write_text("".join(json.dumps({"x": l.centerline[0][0], "y": l.centerline[0][1], "yaw": 0.0}) + "\n"
                             for l in list(HDMap.load(hd).lanes.values())[:60]))
    args = ("sample", "--ckpt", sampling_ckpt["controlmap"], "--from-hd", hd, "--pose", poses, "--steps", 2,
            "--batch", 2, "--workers", 2, "--no-log", "--quiet", "--out")
    out = tmp_path / "out"
    proc = _subprocess(*args, out)
    deadline = time.monotonic() + 120
    while len(_children(proc.pid)) < 2:
        assert proc.poll() is None and time.monotonic() < deadline, proc.stderr.read()
        time.sleep(0.02)
    workers = _children(proc.pid)
    proc.send_signal(signal.SIGTERM)
    code = proc.wait(timeout=60)
    err = proc.stderr.read()
    assert code == 143 and "Traceback" not in err, err

    def alive():  # a worker the stop found still starting ends a moment after the process that started it
        return [pid for pid in workers if Path(f"/proc/{pid}").exists()
                and Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"]

    deadline = time.monotonic() + 30
    while alive() and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not alive() and not (out.exists() and any(out.iterdir())), (alive(), out.exists() and list(out.iterdir()))
    assert cli(*args, out)[0] == 0
    assert cli(*args[:-5], "--workers", 1, "--no-log", "--quiet", "--out", tmp_path / "unbroken")[0] == 0
    made = {p.name: p.read_bytes() for p in sorted(out.iterdir())}
    assert len(made) == 180 and made == {p.name: p.read_bytes() for p in sorted((tmp_path / "unbroken").iterdir())}


def test_a_worker_stopped_inside_a_finalizer_still_stops_quietly():
    """SIGTERM landing in a ``__del__`` (where Python prints the exception and goes on): the worker stops a moment
    later where it can unwind, with no "Exception ignored" traceback (the pool's termination would wait for it)."""
    script = ("import os, signal, time\n"
              "from cmtool.core import workers\n"
              "workers._worker_signals(None)\n"
              "class Finalized:\n"
              "    def __del__(self):\n"
              "        os.kill(os.getpid(), signal.SIGTERM)\n"
              "try:\n"
              "    Finalized()\n"
              "    time.sleep(5)\n"
              "    print('still running')\n"
              "except SystemExit as e:\n"
              "    print('stopped', e.code)\n")
    done = _python(script)
    assert done.stdout.strip() == "stopped 143" and "Traceback" not in done.stderr, done.stderr


def test_a_worker_whose_finally_replaces_the_stop_still_ends_quietly():
    """SIGTERM landing where a ``finally`` puts another error in its place (numpy's savez when the stop lands in a
    zip member's write: CI saw it), and the half-made object's finalizer failing after: the worker still ends, soon
    and unprinted, so leaving the pool does not wait on it (it took its next task and the command hung)."""
    from cmtool.core import workers

    script = ("import time\n"
              "from cmtool.core import workers\n"
              "class HalfWritten:\n"
              "    def __del__(self):\n"
              "        raise ValueError('seek of closed file')\n"
              "def task(_):\n"
              "    half = HalfWritten()\n"
              "    try:\n"
              "        time.sleep(30)\n"
              "    finally:\n"
              "        raise ValueError('the stop replaced')\n"
              "began = time.monotonic()\n"
              "try:\n"
              "    with workers.pool(1, 'fork') as p:  # left by an error: the workers are terminated\n"
              "        p.map_async(task, [0, 1, 2])\n"
              "        time.sleep(1)\n"
              "        raise LookupError\n"
              "except LookupError:\n"
              "    print('left', round(time.monotonic() - began))\n")
    done = _python(script)
    assert done.stdout.startswith("left") and "Traceback" not in done.stderr, done.stderr
    assert int(done.stdout.split()[1]) < 1 + workers.STOP_S + 20, done.stdout


def test_workers_a_pool_terminates_are_not_the_users_signal():
    """Leaving a pool by an error while its workers are busy terminates them with SIGTERM; the command goes on past
    the watchdog's grace period (issue 58: `train pipeline` and `data build` ended themselves with 143 ten seconds
    later)."""
    script = ("import time\nfrom cmtool.cli import cli, main, _Watchdog\nfrom cmtool.core import workers\n"
              "_Watchdog.GRACE_S = 1.0\n"
              "@cli.command('work')\ndef work():\n"
              "    try:\n        with workers.pool(2, 'fork') as p:\n"
              "            p.map_async(time.sleep, [30, 30])\n            time.sleep(1)\n            raise LookupError\n"
              "    except LookupError:\n        time.sleep(4)\n        print('finished', flush=True)\n"
              "main(['work'])\n")
    result = _python(script)
    assert result.returncode == 0 and result.stdout.strip() == "finished", result.stderr


def test_a_terminated_pool_kills_a_worker_that_does_not_end():
    """A worker that outlives its SIGTERM (as one the termination found starting, waiting for ever on the task
    queue's lock) is killed a few seconds later: leaving the pool by an error returns, and no worker is left."""
    script = ("import os, signal, time\nfrom cmtool.core import workers\n"
              "def deaf():\n    signal.signal(signal.SIGTERM, signal.SIG_IGN)\n"
              "try:\n    with workers.pool(2, 'fork', deaf) as p:\n"
              "        pids = [w.pid for w in p._pool]\n        p.map_async(time.sleep, [60, 60])\n"
              "        time.sleep(1)\n        raise LookupError\n"
              "except LookupError:\n    pass\n"
              "print('left', all(not os.path.exists(f'/proc/{pid}') or open(f'/proc/{pid}/stat').read().split()[2]"
              " == 'Z' for pid in pids), flush=True)\n")
    result = _python(script)
    assert result.returncode == 0 and result.stdout.strip() == "left True", result.stderr



@pytest.mark.parametrize("wait, cause", [
    ("p.apply_async(signal.raise_signal, (signal.SIGKILL,)).get()",
     "a worker process was killed (SIGKILL, out of memory?)"),
    ("p.map(os._exit, [3])", "a worker process ended unexpectedly (exit status 3)"),
    ("list(p.imap(signal.raise_signal, [signal.SIGKILL]))", "a worker process was killed (SIGKILL, out of memory?)"),
    ("p.map(abs, [-1])", "a worker process could not start: no space left on device")],
    ids=["killed", "exited", "killed-in-imap", "full-disk-at-start"])
def test_a_worker_that_dies_ends_the_pool_at_once_naming_the_cause(wait, cause):
    """A worker that dies while another works on (killed, exited, or its start failed writing to a full disk): the
    wait for its task ends within seconds with one error naming the cause, and nothing printed (multiprocessing
    started a worker in its place, or another that failed again, and the wait went on for ever)."""
    start = "pathlib.Path('/dev/full').write_text" if "abs" in wait else "None"
    script = ("import os, pathlib, signal, time\nfrom cmtool.core import workers\n"
              "began = time.monotonic()\ntry:\n"
              f"    with workers.pool(2, 'spawn', {start}, ('x',)) as p:\n"
              f"        p.apply_async(time.sleep, (60,))\n        {wait}\n"
              "except Exception as e:\n    print(type(e).__name__, round(time.monotonic() - began), e, sep='|')\n")
    done = _python(script)
    kind, seconds, message = done.stdout.strip().split("|")
    assert (kind, message) == ("CmtoolError", cause) and done.stderr == "", done.stderr
    assert int(seconds) < 15


@pytest.mark.parametrize("held", ["", "        p._outqueue._wlock.acquire()\n"], ids=["waiting", "sending"])
def test_a_pool_whose_waiting_workers_were_killed_still_ends(held):
    """Workers killed while they waited for a task (one of them holding the task queue's lock, for ever), or as one
    sent its result (holding the results' lock: held here by the test): leaving the pool by an error returns within
    seconds (its termination waited for either lock for ever; the second hung a loaded suite run)."""
    script = ("import os, signal, time\nfrom cmtool.core import workers\nbegan = time.monotonic()\ntry:\n"
              "    with workers.pool(2, 'spawn') as p:\n        p.map(abs, [-1, -2])\n" + held +
              "        for w in list(p._pool):\n            os.kill(w.pid, signal.SIGKILL)\n"
              "        time.sleep(0.5)\n        raise LookupError\n"
              "except LookupError:\n    print('left', round(time.monotonic() - began), flush=True)\n")
    done = _python(script)
    assert done.stdout.startswith("left") and int(done.stdout.split()[1]) < 15, done.stderr


def test_ctrl_c_while_the_workers_start_prints_nothing_from_them():
    """Ctrl-C reaching the workers while they start (here: as they import torch for their initializer): none prints a
    KeyboardInterrupt traceback or dies; the pool's tasks are done."""
    script = ("import os, signal, time\nfrom cmtool.core import dist, workers\n"
              "with workers.pool(2, 'spawn', dist.barrier) as p:\n    time.sleep(0.5)\n"
              "    for w in list(p._pool):\n        os.kill(w.pid, signal.SIGINT)\n"
              "    print(p.map(abs, [-1, -2, -3]), flush=True)\n")
    done = _python(script)
    assert done.stdout.strip() == "[1, 2, 3]" and done.stderr == "", done.stderr


def test_a_killed_pooled_sample_run_leaves_nothing_after_the_next_run(sampling_ckpt, tmp_path):
    """`sample --workers 2` killed (SIGKILL) while its files are staged: its temporary files in OUT and its jobs file
    in the temporary folder are removed by the next run of the command, which leaves neither of its own."""
    import json
    import os
    import signal
    import subprocess
    import sys
    import time

    from cmtool.maps.hdmap import HDMap

    hd = tmp_path / "sgp.json"
    assert cli("data", "synth", "--city", "SGP", "--seed", 2, "--extent", 300, "--out", hd)[0] == 0
    poses = tmp_path / "poses.jsonl"
    poses.write_text("".join(json.dumps({"x": l.centerline[0][0], "y": l.centerline[0][1], "yaw": 0.0}) + "\n"
                             for l in list(HDMap.load(hd).lanes.values())[:60]))
    out, temporary = tmp_path / "out", tmp_path / "tmp"
    temporary.mkdir()
    command = [sys.executable, "-m", "cmtool", "sample", "--ckpt", sampling_ckpt["controlmap"], "--from-hd", hd,
               "--pose", poses, "--steps", 2, "--batch", 2, "--workers", 2, "--no-log", "--quiet", "--out", out]
    env = os.environ | {"OMP_NUM_THREADS": "1", "TMPDIR": str(temporary)}
    proc = subprocess.Popen(list(map(str, command)), cwd=REPO, env=env, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 120
    while len(list(out.glob(".cmtool-*.tmp"))) < 3 or not list(temporary.glob("cmtool-run-*/jobs.pickle")):
        assert proc.poll() is None and time.monotonic() < deadline, proc.stderr.read()
        time.sleep(0.02)
    proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=60)
    assert list(out.glob(".cmtool-*.tmp")) and list(temporary.iterdir())
    done = subprocess.run(list(map(str, command)), cwd=REPO, env=env, capture_output=True, text=True, timeout=300,
                          check=False)
    assert done.returncode == 0, done.stderr
    assert not list(out.glob(".*")) and not list(temporary.iterdir()), (list(out.glob(".*")), list(temporary.iterdir()))
    assert len(list(out.iterdir())) == 180

# --- Reliability 4 (issue 57): no wrong or lost output with exit 0 -------------------------------------------------

def test_a_resumed_area_run_makes_the_unbroken_runs_map_byte_for_byte(tmp_path, monkeypatch):
    """An area run stopped after two batches of tiles, one of them then left with fewer tiles than the batch size (as
    a damaged cache holds): the same command makes the unbroken run's map, byte for byte (with one worker checking
    the tiles, the stopped and resumed runs with three)."""
    import cmtool.sample.area as area_module

    hd = tmp_path / "pit.json"
    code, err = cli("data", "synth", "--city", "PIT", "--seed", 0, "--extent", 300, "--out", hd)
    assert code == 0, err
    args = ("sample", "--from-hd", hd, "--area", "90,90,210,210", "--batch", 2, "--steps", 2, "--no-log", "--quiet")
    code, err = cli(*args, "--out", tmp_path / "whole", "--workers", 1)  # the others: 3 workers
    assert code == 0, err
    args += ("--workers", 3)
    real = interrupted_at(monkeypatch, area_module, "write_jsonl", 3)  # as the third batch is kept
    assert cli(*args, "--out", tmp_path / "broken")[0] == 130
    monkeypatch.setattr(area_module, "write_jsonl", real)
    batch = tmp_path / "broken" / ".pit_area.tiles" / "b0000002.jsonl"
    batch.write_text(batch.read_text().splitlines(keepends=True)[0])
    code, err = cli(*args, "--out", tmp_path / "broken")
    assert code == 0, err
    assert (tmp_path / "broken" / "pit_area.json").read_bytes() == (tmp_path / "whole" / "pit_area.json").read_bytes()


@pytest.mark.parametrize("env", [{"RANK": "1"}, {"RANK": "abc"}, {"WORLD_SIZE": "2"},
                                 {"RANK": "2", "WORLD_SIZE": "2", "LOCAL_RANK": "0", "MASTER_ADDR": "127.0.0.1",
                                  "MASTER_PORT": "29500"},
                                 {"RANK": "0", "WORLD_SIZE": "2", "LOCAL_RANK": "0", "MASTER_ADDR": "127.0.0.1",
                                  "MASTER_PORT": "junk"},
                                 {"RANK": "0", "WORLD_SIZE": "2", "LOCAL_RANK": "0", "MASTER_ADDR": "",
                                  "MASTER_PORT": "29500"}],
                         ids=["rank-alone", "rank-abc", "world-alone", "rank-2-of-2", "port-junk", "address-empty"])
def test_a_torchrun_environment_that_does_not_fit_is_one_line(tmp_path, monkeypatch, env):
    """Variables of torchrun without torchrun (or numbers that do not fit together, or a port or address torch cannot
    read): refused, nothing written (`RANK=1` alone made `sample` exit 0 as a process whose maps the main one writes;
    `MASTER_PORT=junk` gave a ValueError traceback from torch's rendezvous)."""
    for key, value in env.items():
        monkeypatch.setenv(key, value)
    check(*cli("sample", *SD_ARGS, "--out", tmp_path / "s"), "RANK")
    assert not (tmp_path / "s").exists()


def test_an_extract_across_the_antimeridian_keeps_its_lengths_and_places(tmp_path):
    """A 600 m road east-west across 180 and a road on either side: the road stays 600 m long and runs east, a box
    across 180 is that box (not the whole extract), and the GeoJSON export's longitudes stay in [-180, 180]."""
    import math

    from cmtool.formats.osm import read_osm

    half = 300 / (111320 * math.cos(math.radians(-16.5)))  # degrees of longitude for 300 m
    osm = tmp_path / "fiji.osm"
    osm.write_text(_osm({1: (-16.5, 180 - half), 2: (-16.5, -180 + half), 3: (-16.51, 179.9), 4: (-16.52, 179.9),
                         5: (-16.51, -179.99), 6: (-16.52, -179.99)}, {10: [1, 2], 11: [3, 4], 12: [5, 6]}))
    sd = read_osm(osm)
    road = next(r.polyline for r in sd.roads if r.id == "w10")
    assert np.linalg.norm(road[-1] - road[0]) == pytest.approx(600, abs=1) and abs(road[-1, 1] - road[0, 1]) < 0.5
    code, err = cli("sample", "--osm", osm, "--area", f"-16.499,{180 - half},-16.501,{-180 + half}", *SD_ARGS[2:],
                    "--out", tmp_path / "a")
    assert code == 0, err
    area = json.loads((tmp_path / "a" / "fiji_area.json").read_text())
    x0, _, x1, _ = area["meta"]["area"]["box_m"]
    assert x1 - x0 == pytest.approx(600, abs=1)
    code, err = cli("export", "--format", "geojson", tmp_path / "a" / "fiji_area.json", "--out", tmp_path / "a.geojson")
    assert code == 0, err
    lons = [p[0] for f in json.loads((tmp_path / "a.geojson").read_text())["features"]
            for p in np.array(f["geometry"]["coordinates"]).reshape(-1, 2)]
    assert max(lons) <= 180 and min(lons) >= -180 and max(lons) > 179.99 and min(lons) < -179.99


def test_export_verify_counts_every_successor_join(tmp_path):
    """A lane graph with 3 successor joins, 2 of them self-loops: Lanelet2's verdict counts all 3 and names the one
    its export does not route (it reported "routes the lane graph's 1 successor joins" and wrote the file)."""
    pytest.importorskip("lanelet2", reason="the lanelet2 wheel (the verify extra)")
    graph = tmp_path / "loops.json"
    graph.write_text(json.dumps({"format": "cmtool.lanegraph", "version": 1, "lanes": [[[-20, 0], [0, 0]],
                                                                                       [[0, 0], [20, 0]]],
                                 "successors": [[0, 1], [0, 0], [1, 1]]}))
    check(*cli("export", "--format", "lanelet2", graph, "--origin", "60,25", "--out", tmp_path / "l.osm", "--verify"),
          "1 of its 3 successor joins not routed [(0, 0)]")
    assert not (tmp_path / "l.osm").exists()


def test_an_area_holds_every_road_it_crosses(tmp_path):
    """`--area all` on one short road makes its lanes (the box was a line of no height: 0 lanes, validity 1.000); a
    road crossing a box with no vertex inside is in the area; a box holding the whole extract is the whole extract."""
    from cmtool.formats.osm import read_osm
    from cmtool.sample.area import area_box

    short = tmp_path / "short.osm"
    short.write_text(_osm({1: (60.0, 24.9), 2: (60.0, 24.9018)}, {10: [1, 2]}))
    code, err = cli("sample", "--osm", short, "--area", "all", *SD_ARGS[2:], "--out", tmp_path / "s")
    assert code == 0, err
    assert json.loads((tmp_path / "s" / "short_area.json").read_text())["lanes"]
    long = tmp_path / "long.osm"
    long.write_text(_osm({1: (60.0, 24.9), 2: (60.0, 24.95), 3: (60.01, 24.9), 4: (60.01, 24.95)},
                         {10: [1, 2], 11: [3, 4]}))
    sd = read_osm(long)
    assert area_box(sd, "59.999,24.92,60.001,24.93")  # no vertex within 1 km of the box
    whole = area_box(sd, "all")
    for spec in ("-90,-180,90,180", "50,10,70,40"):
        assert np.allclose(area_box(sd, spec), whole, atol=0.1), spec


def test_a_legal_long_output_name_is_written(tmp_path):
    """A 250-byte file name (255 is the limit): its temporary file beside it is named short, and renamed into it."""
    graph = tmp_path / "g.json"
    graph.write_text(json.dumps({"format": "cmtool.lanegraph", "version": 1, "lanes": [[[0, 0], [20, 0]]]}))
    out = tmp_path / ("a" * 242 + ".geojson")
    code, err = cli("export", "--format", "geojson", graph, "--origin", "60,25", "--out", out)
    assert code == 0, err
    assert json.loads(out.read_text())["type"] == "FeatureCollection"
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(["g.json", out.name])


@pytest.mark.parametrize("north", [0.0, 0.000004])
def test_an_osm_road_of_one_spot_is_refused_not_laid(tmp_path, north):
    """Issue 66: an OpenStreetMap file whose only road has zero length, or is 0.44 m long, gives one line naming the
    length, not a map made from nothing."""
    (tmp_path / "spot.osm").write_text(
        '<?xml version="1.0" encoding="UTF-8"?>\n<osm version="0.6">\n<node id="1" lat="48.0" lon="11.0"/>\n'
        f'<node id="2" lat="{48.0 + north}" lon="11.0"/>\n<way id="10"><nd ref="1"/><nd ref="2"/>'
        '<tag k="highway" v="residential"/></way>\n</osm>\n')
    code, err = cli("sample", "--osm", tmp_path / "spot.osm", "--center", "48.0,11.0", "--steps", 2, "--no-log",
                    "--out", tmp_path / "out")
    assert code == 1 and err.count("\n") == 1 and "no road to lay lanes on" in err, err
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())


def test_an_area_of_nearly_the_whole_globe_around_a_small_map_holds_it():
    """Issue 66: --area -89,-179,89,179 around a small map holds its every road (the longitudes span the way round
    that holds the map), where it was read as the 2 degrees across 180 and refused."""
    from cmtool.formats.osm import read_osm
    from cmtool.sample.area import area_box

    sd = read_osm(TOWN)
    every = np.concatenate([r.polyline for r in sd.roads])
    x0, y0, x1, y1 = area_box(sd, "-89,-179,89,179")
    assert x0 <= every[:, 0].min() and y0 <= every[:, 1].min() and x1 >= every[:, 0].max() and y1 >= every[:, 1].max()
