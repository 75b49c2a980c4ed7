"""`cmtool eval` end to end on a tiny dataset: both methods, reports, recording, resumable cache."""

import json

import pytest
from rerun.chunk import RrdReader

from cmtool.formats.sumo import netconvert_path
from tests.conftest import in_process

pytestmark = pytest.mark.usefixtures("one_thread")




def test_eval_writes_reports_and_resumes(sampling_ckpt, tiny_data, tmp_path, capsys):
    out = tmp_path / "eval"
    args = ("eval", "--ckpt", sampling_ckpt["controlmap"], "--data", tiny_data, "--steps", 2, "--batch", 4,
            "--out", out, "--no-features", "--rrd-samples", 2, "--quiet")
    code, stdout, err = in_process(capsys, *args, "--n", 4)
    assert code == 0, err
    report = json.loads((out / "metrics.json").read_text())
    baselines = ["rules"] + (["netconvert"] if netconvert_path() else [])
    assert list(report["methods"]) == ["unguided", *baselines, "controlmap", "guaranteed"]
    assert report["settings"]["n"] == 4
    for m in report["methods"].values():
        assert m["scenes"] == 4 and 0.0 <= m["geometry"]["lane_f1"]["mean"] <= 1.0
        assert set(m["topology_fd"]) == {"connectivity", "density", "reach", "convenience"}
        assert 0.0 <= m["geometry"]["validity"]["mean"] <= 1.0
        geo = m["geometry"]
        assert all(v >= 0 and v == int(v) for k in ("dangling", "crossings") for v in geo[k]["per_scene"])
        assert geo["legal_oneway"]["mean"] != geo["legal_oneway"]["mean"] or 0.0 <= geo["legal_oneway"]["mean"] <= 1.0
    assert 0.0 < report["ground_truth_validity"] <= 1.0
    summary = (out / "summary.md").read_text()
    assert f"| metric | unguided | {' | '.join(baselines)} | ControlMap | + guarantee |" in summary
    assert "split test, 4 scenes" in summary
    assert "- data `tiny`" in summary and "`/" not in summary  # no folder of this machine
    legal = [report["methods"][m]["geometry"]["legal_oneway"]["mean"] for m in ("controlmap", "guaranteed")]
    assert not all(v == v for v in legal) or legal[1] >= legal[0]  # the guarantee turns wrong-way lanes round
    frames = report["frames"]
    assert sum(frames["scenes"].values()) == 4 and set(frames["lane_f1"]) == set(report["methods"])
    assert frames["lanes_per_map"]["rules"] > 0 and "| lane F1 @1 m, junction frames" in summary
    assert (out / "gallery.png").stat().st_size > 0
    assert "| validity score ↑ |" in summary and "validity score of the ground truth itself" in summary
    assert "| lanes joined to nothing, per map ↓ |" in summary and "| lane crossings outside junctions, per map ↓ |" \
        in summary and "| lane length on one-way SD roads running the legal way ↑ |" in summary
    assert "| lane F1 @1 m ↑ |" in stdout
    assert "- lanes: least-squares Bézier curves with 6 control points" in summary
    # the decisions on the SD roads: junction movements against the truth's, lane length no SD road explains
    made = report["decisions"]
    assert list(made) == [*report["methods"], "truth"]
    truth = made["truth"]
    assert truth["truth_movements"] > 0 and truth["movement_f1"] == 1.0 and truth["unexplained_share"] < 0.05
    for m, d in made.items():
        assert d["true_movements"] <= min(d["movements"], d["truth_movements"]) and d["lane_m"] > 0, m
        assert d["truth_movements"] == truth["truth_movements"], m
        assert d["movement_precision"] == (d["true_movements"] / d["movements"] if d["movements"] else 1.0), m
        assert d["movement_recall"] == d["true_movements"] / d["truth_movements"], m
        assert 0.0 <= d["unexplained_share"] <= 1.0, m
    assert made["rules"]["movement_recall"] > 0.5  # the rules make every legal movement
    assert made["guaranteed"]["unexplained_share"] <= made["controlmap"]["unexplained_share"]
    assert made["guaranteed"]["unexplained_share"] < 0.05  # every composed lane lies on an SD road
    head = f"### Decisions on the SD roads ({truth['truth_movements']} junction movements in the ground truth of the 4"
    for text in (summary, stdout):
        assert head in text and "| junction movements, F1 ↑ |" in text
    rows = {line.split(" | ")[0]: line.split(" | ")[1:] for line in summary.splitlines() if line.startswith("| ")}
    assert rows["| junction movements, precision ↑"][1] == f"{made['rules']['movement_precision']:.3f}"
    assert rows["| junction movements, recall ↑"][-1] == "1 |"
    assert rows["| share of the lane length no SD road explains ↓"] == [
        f"{made[m]['unexplained_share']:.3f}" for m in made][:-1] + [f"{truth['unexplained_share']:.3f} |"]
    first = (out / "cache" / "controlmap.jsonl").read_text().splitlines()
    # more scenes later: the first batch comes from the cache, unchanged
    code, _, err = in_process(capsys, *args, "--n", 8)
    assert code == 0, err
    lines = (out / "cache" / "controlmap.jsonl").read_text().splitlines()
    assert len(lines) == 8 and lines[:4] == first
    rows = {}
    for chunk in RrdReader(out / "eval.rrd").stream():
        batch = chunk.to_record_batch()
        if "sample" in batch.schema.names:
            rows.setdefault(chunk.entity_path, set()).update(batch.column("sample").to_pylist())
    assert rows["/metrics/lane_f1/controlmap"] == set(range(8)) == rows["/metrics/lane_f1/unguided"]
    assert rows["/scene/controlmap/hd/lanes"] == {0, 1} == rows["/scene/truth/hd/lanes"]  # --rrd-samples 2
    # a run in one go scores exactly what the resumed one did
    code, _, err = in_process(capsys, *args[:-5], tmp_path / "whole", "--no-features", "--rrd-samples", 2, "--quiet",
                              "--n", 8)
    assert code == 0, err
    scores = [{m: {k: v for k, v in r.items() if k != "seconds"} for m, r in
               json.loads((d / "metrics.json").read_text())["methods"].items()} for d in (tmp_path / "whole", out)]
    assert scores[0] == scores[1]
    # the metrics' timing on those maps, tiled
    code, stdout, err = in_process(capsys, "bench", "metrics", "--eval", tmp_path / "whole", "--tile", 2,
                                   "--repeats", 1, "--no-features")
    assert code == 0, err
    assert "16 scene pairs, 1 repeats" in stdout and "| validity |" in stdout and "| all of `evaluate` |" in stdout
    code, _, err = in_process(capsys, "bench", "metrics", "--eval", tmp_path)
    assert code == 1 and "no eval cache here" in err
    # the cache refuses to mix settings
    code, _, err = in_process(capsys, *args, "--n", 8, "--cfg", 0.5)
    assert code == 1 and "made with other settings (cfg)" in err
    code, _, err = in_process(capsys, *args, "--n", 8, "--smooth", 0)
    assert code == 1 and "made with other settings (smooth)" in err
    # ... and a cache from before the step noise had its own stream (no "noise" entry)
    meta = json.loads((out / "cache" / "settings.json").read_text())
    (out / "cache" / "settings.json").write_text(json.dumps({k: v for k, v in meta.items() if k != "noise"}))
    code, _, err = in_process(capsys, *args, "--n", 8)
    assert code == 1 and "made with other settings (noise)" in err


def test_the_guarantee_of_eval_maps_is_the_same_in_worker_processes(tiny_data):
    from cmtool.core.workers import each
    from cmtool.data.cache import load_dataset, scene_sd_maps
    from cmtool.eval.evaluation import as_sampled
    from cmtool.sample import DEFAULT_COUNTS
    from cmtool.sample.checks import guaranteed

    data = load_dataset(tiny_data, "test")
    scenes = [data.scene(i) for i in range(min(6, len(data)))]
    maps = [s.to_lanegraph() for s in scenes]
    items = [(m, s, sd_map, DEFAULT_COUNTS) for m, s, sd_map in zip(maps, scenes, scene_sd_maps(tiny_data, "test"))]
    here, pooled = as_sampled(maps, tiny_data, "test", scenes), each(guaranteed, items, 3)
    assert len(here) == len(scenes) and [g.to_json() for g in here] == [g.to_json() for g in pooled]


def test_unguided_and_guided_differ_only_by_the_control(sampling_ckpt, tiny_data, tmp_path, capsys):
    out = tmp_path / "w0"
    code, _, err = in_process(capsys, "eval", "--ckpt", sampling_ckpt["controlmap"], "--data", tiny_data, "--n", 4,
                          "--steps", 2, "--batch", 4, "--cfg", 0, "--out", out, "--no-features", "--quiet")
    assert code == 0, err
    unguided = [json.loads(l)["lanes"] for l in (out / "cache" / "unguided.jsonl").read_text().splitlines()]
    guided = [json.loads(l)["lanes"] for l in (out / "cache" / "controlmap.jsonl").read_text().splitlines()]
    # w = 0 ignores the SD control; the scenes' cities (BOS) are unknown to the checkpoint -> null label too
    assert unguided == guided


def test_eval_needs_a_controlmap(sampling_ckpt, tiny_data, tmp_path, capsys):
    code, _, err = in_process(capsys, "eval", "--ckpt", sampling_ckpt["dit"], "--data", tiny_data, "--out", tmp_path / "x",
                          "--no-features")
    assert code == 1 and "give a ControlMap checkpoint" in err


def test_ablations_write_tables_pictures_and_recording(sampling_ckpt, tiny_data, tmp_path, capsys):
    common = ("--ckpt", sampling_ckpt["controlmap"], "--data", tiny_data, "--n", 3, "--steps", 2, "--out", tmp_path,
              "--quiet")
    code, out, err = in_process(capsys, "ablate", "cfg", *common, "--w", "0,0.5,1", "--seeds", 2, "--no-features")
    assert code == 0, err
    sweep = json.loads((tmp_path / "ablate_cfg.json").read_text())
    assert [r["w"] for r in sweep["rows"]] == [0.0, 0.5, 1.0]
    assert all(r["diversity_m"] > 0 for r in sweep["rows"])  # two seeds give two different maps
    assert (tmp_path / "ablate_cfg.png").stat().st_size > 0 and "| w | sd_coverage |" in out
    steps = set()
    for chunk in RrdReader(tmp_path / "ablate_cfg.rrd").stream():
        batch = chunk.to_record_batch()
        if chunk.entity_path == "/metrics/sd_coverage":
            steps.update(batch.column("cfg").to_pylist())
    assert steps == {0, 500, 1000}
    code, out, err = in_process(capsys, "ablate", "city-swap", *common, "--labels", "SGP,LAV")
    assert code == 0, err
    swap = json.loads((tmp_path / "ablate_city_swap.json").read_text())
    rows = swap["rows"]
    assert [r["label"] for r in rows] == ["SGP", "LAV"] and [r["drives_on"] for r in rows] == ["left", "right"]
    assert swap["sampler"] == sweep["sampler"] == "ddpm-trailing"  # the default: every step draws fresh noise ...
    again = tmp_path / "again"
    code, _, err = in_process(capsys, "ablate", "city-swap", *common[:-3], "--out", again, "--quiet",
                              "--labels", "SGP,LAV")
    assert code == 0, err
    assert json.loads((again / "ablate_city_swap.json").read_text()) == swap  # ... from the seed
    code, _, err = in_process(capsys, "ablate", "city-swap", *common[:-3], "--out", tmp_path / "city", "--quiet",
                              "--labels", "SGP,LAV", "--city-cfg", 3)
    assert code == 0, err
    guided = json.loads((tmp_path / "city" / "ablate_city_swap.json").read_text())
    assert swap["city_cfg"] == 1.0 and guided["city_cfg"] == 3
    assert all(r["left_hand"] is None or 0.0 <= r["left_hand"] <= 1.0 for r in rows)
    assert all(r["left_hand_oncoming"] is None or 0.0 <= r["left_hand_oncoming"] <= 1.0 for r in rows)
    assert "left_hand_oncoming" in (tmp_path / "ablate_city_swap.md").read_text()
    code, _, err = in_process(capsys, "ablate", "city-swap", *common, "--labels", "SGP,XYZ")
    assert code == 1 and "unknown city 'XYZ'" in err


def test_city_swap_of_a_dit_is_its_controlmap_at_w0(sampling_ckpt, tiny_data, tmp_path, capsys):
    common = ("--data", tiny_data, "--n", 3, "--steps", 2, "--quiet", "--labels", "SGP,LAV")
    code, _, err = in_process(capsys, "ablate", "city-swap", "--ckpt", sampling_ckpt["dit"], *common,
                              "--out", tmp_path / "dit")
    assert code == 0, err
    code, _, err = in_process(capsys, "ablate", "city-swap", "--ckpt", sampling_ckpt["controlmap"], "--cfg", 0,
                              *common, "--out", tmp_path / "w0")
    assert code == 0, err
    rows = [json.loads((tmp_path / d / "ablate_city_swap.json").read_text())["rows"] for d in ("dit", "w0")]
    assert rows[0] == rows[1] and rows[0][0]["oncoming_points"] > 0
    code, _, err = in_process(capsys, "ablate", "cfg", "--ckpt", sampling_ckpt["dit"], *common[:-2],
                              "--out", tmp_path / "x")
    assert code == 1 and "needs a ControlMap checkpoint" in err


def test_ablate_dit_compares_checkpoints_on_the_same_noise(sampling_ckpt, tiny_data, tmp_path, capsys):
    common = ("--data", tiny_data, "--n", 4, "--steps", 2, "--quiet")
    code, out, err = in_process(capsys, "ablate", "dit", "--ckpt", sampling_ckpt["dit"], "--ckpt",
                                sampling_ckpt["controlmap"], *common, "--out", tmp_path / "a")
    assert code == 0, err
    report = json.loads((tmp_path / "a" / "ablate_dit.json").read_text())
    truth, dit, controlmap = report["rows"]
    assert truth["name"] == "ground truth" and truth["fd_density"] == 0.0 and truth["validity"] > 0.9
    assert dit["name"] == "dit" and controlmap["name"] == "controlmap"
    # a ControlMap without its control is its DiT: the same maps from the same noise
    assert {k: v for k, v in dit.items() if k != "name"} == {k: v for k, v in controlmap.items() if k != "name"}
    assert dit["lanes"] > 0 and 0.0 <= dit["validity"] <= 1.0 and dit["dangling"] >= 0 and dit["crossings"] >= 0
    assert "| fd_reach |" in out and (tmp_path / "a" / "ablate_dit.png").stat().st_size > 0
    code, _, err = in_process(capsys, "ablate", "dit", "--ckpt", sampling_ckpt["dit"], *common, "--seed", 1,
                              "--out", tmp_path / "b")
    assert code == 0, err
    other = json.loads((tmp_path / "b" / "ablate_dit.json").read_text())["rows"][1]
    assert other != dit and other["name"] == "dit"


def test_eval_cache_tells_weights_apart_at_the_same_path(sampling_ckpt, tiny_data, tmp_path, capsys):
    import shutil

    from safetensors.torch import load_file, save_file

    from cmtool.model import checkpoint as ckpt

    src = ckpt.resolve(sampling_ckpt["controlmap"])
    cm = tmp_path / "cm"
    shutil.copytree(src, cm)
    config = json.loads((cm / ckpt.CONFIG).read_text())
    config["rvae"] = str(ckpt.resolve(ckpt.linked(src, config["rvae"])))
    (cm / ckpt.CONFIG).write_text(json.dumps(config))
    args = ("eval", "--ckpt", cm, "--data", tiny_data, "--n", 4, "--steps", 2, "--batch", 4, "--out", tmp_path / "e",
            "--no-features", "--rrd-samples", 0, "--quiet")
    code, _, err = in_process(capsys, *args)
    assert code == 0, err
    weights = load_file(str(cm / ckpt.WEIGHTS))  # re-trained (or re-packed) weights in the same folder
    name = next(k for k in weights if k.startswith("zero."))
    weights[name] = weights[name] + 0.01
    save_file(weights, str(cm / ckpt.WEIGHTS))
    code, _, err = in_process(capsys, *args)
    assert code == 1 and "made with other settings (weights)" in err


def test_ablate_rvae_scores_reconstructions_and_the_driving_side(sampling_ckpt, tiny_data, tmp_path, capsys):
    args = ("--data", tiny_data, "--n", 4, "--quiet")
    rvae = ("ablate", "rvae", "--rvae", sampling_ckpt["rvae"])
    code, out, err = in_process(capsys, *rvae, *args, "--out", tmp_path / "a")
    assert code == 0, err
    rows = json.loads((tmp_path / "a" / "ablate_rvae.json").read_text())["rows"]
    assert [(r["split"], r["city"]) for r in rows] == [("train", "LAV"), ("train", "PIT"), ("train", "SGP"),
                                                       ("test", "BOS")]
    assert all(r["scenes"] == 4 and 0.0 <= r["f1"] <= 1.0 for r in rows) and "| f1 |" in out
    assert all(r["f1_0.5m"] <= r["f1"] and 0.0 <= r["validity"] <= 1.0 for r in rows)
    assert all(r["succ_recall"] is None or 0.0 <= r["succ_recall"] <= 1.0 for r in rows) and "succ_precision" in out
    assert all(min(r["succ_precision"], r["succ_recall"]) <= r["succ_f1"] <= max(r["succ_precision"], r["succ_recall"])
               for r in rows if r["succ_precision"] is not None and r["succ_recall"] is not None)
    truth = {r["city"]: r["left_hand_oncoming_truth"] for r in rows}
    assert truth["SGP"] > 0.8 and truth["LAV"] < 0.2 and truth["BOS"] < 0.2  # each city's own side
    # the RVAE's own encoder is the default
    code, _, err = in_process(capsys, *rvae, "--encoder", sampling_ckpt["rvae"], *args, "--out", tmp_path / "b")
    assert code == 0, err
    assert (tmp_path / "b" / "ablate_rvae.json").read_text() == (tmp_path / "a" / "ablate_rvae.json").read_text()
    # a looser tolerance can only cover more of each polyline
    assert in_process(capsys, *rvae, *args, "--tol", 4, "--out", tmp_path / "t")[0] == 0
    loose = json.loads((tmp_path / "t" / "ablate_rvae.json").read_text())
    assert loose["tol_m"] == 4.0 and all(l["f1"] >= r["f1"] for l, r in zip(loose["rows"], rows))
    assert any(l["f1"] > r["f1"] for l, r in zip(loose["rows"], rows))
    # --split measures that split only, with the same numbers; an unknown one is named
    assert in_process(capsys, *rvae, *args, "--split", "test", "--out", tmp_path / "s")[0] == 0
    assert json.loads((tmp_path / "s" / "ablate_rvae.json").read_text())["rows"] == rows[-1:]
    code, _, err = in_process(capsys, *rvae, *args, "--split", "val", "--out", tmp_path / "s")
    assert code == 1 and "no split val (it has train, test)" in err
    # a packed decoder holds no encoder: it needs --encoder, and cannot be one
    assert in_process(capsys, "pack", "--ckpt", sampling_ckpt["controlmap"], "--out", tmp_path / "w")[0] == 0
    packed = tmp_path / "w" / "rvae"
    code, _, err = in_process(capsys, "ablate", "rvae", "--rvae", packed, *args, "--out", tmp_path / "c")
    assert code == 1 and "give --encoder RUN" in err
    code, _, err = in_process(capsys, "ablate", "rvae", "--encoder", packed, *args, "--out", tmp_path / "c")
    assert code == 1 and "holds no encoder" in err
    code, _, err = in_process(capsys, "ablate", "rvae", "--rvae", sampling_ckpt["dit"], *args, "--out", tmp_path / "c")
    assert code == 1 and "not an RVAE" in err
