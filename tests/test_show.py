"""`data show`: the PNG grid and the Rerun recording, read back with rerun's own reader."""

from collections import Counter

import cv2
import numpy as np
import pytest
from rerun.chunk import RrdReader

from cmtool.core.errors import CmtoolError
from cmtool.data.cache import load_dataset
from cmtool.viz.show import pick, show_dataset


@pytest.fixture(scope="module")
def dataset(tiny_data):
    return tiny_data


def test_png_grid_has_expected_size_and_content(dataset, tmp_path):
    png = tmp_path / "grid.png"
    show_dataset(dataset, n=4, png=png, split="train", seed=1)
    img = cv2.cvtColor(cv2.imread(str(png)), cv2.COLOR_BGR2RGB)
    # 2 x 2 tiles of (22 + 256) x (256 + 2 + 256) px, 6 px gaps, plus a 40 px legend strip
    assert img.shape == (2 * (22 + 256 + 6) + 6 + 40, 2 * (514 + 6) + 6, 3)
    tile = img[6 + 22: 6 + 22 + 256, 6: 6 + 256]
    saturated = (tile.max(axis=2).astype(int) - tile.min(axis=2)) > 100
    assert saturated.sum() > 200  # direction-coloured lanes drawn
    sd = img[6 + 22: 6 + 22 + 256, 6 + 258: 6 + 514]
    assert (sd.max(axis=2) > 60).sum() > 500  # roads drawn in the SD panel
    again = tmp_path / "again.png"
    show_dataset(dataset, n=4, png=again, split="train", seed=1)
    assert np.array_equal(cv2.imread(str(png)), cv2.imread(str(again)))


def test_rrd_reads_back_with_layout(dataset, tmp_path):
    rrd = tmp_path / "show.rrd"
    show_dataset(dataset, n=3, rrd=rrd, split="test", seed=0)
    reader = RrdReader(rrd)
    assert len(reader.recordings()) == 1 and len(reader.blueprints()) == 1
    rows, strips, samples = Counter(), {}, {}
    for chunk in reader.stream():
        rows[chunk.entity_path] += chunk.num_rows
        batch = chunk.to_record_batch()
        if "sample" in batch.schema.names:
            samples.setdefault(chunk.entity_path, set()).update(batch.column("sample").to_pylist())
        if chunk.entity_path.endswith("hd/lanes"):
            strips[chunk.entity_path] = len(batch.column("LineStrips2D:strips")[0])
    data = load_dataset(dataset, "test")
    for k, i in enumerate(pick(len(data), 3, 0)):
        arrows = len(data.scene(i).edges) > 0  # successor arrows only where the frame holds a successor link
        for path in ("hd/lanes", "hd/lights/green", "hd/lights/red", "control/sd") + ("hd/successors",) * arrows:
            assert rows[f"/sample_{k}/{path}"] == 1, path
            assert f"/sample_{k}/{path}" not in samples  # static: every scene shown whatever the time
        assert rows[f"/sample_{k}/hd/successors"] == int(arrows)
        assert strips[f"/sample_{k}/hd/lanes"] == data.line_mask[i].sum()
    assert rows["/info"] == 1
    assert not any(p.startswith("/sample_3") for p in rows)


def test_show_needs_an_output(dataset):
    with pytest.raises(CmtoolError, match="nothing to write"):
        show_dataset(dataset)
    with pytest.raises(CmtoolError, match="no split 'val'"):
        show_dataset(dataset, png="x.png", split="val")


def test_lights_are_short_bars_across_their_lanes_at_their_stop_lines(tmp_path):
    """A light is drawn, in the pictures and in the viewer, as a short bar across its lane where its light line starts
    (its stop line), not as a broad band along the whole line that smeared along the roads."""
    import rerun as rr

    from cmtool.viz.draw import GREEN, LIGHT_BAR_HALF_M, lanes_image, light_bars
    from cmtool.viz.recording import log_lanes

    lane = np.stack([np.linspace(-20.0, 20.0, 20), np.zeros(20)], axis=1)  # 40 m forward along the ego's x
    turn = np.stack([np.zeros(20), np.linspace(5.0, 25.0, 20)], axis=1)  # 20 m to the left from (0, 5)
    bars = light_bars([lane, turn])
    assert bars.shape == (2, 2, 2)
    assert np.allclose(bars.mean(axis=1), [lane[0], turn[0]])  # centred where the lines start
    across = bars[:, 1] - bars[:, 0]
    assert np.allclose(np.linalg.norm(across, axis=1), 2 * LIGHT_BAR_HALF_M)
    assert np.allclose([across[0] @ [1.0, 0.0], across[1] @ [0.0, 1.0]], 0.0)  # square to the lines

    size, frame_m = 256, 64.0  # 4 px a metre, forward up, left left: ego (x, y) at row 128 - 4x, column 128 - 4y
    img = lanes_image([lane], [lane], [], [], frame_m, size, ego=False)
    rows, cols = np.nonzero(np.abs(img.astype(int) - GREEN).max(axis=2) <= 30)
    assert len(rows) > 10  # the bar is drawn
    assert np.hypot(rows - (128 + 4 * 20), cols - 128).max() <= 4 * 2.5, "green away from the stop line"

    rec = rr.RecordingStream("test")
    rec.save(str(tmp_path / "lights.rrd"))
    log_lanes(rec, "", [lane, turn], green=[lane, turn], static=True)
    rec.flush()
    rec.disconnect()
    strips = [np.array(s.as_py()) for chunk in RrdReader(tmp_path / "lights.rrd").stream()
              if chunk.entity_path == "/hd/lights/green"
              for s in chunk.to_record_batch().column("LineStrips2D:strips")[0]]
    assert np.allclose(strips, bars)
