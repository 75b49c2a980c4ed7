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
import resource
import shutil
import zipfile
from pathlib import Path

import numpy as np
import pytest

from tests.conftest import REPO, SHARED_DATA

pytestmark = pytest.mark.usefixtures("one_thread")

AV2 = next(iter(sorted((SHARED_DATA / "av2").rglob("log_map_archive_*.json"))), None)
LANELET2 = next(iter(sorted((SHARED_DATA / "lanelet2").rglob("*.osm"))), None)
SD_PNG = REPO / "sample_data" / "sd_bos.png"
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
                        "pack": "pack --ckpt BAD --out {out}/pk"}.items()
      if (cmd, bad) != ("info", "badweights")],  # info reads the config alone
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


def test_eval_killed_midway_resumes_to_the_same_numbers(ws, tmp_path):
    """kill -9 while `cmtool eval` generates maps, then the same command again: it continues from its cache and
    ends with the metrics of a run never interrupted."""
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
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    assert not (killed / "metrics.json").exists()
    code, err = cli(*args, "--out", killed)
    assert code == 0, err
    numbers = [json.loads((run / "metrics.json").read_text()) for run in (killed, whole)]
    for result in numbers:
        for method in result["methods"].values():
            method.pop("seconds")  # timings differ
    assert numbers[0] == numbers[1]
