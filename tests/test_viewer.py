"""The recordings as the Rerun viewer draws them: each kind has its own application id and layout, and its
screenshot (Xvfb + a software Vulkan driver; skipped where they are missing) shows every view filled, the
control-residual heatmaps with structure, and the time panel."""

import cv2
import numpy as np
import pytest

from cmtool.viz.recording import APP_IDS
from cmtool.viz.screenshot import missing, screenshot
from tests.conftest import REPO
from tests.test_train import write_recipe

SD = REPO / "sample_data" / "sd_bos.png"


@pytest.fixture(scope="module")
def recordings(tmp_path_factory, tiny_data):
    """One recording of each kind: data show, train (a few RVAE steps), sample, eval, ablate cfg and sample --area
    (the shipped weights)."""
    import contextlib
    import io

    root = tmp_path_factory.mktemp("viewer")

    def run(*args):
        from cmtool.cli import main

        err = io.StringIO()
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            try:
                main([str(a) for a in args])
            except SystemExit as e:
                assert not e.code, err.getvalue()

    run("data", "show", tiny_data, "--n", 4, "--rrd", root / "data.rrd")
    recipe = write_recipe(root / "rvae.toml", "rvae", 4, data=str(tiny_data), preview_every=2)
    run("train", "rvae", "--recipe", recipe, "--out", root / "rvae", "--quiet")
    run("sample", "--sd", SD, "--steps", 6, "--out", root / "sample", "--quiet")
    run("eval", "--data", tiny_data, "--n", 4, "--steps", 4, "--no-features", "--rrd-samples", 4, "--out",
        root / "eval", "--quiet")
    run("ablate", "cfg", "--data", tiny_data, "--n", 2, "--w", "0,1", "--seeds", 1, "--steps", 2, "--no-features",
        "--out", root / "ablate")
    run("sample", "--osm", REPO / "sample_data" / "town_bos.osm", "--area", "42.3560,-71.0640,42.3575,-71.0620",
        "--steps", 4, "--sampler", "dpm++2m-sde", "--out", root / "area", "--quiet")
    return {"data": root / "data.rrd", "train": root / "rvae" / "train.rrd", "sample": root / "sample" / "sample.rrd",
            "eval": root / "eval" / "eval.rrd", "ablate": root / "ablate" / "ablate_cfg.rrd",
            "area": root / "area" / "area.rrd"}


def test_each_kind_of_recording_has_its_own_application_id(recordings):
    from rerun.chunk import RrdReader

    for kind, path in recordings.items():
        stores = RrdReader(path).recordings() + RrdReader(path).blueprints()
        assert {s.application_id for s in stores} == {APP_IDS[kind]}, kind
    assert len(set(APP_IDS.values())) == len(APP_IDS)


def busy(region: np.ndarray) -> float:
    """Share of a region's pixels that differ clearly from its most common colour (0 for an empty view)."""
    flat = region.reshape(-1, 3).astype(int)
    colours, counts = np.unique(flat // 8, axis=0, return_counts=True)
    background = colours[counts.argmax()] * 8
    return float((np.abs(flat - background).sum(axis=1) > 60).mean())


def cell(img, x0, x1, y0, y1):
    """The region of ``img`` between fractions x0..x1 of its width and y0..y1 of its height."""
    h, w = img.shape[:2]
    return img[int(y0 * h):int(y1 * h), int(x0 * w):int(x1 * w)]


# views each layout must fill, as fractions of the window (x0, x1, y0, y1) below the 3% title bar
VIEWS = {
    "sample": {f"map view {k}": (0.25 * k + 0.01, 0.25 * (k + 1) - 0.01, 0.07, 0.38) for k in range(3)}
    | {"latent": (0.01, 0.11, 0.45, 0.74), "heatmaps": (0.13, 0.38, 0.43, 0.74),
       "noise norms": (0.40, 0.56, 0.43, 0.74), "residual norms": (0.58, 0.74, 0.43, 0.74),
       "info": (0.76, 0.99, 0.07, 0.4), "scores": (0.76, 0.99, 0.5, 0.73)},
    "eval": {f"map view {k}": (0.2 * k + 0.02, 0.2 * (k + 1) - 0.02, 0.1, 0.43) for k in range(4)}
    | {f"score plot {k}": (0.335 * k + 0.02, 0.335 * (k + 1) - 0.02, 0.5, 0.73) for k in range(3)},
    "train": {f"plot {k}": (0.25 * k + 0.02, 0.25 * (k + 1) - 0.02, 0.06, 0.37) for k in range(4)}
    | {f"preview {k}": (0.25 * k + 0.02, 0.25 * (k + 1) - 0.02, 0.42, 0.56) for k in range(4)},
    "data": {"scene grid": (0.0, 0.8, 0.05, 0.95)},
    "ablate": {f"scene {k} {part}": (0.5 * k + 0.02, 0.5 * (k + 1) - 0.02, y0, y1) for k in range(2)
               for part, (y0, y1) in (("at w", (0.07, 0.29)), ("ground truth", (0.34, 0.56)))}
    | {f"score plot {k}": (0.25 * k + 0.02, 0.25 * (k + 1) - 0.02, 0.61, 0.73) for k in range(2)},
    "area": {"area map": (0.15, 0.7, 0.1, 0.7), "info": (0.85, 0.98, 0.1, 0.5)},
}


@pytest.mark.skipif(missing() is not None, reason=f"no headless viewer here: {missing()}")
@pytest.mark.parametrize("kind", list(VIEWS))
def test_viewer_draws_every_view(recordings, tmp_path, kind):
    png = screenshot(recordings[kind], tmp_path / f"{kind}.png")
    img = cv2.imread(str(png))
    assert img is not None and img.shape[:2] == (1000, 1600)
    for name, box in VIEWS[kind].items():
        assert busy(cell(img, *box)) > 0.003, f"{kind}: {name} is empty ({png})"
    if kind == "sample":
        # the latent fills its view (an 8 x 8 grid of one channel, not a 64 x 8 strip at the edge) and the residual
        # heatmaps show structure: many colours of a colour map (about 180), not flat squares (about 30)
        assert busy(cell(img, *VIEWS["sample"]["latent"])) > 0.2, f"latent view not filled ({png})"
        heatmaps = cell(img, *VIEWS["sample"]["heatmaps"]).reshape(-1, 3)
        assert len(np.unique(heatmaps // 16, axis=0)) > 80, f"flat heatmaps ({png})"
        # the info document fits its view: no text runs into its right edge (its table was cut off there)
        assert busy(cell(img, 0.99, 1.0, 0.06, 0.45)) < 0.002, f"info cut off at the right edge ({png})"
    if kind != "data":  # the time panel, open on the recording's timeline, lists the streams at the bottom left
        assert busy(cell(img, 0.0, 0.1, 0.8, 0.98)) > 0.01, f"{kind}: no time panel ({png})"


def test_serve_serves_the_recording_and_the_web_viewer(tmp_path):
    """`sample --serve`: Rerun's web viewer on port 9090 and the recording over gRPC on 9876, until Ctrl-C."""
    import socket
    import subprocess
    import sys
    import time
    import urllib.request

    proc = subprocess.Popen([sys.executable, "-m", "cmtool", "sample", "--sd", str(SD), "--steps", "2", "--out",
                             str(tmp_path / "s"), "--serve", "--quiet"], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, cwd=REPO)
    try:
        lines = []
        deadline = time.monotonic() + 300
        while not any("serving until Ctrl-C" in line for line in lines):
            assert proc.poll() is None and time.monotonic() < deadline, "".join(lines) + proc.stderr.read()
            lines.append(proc.stderr.readline())
        assert "open http://" in lines[0] and "9090/?url=rerun%2Bhttp://" in lines[0] and "ssh -L 9090" in lines[0]
        assert urllib.request.urlopen("http://127.0.0.1:9090/", timeout=10).status == 200
        with socket.create_connection(("127.0.0.1", 9876), timeout=10):
            pass
        assert (tmp_path / "s" / "sample.rrd").stat().st_size > 0  # the file is written as well
    finally:
        proc.terminate()
        proc.wait(timeout=30)


# views that identify each kind's layout (a subset of its view names; data's scene views are titled "#k CITY ...")
LAYOUT_VIEWS = {
    "data": {"#"},
    "train": {"rvae: loss", "rvae: learning rate", "rvae: gradient norm"},
    "sample": {"SD control", "x0 lanes over diffusion steps", "latent x_t", "noise prediction norms"},
    "eval": {"SD input", "unguided DiT", "ControlMap", "ground truth", "scores of this scene"},
    "ablate": {"scene 0: at this w", "scene 1: at this w"},
    "area": {"area: tiles, then the stitched map"},
}


@pytest.mark.skipif(missing() is not None, reason=f"no headless viewer here: {missing()}")
def test_recordings_opened_one_after_another_keep_their_own_layouts(recordings, tmp_path, monkeypatch):
    """In one running viewer, each recording opened after another shows its own views (none of the others', none
    empty or failing), and going back to the first shows its layout again."""
    import socket

    from rerun.experimental import ViewerClient

    for var in ("XDG_DATA_HOME", "XDG_CONFIG_HOME", "XDG_CACHE_HOME"):  # no layout remembered from earlier runs
        monkeypatch.setenv(var, str(tmp_path))
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    viewer = ViewerClient.spawn(headless=True, port=port, hide_welcome_screen=True)
    try:
        for kind in ["data", "sample", "eval", "train", "ablate", "area", "data"]:
            viewer.open(str(recordings[kind]))
            state = viewer.get_state()
            names = {"#" if view.name.startswith("#") else view.name for view in state.views}
            assert LAYOUT_VIEWS[kind] <= names, f"{kind}: views {sorted(names)}"
            others = set().union(*(v for k, v in LAYOUT_VIEWS.items() if k != kind))
            assert not names & others, f"{kind} shows views of another recording: {sorted(names & others)}"
            problems = [(view.name, r.summary) for view in state.views for r in view.reports]
            assert not problems, f"{kind}: {problems}"
    finally:
        viewer.quit()


def roads(img: np.ndarray) -> np.ndarray:
    """Which pixels differ clearly from the most common colour (roads and lanes on the background)."""
    flat = img.reshape(-1, 3).astype(int)
    colours, counts = np.unique(flat // 8, axis=0, return_counts=True)
    return np.abs(img.astype(int) - colours[counts.argmax()] * 8).sum(axis=2) > 60


def box_grid(mask: np.ndarray, top: float, bottom: float, left: float, right: float, n: int = 12) -> np.ndarray:
    """(n, n): whether each cell of the pixel rectangle (rows north to south) holds some of ``mask``."""
    r = np.linspace(top, bottom, n + 1).round().astype(int)
    c = np.linspace(left, right, n + 1).round().astype(int)
    return np.array([[mask[r[i]:r[i + 1], c[j]:c[j + 1]].mean() > 0.02 for j in range(n)] for i in range(n)])


@pytest.mark.skipif(missing() is not None, reason=f"no headless viewer here: {missing()}")
def test_the_area_recording_is_north_up_as_its_picture(recordings, tmp_path):
    """Where the viewer draws the area's roads, on a grid over the box, agrees with the SD map of the area's PNG
    (north up), not with that map mirrored north-south, as the viewer drew it before."""
    import json

    from cmtool.sample.area import ON_SCREEN_M
    from cmtool.viz.draw import title_strip

    out = recordings["area"].parent
    x0, y0, x1, y1 = json.loads(next(out.glob("*_area.json")).read_text())["meta"]["area"]["box_m"]
    size, extent = 1024, max(x1 - x0, y1 - y0) + 8.0  # the PNG's SD panel: the box's square and 4 m, north up
    top = title_strip("", size).shape[0]
    sd = roads(cv2.imread(str(next(out.glob("*_area.png"))))[top:top + size, :size])
    px = lambda m: (m + extent / 2) / extent * size  # noqa: E731
    picture = box_grid(sd, px(-y1), px(-y0), px(x0), px(x1))
    img = cv2.imread(str(screenshot(recordings["area"], tmp_path / "area.png")))
    # the area view, which fits the roads it shows, left of the corner where the viewer's notices may pop up
    view = roads(cell(img, 0.0, 0.78, 0.06, 0.75))
    rows, cols = np.nonzero(view)
    margin = ON_SCREEN_M + 2.0  # the roads shown reach this far around the box (drawn 2 m wide)
    sx, sy = (cols.max() - cols.min()) / (x1 - x0 + 2 * margin), (rows.max() - rows.min()) / (y1 - y0 + 2 * margin)
    shown = box_grid(view, rows.min() + margin * sy, rows.max() - margin * sy, cols.min() + margin * sx,
                     cols.max() - margin * sx)
    agree, mirrored = (shown == picture).mean(), (shown == picture[::-1]).mean()
    assert agree > 0.8 and agree > mirrored + 0.2, (agree, mirrored)


def test_docs_name_the_timelines_of_every_recording(recordings):
    """docs/viewer.md's table gives each kind of recording the timelines it has (Rerun's own log_time aside)."""
    import re

    from rerun.chunk import RrdReader

    documented = {}
    for line in (REPO / "docs" / "viewer.md").read_text().splitlines():
        cells = [c.strip() for c in line.strip("|").split("|")]
        if len(cells) == 5 and cells[2].strip("`") in APP_IDS.values():
            documented[cells[2].strip("`")] = set(re.findall(r"`([^`]+)`", cells[3]))
    for kind, path in recordings.items():
        timelines = {n for c in RrdReader(path).stream() for n in c.to_record_batch().schema.names
                     if ":" not in n and n not in ("rerun.controls.RowId", "log_time", "log_tick")}
        assert timelines == documented[APP_IDS[kind]], kind


def test_a_data_recording_shows_every_scene_at_any_time_in_rows_without_gaps(tiny_data, tmp_path):
    """`data show` logs its scenes static (a scene logged at a time showed nothing while the cursor stood before it)
    and lays them out in rows of near-equal length, so that no cell of its layout is empty."""
    from rerun.chunk import RrdReader

    from cmtool.viz.recording import grid_rows
    from cmtool.viz.show import show_dataset

    show_dataset(tiny_data, n=13, rrd=tmp_path / "data.rrd")
    names = {n for c in RrdReader(tmp_path / "data.rrd").stream() for n in c.to_record_batch().schema.names}
    assert "sample" not in names and "log_time" not in names
    assert grid_rows(13) == [4, 3, 3, 3] and grid_rows(16) == [4, 4, 4, 4] and grid_rows(1) == [1]
    for n in range(1, 40):
        rows = grid_rows(n)
        assert sum(rows) == n and max(rows) - min(rows) <= 1 and abs(len(rows) - n ** 0.5) < 1
