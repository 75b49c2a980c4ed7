"""Recipes and the dataset cache: determinism, resumability, split by city, real maps."""

from pathlib import Path

import numpy as np
import pytest

from cmtool.core.errors import CmtoolError
from cmtool.data import cache
from cmtool.data.cache import build_dataset, load_dataset, load_manifest
from cmtool.train.recipe import load_recipe

REPO = Path(__file__).resolve().parents[1]
TINY = REPO / "recipes" / "data_tiny.toml"
SHARED_DATA = REPO / ".." / "shared" / "data"


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    out = tmp_path_factory.mktemp("tiny")
    summary = build_dataset(load_recipe(TINY), out, workers=2, progress=False)
    return out, summary


def arrays(out, split):
    return load_dataset(out, split).arrays


def test_tiny_build_is_split_by_city(tiny):
    out, summary = tiny
    counts = {s: (v["scenes"], v["cities"]) for s, v in summary["splits"].items()}
    assert counts == {"train": (24, {"LAV": 8, "PIT": 8, "SGP": 8}), "test": (8, {"BOS": 8})}
    manifest = load_manifest(out)
    assert manifest["cities"] == ["LAV", "PIT", "SGP", "BOS"] and manifest["px_m"] == 0.5
    train, test = load_dataset(out, "train"), load_dataset(out, "test")
    assert set(train.city.tolist()) == {"LAV", "PIT", "SGP"} and set(test.city.tolist()) == {"BOS"}
    assert test.city_index.tolist() == [3] * 8
    assert train.lines.shape == (24, 50, 20, 2) and train.lines.dtype == np.float32
    assert train.cut.shape == (24,) and train.cut.dtype == np.int32
    assert train.sd.shape == (24, 128, 128, 3) and train.sd.dtype == np.uint8
    assert train.line_mask.sum(1).min() >= 1  # every scene has its ego lane
    assert np.abs(train.lines).max() <= 32.0 + 1e-4
    assert (train.sd[..., 0] > 0).any()


def test_scenes_read_back_with_valid_edges(tiny):
    out, _ = tiny
    data = load_dataset(out)  # all splits
    assert len(data) == 32
    edges = 0
    for scene in data:
        graph = scene.to_lanegraph()  # validates indices through the interchange format
        n = int(scene.line_mask.sum())
        assert all(0 <= i < n and 0 <= j < n for i, j in graph.successors)
        edges += len(graph.successors)
        # the ego lane passes through the origin with heading +x
        assert np.min(np.linalg.norm(scene.lines[scene.line_mask].reshape(-1, 2), axis=1)) < 3.0
    assert edges > 0


def test_build_is_deterministic(tiny, tmp_path):
    out, _ = tiny
    build_dataset(load_recipe(TINY), tmp_path, workers=1, progress=False)
    for split in ("train", "test"):
        a, b = arrays(out, split), arrays(tmp_path, split)
        for key in a:
            np.testing.assert_array_equal(a[key], b[key], err_msg=key)


def test_resume_rebuilds_only_missing_shard(tmp_path):
    build_dataset(load_recipe(TINY), tmp_path, workers=1, progress=False)
    shards = sorted(tmp_path.glob("*/*.npz"))
    assert len(shards) == 8  # 4 maps x 8 scenes, 4 scenes per shard
    before = {p: p.stat().st_mtime_ns for p in shards}
    reference = arrays(tmp_path, "train")
    shards[3].unlink()
    summary = build_dataset(load_recipe(TINY), tmp_path, workers=1, progress=False)
    assert summary["units_built"] == 1 and summary["units_skipped"] == 3
    assert [p for p in shards if p.stat().st_mtime_ns != before[p]] == [shards[3]]
    again = arrays(tmp_path, "train")
    for key in reference:
        np.testing.assert_array_equal(reference[key], again[key], err_msg=key)
    assert build_dataset(load_recipe(TINY), tmp_path, workers=1, progress=False)["units_built"] == 0


def test_interrupted_build_leaves_no_partial_shard(tmp_path, monkeypatch):
    calls = []

    def failing(fh, **arrays):
        calls.append(1)
        if len(calls) == 3:
            fh.write(b"PK partial")
            raise KeyboardInterrupt
        return np.savez(fh, **arrays)

    monkeypatch.setattr(cache.np, "savez_compressed", failing)
    with pytest.raises(KeyboardInterrupt):
        build_dataset(load_recipe(TINY), tmp_path, workers=1, progress=False)
    assert len(list(tmp_path.glob("*/*.npz"))) == 2
    assert not list(tmp_path.glob("*/.*"))  # no temporary file left behind
    with pytest.raises(CmtoolError, match="did not finish"):
        load_manifest(tmp_path)
    monkeypatch.undo()
    summary = build_dataset(load_recipe(TINY), tmp_path, workers=1, progress=False)
    assert summary["units_skipped"] == 1 and len(list(tmp_path.glob("*/*.npz"))) == 8


def test_other_recipe_into_same_folder_is_refused(tiny, tmp_path):
    out, _ = tiny
    other = tmp_path / "other.toml"
    other.write_text(TINY.read_text().replace("scenes_per_map = 8", "scenes_per_map = 6"))
    with pytest.raises(CmtoolError, match="different recipe"):
        build_dataset(load_recipe(other), out, workers=1, progress=False)
    (tmp_path / "stuff").mkdir()
    (tmp_path / "stuff" / "notes.txt").write_text("mine")
    with pytest.raises(CmtoolError, match="not a cmtool dataset"):
        build_dataset(load_recipe(other), tmp_path / "stuff", workers=1, progress=False)


def capped(tmp_path, num_lines: int) -> Path:
    """recipes/data_tiny.toml with another line cap."""
    path = tmp_path / f"tiny_{num_lines}.toml"
    path.write_text(TINY.read_text().replace("num_lines = 50", f"num_lines = {num_lines}"))
    return path


def test_line_cap_cuts_are_counted_per_split_and_source(tmp_path, capsys):
    from tests.conftest import in_process

    build_dataset(load_recipe(capped(tmp_path, 200)), tmp_path / "all", workers=1, progress=False)  # no scene has 200 pieces
    summary = build_dataset(load_recipe(capped(tmp_path, 5)), tmp_path / "cap", workers=1, progress=False)
    assert summary["num_lines"] == 5
    manifest = load_manifest(tmp_path / "cap")
    for split, sources in (("train", ("LAV", "PIT", "SGP")), ("test", ("BOS",))):
        full, cap = load_dataset(tmp_path / "all", split), load_dataset(tmp_path / "cap", split)
        assert full.cut.sum() == 0 and np.array_equal(full.pose, cap.pose)
        cut = np.maximum(full.line_mask.sum(1) - 5, 0)
        assert cut.sum() > 0 and np.array_equal(cap.cut, cut) and [s.cut for s in cap] == cut.tolist()
        rows = {f"procedural {c}": {"scenes": 8, "scenes_cut": int((cut[cap.city == c] > 0).sum()),
                                     "pieces_cut": int(cut[cap.city == c].sum())} for c in sources}
        expected = {"scenes_cut": int((cut > 0).sum()), "pieces_cut": int(cut.sum()), "sources": rows}
        assert summary["splits"][split]["line_cap"] == expected == manifest["splits"][split]["line_cap"]
    # a resumed build reads the counts back from the shards: one shard rebuilt, then none
    sorted((tmp_path / "cap").glob("train/*.npz"))[2].unlink()
    resumed = build_dataset(load_recipe(capped(tmp_path, 5)), tmp_path / "cap", workers=1, progress=False)
    assert resumed["units_built"] == 1 and resumed["splits"] == summary["splits"]
    code, out, _ = in_process(capsys, "data", "build", "--recipe", capped(tmp_path, 5), "--out", tmp_path / "cap")
    train = summary["splits"]["train"]["line_cap"]
    assert code == 0 and f"train: 24 scenes (LAV 8, PIT 8, SGP 8); line cap 5: {train['scenes_cut']} scenes (" in out
    for source, row in train["sources"].items():  # one line per source that lost pieces
        assert (f"\n  {source}: {row['scenes_cut']} scene" in out) == (row["scenes_cut"] > 0)
    code, out, _ = in_process(capsys, "data", "build", "--recipe", capped(tmp_path, 200), "--out", tmp_path / "all")
    assert "test: 8 scenes (BOS 8); no scene hit the line cap (200 lines)" in out


def test_no_frame_stands_on_a_road_the_jitter_dropped(tmp_path):
    recipe = tmp_path / "drop.toml"
    recipe.write_text(TINY.read_text().replace("drop_minor = 0.02", "drop_minor = 0.5"))
    build_dataset(load_recipe(recipe), tmp_path / "out", workers=1, progress=False)
    data = load_dataset(tmp_path / "out")
    centre = data.sd[:, 56:72, 56:72, 0]  # 8 m around the ego: its road, shifted by the jitter at most ~3 m
    assert len(data) == 32 and (centre > 0).any(axis=(1, 2)).all()


def test_shards_built_before_the_cut_and_frame_arrays_still_load(tmp_path):
    out = tmp_path / "out"
    build_dataset(load_recipe(capped(tmp_path, 5)), out, workers=1, progress=False)
    reference = arrays(out, "train")
    old = sorted(out.glob("train/*.npz"))[0]  # the first 4 train scenes
    with np.load(old) as z:
        kept = {k: z[k] for k in z.files if k not in ("cut", "kind", "tags")}
    np.savez_compressed(old, **kept)
    data = load_dataset(out, "train")
    assert reference["cut"][:4].sum() > 0 and data.cut[:4].tolist() == [0] * 4 and data.scene(0).cut == 0
    assert data.kind[:4].tolist() == [""] * 4 and data.scene(0).kind == "" and all(data.kind[4:])
    assert np.array_equal(data.cut[4:], reference["cut"][4:]) and np.array_equal(data.lines, reference["lines"])
    summary = build_dataset(load_recipe(capped(tmp_path, 5)), out, workers=1, progress=False)  # resumes, counts it as 0
    assert summary["units_built"] == 0
    assert summary["splits"]["train"]["line_cap"]["pieces_cut"] == int(reference["cut"][4:].sum())
    assert summary["splits"]["train"]["frames"]["kinds"]["unknown"] == 4


def test_build_reports_the_mix_of_frame_kinds(tiny, tmp_path, capsys):
    from cmtool.data.frames import KINDS, TAGS
    from tests.conftest import in_process

    out, summary = tiny
    for split in ("train", "test"):
        data = load_dataset(out, split)
        frames = summary["splits"][split]["frames"]
        assert frames == load_manifest(out)["splits"][split]["frames"]
        assert sum(frames["kinds"].values()) == len(data) and set(data.kind.tolist()) == set(frames["kinds"])
        assert {k.split()[0] for k in frames["kinds"]} <= set(KINDS) and set(frames["tags"]) <= set(TAGS)
        tagged = {t: sum(t in row.split(",") for row in data.tags.tolist()) for t in frames["tags"]}
        assert tagged == frames["tags"]
    assert len(summary["splits"]["train"]["frames"]["kinds"]) >= 4  # a mix, not one kind
    code, text, _ = in_process(capsys, "data", "build", "--recipe", TINY, "--out", out)
    assert code == 0 and "\n  frames: junction " in text and "\n  tags: " in text
    straight = tmp_path / "straight.toml"
    mix = "[data.frame_mix]\njunction = 0\napproach = 0\nexit = 0\nend = 0\ncurve = 0\nstraight = 1\n"
    body = TINY.read_text()
    straight.write_text(body[:body.index("[data.frame_mix]")] + mix + body[body.index("[data.sd_jitter]"):])
    only = build_dataset(load_recipe(straight), tmp_path / "straight", workers=1, progress=False)
    assert set(only["splits"]["test"]["frames"]["kinds"]) == {"straight"}


@pytest.mark.parametrize("text, match", [
    ("[data]\nmaps_per_cty = 2\n", r"bad\.toml: data\.maps_per_cty: unknown key"),
    ("[data]\nmaps_per_city = 'two'\n", r"bad\.toml: data\.maps_per_city: expected int"),
    ("[data]\ntrain_cities = ['LAV', 3]\n", r"data\.train_cities\[1\]: expected str"),
    ("[data.sd_jitter]\noffset = 1.0\n", r"data\.sd_jitter\.offset: unknown key"),
    ("[dat]\n", r"bad\.toml: dat: unknown key"),
    ("[data]\npx_m = 0.3\n", r"data\.px_m: frame_m / px_m must be a whole number"),
    ("[data]\ntest_cities = ['PIT']\n", r"data\.test_cities: \['PIT'\] also in train_cities"),
    ("[[data.real_maps]]\nformat = 'av2'\npath = 'nowhere/*.json'\n", r"data\.real_maps\[0\]\.path: no file matches"),
    ("[[data.real_maps]]\npath = 'x.json'\n", r"data\.real_maps\[0\]\.format: missing"),
    ("[data\n", r"bad\.toml: malformed TOML"),
    ("[data.frame_mix]\ncurve = -1.0\n", r"data\.frame_mix: shares of .* \(curve = -1\.0\)"),
    ("[data.frame_mix]\njunction = 0\napproach = 0\nexit = 0\nend = 0\ncurve = 0\nstraight = 0\n", r"not all 0"),
    ("[data.sd_jitter]\nlanes_known_major = 2.0\n", r"data\.sd_jitter\.lanes_known_major: must be a probability"),
    ("[data.sd_jitter]\nwobble_m = -1\n", r"data\.sd_jitter\.wobble_m: must be a finite number >= 0"),
])
def test_recipe_errors_name_file_and_key(tmp_path, text, match):
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(CmtoolError, match=match):
        load_recipe(path)


def test_recipe_defaults_and_int_as_float(tmp_path):
    path = tmp_path / "r.toml"
    path.write_text("[data]\nextent = 500\n")
    data = load_recipe(path).data
    assert data.extent == 500.0 and isinstance(data.extent, float)
    assert data.train_cities == ["LAV", "PIT", "SGP"] and data.test_cities == ["BOS"]
    assert data.px_m == 0.5 and data.num_lines == 50 and not data.sd_jitter.enabled
    for name in ("data_tiny", "data_cpu", "data_paper"):
        assert load_recipe(REPO / "recipes" / f"{name}.toml").data.name == name.split("_")[1]


def test_real_maps_join_the_split_they_name(tmp_path):
    av2 = SHARED_DATA / "av2"
    files = sorted(av2.glob("*.json")) if av2.is_dir() else []
    if not files:
        pytest.skip("shared Argoverse 2 sample maps not available")
    recipe = tmp_path / "real.toml"
    recipe.write_text(
        "[data]\nmaps_per_city = 0\ntest_maps_per_city = 0\nscenes_per_map = 3\n"
        f"[[data.real_maps]]\nformat = 'av2'\npath = '{files[0]}'\nsplit = 'real'\n"
    )
    summary = build_dataset(load_recipe(recipe), tmp_path / "out", workers=1, progress=False)
    assert list(summary["splits"]) == ["real"] and summary["splits"]["real"]["scenes"] == 3
    assert list(summary["splits"]["real"]["line_cap"]["sources"]) == [f"av2:{files[0].name}"]
    data = load_dataset(tmp_path / "out", "real")
    assert data.source.tolist() == [f"av2:{files[0].name}"] * 3 and data.city.tolist() == ["PIT"] * 3
    assert load_manifest(tmp_path / "out")["cities"] == ["LAV", "PIT", "SGP", "BOS"]
    assert data.line_mask.sum() > 0


def test_real_maps_read_cmtool_hd_map_files(tmp_path):
    """[[data.real_maps]] with format = "hdmap" reads cmtool's own HD map JSON (what `data import` and `data synth`
    write, and what eval's "is a map file" hint sends there), its city kept or set by the entry."""
    from cmtool.data.synth import generate_city

    hd = generate_city("SGP", seed=3, extent=300.0)
    hd.save(tmp_path / "mine.json")
    recipe = tmp_path / "real.toml"
    recipe.write_text("[data]\nmaps_per_city = 0\ntest_maps_per_city = 0\nscenes_per_map = 3\n"
                      "[[data.real_maps]]\nformat = 'hdmap'\npath = 'mine.json'\nsplit = 'mine'\n"
                      "[[data.real_maps]]\nformat = 'hdmap'\npath = 'mine.json'\nsplit = 'other'\ncity = 'KAR'\n")
    summary = build_dataset(load_recipe(recipe), tmp_path / "out", workers=1, progress=False)
    assert summary["splits"]["mine"]["scenes"] == 3 and summary["splits"]["other"]["scenes"] == 3
    mine, other = load_dataset(tmp_path / "out", "mine"), load_dataset(tmp_path / "out", "other")
    assert mine.city.tolist() == ["SGP"] * 3 and other.city.tolist() == ["KAR"] * 3
    assert mine.source.tolist() == ["procedural:SGP:seed=3"] * 3 and mine.line_mask.sum() > 0  # the map's own
    (tmp_path / "mine.json").write_text("{}")
    with pytest.raises(CmtoolError, match="mine.json"):
        build_dataset(load_recipe(recipe), tmp_path / "again", workers=1, progress=False)


def test_progress_line_reports_rate_and_eta():
    import io

    from cmtool.core.progress import Progress, format_seconds

    stream = io.StringIO()
    with Progress(total=10, label="build", unit="scenes", stream=stream) as bar:
        bar.update(4, loss=0.25)
        assert "4/10 scenes (40%)" in bar.line() and "scenes/s" in bar.line() and "ETA" in bar.line()
        assert "loss=0.25" in bar.line()
        bar.update(6)
    lines = stream.getvalue().splitlines()
    assert lines[0].startswith("build  4/10") and "10/10 scenes (100%)" in lines[-1] and "ETA" not in lines[-1]
    assert format_seconds(75) == "1m15s" and format_seconds(3700) == "1h01m"
    slow = Progress(total=10, label="ablate", unit="runs", stream=io.StringIO())
    slow.update(2)
    slow.start -= 180.0  # two runs in three minutes
    assert "90 s per run" in slow.line() and "runs/s" not in slow.line()
