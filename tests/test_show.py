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
