"""``cmtool data show``: a picture grid and a Rerun recording of scenes from a dataset cache."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import rerun as rr

from cmtool.core.errors import CmtoolError
from cmtool.core.jsonio import OutputSet, atomic_open
from cmtool.data.cache import load_dataset
from cmtool.viz.draw import grid, lanes_panel, legend, sd_panel, title_strip
from cmtool.viz.recording import close_recording, log_scene, open_recording, scenes_blueprint

PANEL = 256
# zlib's fastest level on unfiltered rows: flat-coloured drawings come out faster and a third smaller than with
# OpenCV's default settings (where its PNG writer lets the filter be chosen)
PNG_OPTIONS = ([cv2.IMWRITE_PNG_COMPRESSION, 1, cv2.IMWRITE_PNG_FILTER, cv2.IMWRITE_PNG_FILTER_NONE]
               if hasattr(cv2, "IMWRITE_PNG_FILTER") else [])


def pick(count: int, n: int, seed: int = 0) -> list[int]:
    """``n`` distinct indices out of ``count`` (sorted; the same for the same seed)."""
    return sorted(np.random.default_rng(seed).choice(count, size=min(n, count), replace=False).tolist())


def scene_title(k: int, scene) -> str:
    return f"#{k} {scene.city} {scene.kind}  {scene.source}" if scene.kind else f"#{k} {scene.city}  {scene.source}"


def scene_tile(scene, title: str, panel: int = PANEL) -> np.ndarray:
    """A title strip over the HD lanes panel and the SD raster panel side by side."""
    sd = sd_panel(scene.sd, panel) if scene.sd is not None else np.zeros((panel, panel, 3), np.uint8)
    body = np.concatenate([lanes_panel(scene, panel), np.full((panel, 2, 3), 60, np.uint8), sd], axis=1)
    return np.concatenate([title_strip(title, body.shape[1]), body], axis=0)


def write_png(path, image: np.ndarray, outputs: OutputSet | None = None) -> None:
    """Write an RGB picture as a PNG file, atomically or, with ``outputs``, staged with the command's other files."""
    png = png_bytes(path, image)
    if outputs is not None:
        outputs.write_bytes(path, png)
    else:
        with atomic_open(path, "wb") as f:
            f.write(png)


def png_bytes(path, image: np.ndarray) -> bytes:
    """The PNG file of an RGB picture that is to be written to ``path`` (named in errors)."""
    path = Path(path)
    if path.suffix.lower() != ".png":
        raise CmtoolError(f"{path}: a picture is written as PNG; give a path ending in .png")
    ok, png = cv2.imencode(".png", cv2.cvtColor(image, cv2.COLOR_RGB2BGR), PNG_OPTIONS)
    if not ok:
        raise CmtoolError(f"{path}: could not encode the picture")
    return png.tobytes()


def show_dataset(data_dir, n: int = 16, png=None, rrd=None, split: str | None = None, seed: int = 0) -> None:
    """Pick ``n`` scenes of ``split`` (all splits when None) and write a PNG grid and/or an .rrd."""
    if png is None and rrd is None:
        raise CmtoolError("nothing to write: give a PNG path, an .rrd path, or both")
    if n < 1:
        raise CmtoolError(f"n: must be at least 1, got {n}")
    data = load_dataset(data_dir, split)
    chosen = pick(len(data), n, seed)
    scenes = [data.scene(i) for i in chosen]
    titles = [scene_title(i, s) for i, s in zip(chosen, scenes)]
    if png is not None:
        tiles = [scene_tile(s, t) for s, t in zip(scenes, titles)]
        picture = grid(tiles, columns=int(np.ceil(np.sqrt(len(tiles)))))
        write_png(png, np.concatenate([picture, legend(picture.shape[1])], axis=0))
    if rrd is not None:
        rec = open_recording("data")
        rec.send_blueprint(scenes_blueprint(titles, data.frame_m / 2.0))
        rec.log("info", rr.TextDocument(
            f"# cmtool data show\n\ndataset: `{data_dir}`\n\nsplit: {split or 'all'}, seed {seed}\n\n"
            + "\n".join(f"- sample_{k}: scene {t}" for k, t in enumerate(titles)), media_type="text/markdown"),
            static=True)
        for k, scene in enumerate(scenes):
            log_scene(rec, f"sample_{k}/", scene)
        close_recording(rec, rrd)
