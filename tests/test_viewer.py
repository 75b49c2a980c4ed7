"""The recordings as the Rerun viewer draws them: each kind has its own application id and layout, and its
screenshot (Xvfb + a software Vulkan driver; skipped where they are missing) shows every view filled, the
control-residual heatmaps with structure, and the time panel; sample.rrd's, as the README's quick start makes it,
shows its latent's whole 8 x 8 grid, every value of its 2-step plots as a dot, and no legend over what they plot."""

import cv2
import numpy as np
import pytest

from cmtool.viz.recording import APP_IDS
from cmtool.viz.screenshot import missing, screenshot
from tests.conftest import REPO
from tests.test_train import write_recipe

SD = REPO / "sample_data" / "sd_bos.png"
QUICK_START = ("--sd", "sample_data/sd_sgp.png", "--cfg", 0.7, "--city", "SGP")  # README, from the root; 2 steps


@pytest.fixture(scope="module")
def recordings(tmp_path_factory, tiny_data):
    """One recording of each kind: data show, train (a few RVAE steps), sample (the README's quick start), eval,
    ablate cfg and sample --area (the shipped weights)."""
    import contextlib
    import io

    root = tmp_path_factory.mktemp("viewer")

    def run(*args):
        import sys
        from unittest import mock

        from cmtool.cli import main

        err = io.StringIO()
        # the command line as a user types it in the repository's root (the recordings' info quotes it), not pytest's,
        # which differs run to run; the clone's own path, however long, is not in it
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()), contextlib.chdir(REPO), \
                mock.patch.object(sys, "argv", ["cmtool", *map(str, args)]):
            try:
                main([str(a) for a in args])
            except SystemExit as e:
                assert not e.code, err.getvalue()

    run("data", "show", tiny_data, "--n", 4, "--rrd", root / "data.rrd")
    recipe = write_recipe(root / "rvae.toml", "rvae", 4, data=str(tiny_data), preview_every=2)
    run("train", "rvae", "--recipe", recipe, "--out", root / "rvae", "--quiet")
    run("sample", *QUICK_START, "--out", root / "sample", "--quiet")
    run("eval", "--data", tiny_data, "--n", 4, "--steps", 4, "--no-features", "--rrd-samples", 4, "--out",
        root / "eval", "--quiet")
    run("ablate", "cfg", "--data", tiny_data, "--n", 2, "--w", "0,1", "--seeds", 1, "--steps", 2, "--no-features",
        "--out", root / "ablate")
    run("sample", "--osm", "sample_data/town_bos.osm", "--area", "42.3560,-71.0640,42.3575,-71.0620",
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
    | {"latent": (0.01, 0.14, 0.46, 0.68), "heatmaps": (0.16, 0.40, 0.43, 0.74),
       "noise norms": (0.42, 0.57, 0.43, 0.68), "residual norms": (0.59, 0.74, 0.43, 0.68),
       "info": (0.76, 0.99, 0.07, 0.4), "scores": (0.76, 0.99, 0.5, 0.69)}
    | {f"{plot} key": (x0, x1, 0.705, 0.75) for plot, x0, x1 in (("noise norms", 0.41, 0.575),
                                                                  ("residual norms", 0.585, 0.745),
                                                                  ("scores", 0.755, 0.995))},
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


@pytest.fixture(scope="module")
def shots(recordings, tmp_path_factory):
    """``shot(kind)``: the path of a screenshot of that kind's recording, taken once for all the tests."""
    root, taken = tmp_path_factory.mktemp("shots"), {}

    def shot(kind: str):
        if kind not in taken:
            taken[kind] = screenshot(recordings[kind], root / f"{kind}.png")
        return taken[kind]

    return shot


@pytest.mark.skipif(missing() is not None, reason=f"no headless viewer here: {missing()}")
@pytest.mark.parametrize("kind", list(VIEWS))
def test_viewer_draws_every_view(shots, kind):
    png = shots(kind)
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


def rgb(png) -> np.ndarray:
    return cv2.cvtColor(cv2.imread(str(png)), cv2.COLOR_BGR2RGB)


def of_hue(region: np.ndarray, colours, tol: int = 6) -> np.ndarray:
    """Which pixels of an RGB region have the hue of one of ``colours`` (within ``tol`` of OpenCV's 180 hue steps),
    clearly saturated and bright: a series' line or dot, also where it is blended with what it is drawn over."""
    hsv = cv2.cvtColor(np.ascontiguousarray(region), cv2.COLOR_RGB2HSV).astype(int)
    hues = cv2.cvtColor(np.array([colours], np.uint8), cv2.COLOR_RGB2HSV)[0, :, 0].astype(int)
    d = np.abs(hsv[..., :1] - hues)
    return (np.minimum(d, 180 - d) <= tol).any(axis=2) & (hsv[..., 1] >= 90) & (hsv[..., 2] >= 90)


def dots_at(region: np.ndarray, colours) -> list[float]:
    """Where a plot region shows dots (blobs 5 px across and more, not lines) of the hue of ``colours``: the x of
    each group of dots one above another, as fractions of the region's width. Light grey counts as part of a dot
    (the time cursor's line runs through the dots of the step under it)."""
    hue = of_hue(region, colours)
    light = (region.min(axis=2) > 150) & (np.ptp(region.astype(int), axis=2) < 24)
    blobs = cv2.morphologyEx((hue | light).astype(np.uint8), cv2.MORPH_OPEN,
                             cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (5, 5)))
    n, labels, _, centres = cv2.connectedComponentsWithStats(blobs)
    groups = []
    for x in sorted(centres[k, 0] for k in range(1, n) if (hue & (labels == k)).sum() >= 6):
        if groups and x - groups[-1][-1] <= 6:
            groups[-1].append(x)
        else:
            groups.append([x])
    return [float(np.mean(g)) / region.shape[1] for g in groups]


@pytest.mark.skipif(missing() is not None, reason=f"no headless viewer here: {missing()}")
def test_the_latent_shows_its_whole_8_by_8_grid(shots):
    """The latent view shows all 8 columns and 8 rows of a channel's grid as square cells of one colour each (it
    showed about 6 columns, the others cut off at the view's edge)."""
    png = shots("sample")
    region = cell(rgb(png), 0.0, 0.15, 0.445, 0.75)  # the latent view below its channel slider
    hsv = cv2.cvtColor(np.ascontiguousarray(region), cv2.COLOR_RGB2HSV)
    drawn = (hsv[..., 1] > 60) & (hsv[..., 2] > 40)  # a colour map's colours, not the grey background or text
    rows, cols = drawn.sum(axis=1), drawn.sum(axis=0)
    ys, xs = np.flatnonzero(rows > 0.5 * rows.max()), np.flatnonzero(cols > 0.5 * cols.max())
    top, bottom, left, right = ys.min(), ys.max() + 1, xs.min(), xs.max() + 1
    width, height = right - left, bottom - top
    assert width > 100 and abs(width / height - 1) < 0.06, f"the latent is not a whole square grid: {width} x " \
        f"{height} px ({png})"
    side = width / 8
    centres = np.zeros((8, 8, 3))
    for i in range(8):
        for j in range(8):
            y, x = int(top + (i + 0.5) * height / 8), int(left + (j + 0.5) * side)
            patch = region[y - int(side / 5):y + int(side / 5) + 1, x - int(side / 5):x + int(side / 5) + 1].astype(int)
            assert np.ptp(patch.reshape(-1, 3), axis=0).max() <= 12, f"cell ({i}, {j}) is not one colour ({png})"
            centres[i, j] = patch.reshape(-1, 3).mean(axis=0)
    steps = np.abs(np.diff(centres, axis=1)).max(axis=2)  # (8, 7): each row's change from column to column
    assert (steps.max(axis=0) > 6).all(), f"neighbouring columns not distinct: {steps.max(axis=0)} ({png})"


@pytest.mark.skipif(missing() is not None, reason=f"no headless viewer here: {missing()}")
def test_the_sample_plots_show_each_step_as_a_dot(shots):
    """At the default 2 steps each series of the noise and residual norms is two dots joined by a line, the dots
    away from the plot's edges (a single line from edge to edge read as one segment)."""
    from cmtool.viz.trajectory import EPS_SERIES, block_colours

    png = shots("sample")
    img = rgb(png)
    hues = {"noise norms": [c for key, (_, c) in EPS_SERIES.items() if key != "guided"],  # (guided is white)
            "residual norms": block_colours(6).tolist()}
    for plot, colours in hues.items():
        at = dots_at(cell(img, *VIEWS["sample"][plot]), colours)
        assert len(at) == 2 and 0.1 < at[0] < at[1] - 0.15 and at[1] < 0.9, f"{plot}: dots at {at} ({png})"


@pytest.mark.skipif(missing() is not None, reason=f"no headless viewer here: {missing()}")
def test_no_legend_covers_what_the_sample_plots_show(recordings, shots):
    """Rerun's legend, drawn inside a plot, covered the noise norms' lines, the block-0 residual line and the top of
    the validity bar. The sample layout hides it in every plot (its blueprint, read back) and names the series in a
    key under each plot, each name in its series' colour (the screenshot); every score's bar shows whole, its top
    flat and its height in proportion to the score."""
    import json

    from rerun.chunk import RrdReader

    from cmtool.sample.scores import SCORES
    from cmtool.viz.trajectory import EPS_SERIES, SCORE_COLOURS, block_colours

    path = recordings["sample"]
    views, legends = {}, {}
    for chunk in RrdReader(path).stream(store=RrdReader(path).blueprints()[0]):
        batch = chunk.to_record_batch()
        if "ViewBlueprint:class_identifier" in batch.schema.names:
            views[chunk.entity_path] = (batch.column("ViewBlueprint:class_identifier")[0][0].as_py(),
                                        batch.column("ViewBlueprint:display_name")[0][0].as_py())
        if chunk.entity_path.endswith("/PlotLegend"):
            visible = batch.column("PlotLegend:visible") if "PlotLegend:visible" in batch.schema.names else None
            legends[chunk.entity_path.removesuffix("/PlotLegend")] = None if visible is None else visible[0][0].as_py()
    plots = {path: name for path, (kind, name) in views.items() if kind in ("TimeSeries", "BarChart")}
    assert len(plots) == 3, views
    for view, name in plots.items():
        assert legends.get(view) is False, f"{name}: Rerun's legend is shown over the plot"

    png = shots("sample")
    img = rgb(png)
    keys = {"noise norms": [c for _, c in EPS_SERIES.values()], "residual norms": block_colours(6).tolist(),
            "scores": list(SCORE_COLOURS)}
    for plot, colours in keys.items():
        region = cell(img, *VIEWS["sample"][f"{plot} key"])
        for colour in colours:
            if max(colour) - min(colour) < 30:  # white: the series shown as white text
                shown = (region.min(axis=2) > 200).sum()
            else:
                shown = of_hue(region, [colour]).sum()
            assert shown > 20, f"{plot}: no key for the series in {colour} ({png})"

    meta = json.loads(next(path.parent.glob("*.json")).read_text())["meta"]
    chart = cell(img, 0.755, 0.995, 0.46, 0.73)
    heights = {}
    for key, colour in zip(SCORES, SCORE_COLOURS):
        _, labels, stats, _ = cv2.connectedComponentsWithStats(of_hue(chart, [colour]).astype(np.uint8))
        k = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))  # the bar
        x, w = stats[k, cv2.CC_STAT_LEFT], stats[k, cv2.CC_STAT_WIDTH]
        tops = [int(np.argmax(labels[:, c] == k)) for c in range(x + w // 10, x + w - w // 10)]
        assert np.ptp(tops) <= 2, f"the {SCORES[key]} bar is partly covered: its top at rows {sorted(set(tops))}"
        heights[key] = stats[k, cv2.CC_STAT_TOP] + stats[k, cv2.CC_STAT_HEIGHT] - np.median(tops)
    tallest = max(heights, key=heights.get)
    for key, h in heights.items():
        assert abs(h / heights[tallest] - meta[key] / meta[tallest]) < 0.03, (heights, meta, png)


@pytest.mark.skipif(missing() is not None, reason=f"no headless viewer here: {missing()}")
def test_the_area_recording_is_north_up_as_its_picture(recordings, shots):
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
    img = cv2.imread(str(shots("area")))
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
