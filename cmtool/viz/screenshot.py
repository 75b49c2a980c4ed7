"""Screenshots of recordings as the Rerun viewer draws them, without a screen.

The viewer runs on a virtual X screen (Xvfb) and renders with any Vulkan driver, Mesa's software one
(lavapipe) included; Debian packages ``xvfb mesa-vulkan-drivers`` (and ``xdotool``, which moves the
pointer out of the way so that no hover tooltip covers a view)::

    python -m cmtool.viz.screenshot out/sample.rrd docs/viewer_sample.png
"""

from __future__ import annotations

import os
import shlex
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import cv2

from cmtool.core.errors import CmtoolError

SIZE = (1600, 1000)


def missing() -> str | None:
    """What is missing to take screenshots here (None when nothing is)."""
    if shutil.which("xvfb-run") is None:
        return "xvfb-run is not installed (Debian: apt-get install xvfb mesa-vulkan-drivers)"
    if _rerun() is None:
        return "the rerun viewer is not installed (pip install rerun-sdk)"
    return None


def screenshot(rrd: str | os.PathLike, png: str | os.PathLike, size: tuple[int, int] = SIZE,
               timeout_s: float = 300.0) -> Path:
    """Open ``rrd`` in the Rerun viewer on a virtual screen of ``size`` pixels and save what it draws to ``png``
    (at that size)."""
    reason = missing()
    if reason:
        raise CmtoolError(f"cannot take a screenshot: {reason}")
    png = Path(png)
    png.parent.mkdir(parents=True, exist_ok=True)
    width, height = size
    pointer = "mover=; "  # keep moving the pointer in a corner while the viewer starts: no view gets a hover tooltip
    if shutil.which("xdotool"):
        pointer = (f"(while :; do xdotool mousemove 0 {height - 1}; sleep 0.3; xdotool mousemove 1 {height - 1}; "
                   "sleep 0.3; done) >/dev/null 2>&1 & mover=$!; ")
    # --new: a viewer of its own, also where another viewer or a served recording holds Rerun's port (the
    # viewer would hand the recording to that one and save no screenshot)
    viewer = shlex.join([*_rerun(), "--new", "--window-size", f"{width}x{height}", "--screenshot-to", str(png),
                         str(rrd)])
    with tempfile.TemporaryDirectory() as home:  # a fresh viewer state: no layout remembered from earlier runs
        env = os.environ | {"XDG_DATA_HOME": home, "XDG_CONFIG_HOME": home, "XDG_CACHE_HOME": home}
        try:
            done = subprocess.run(["xvfb-run", "-a", "-s", f"-screen 0 {width}x{height}x24", "sh", "-c",
                                   pointer + viewer + "; status=$?; kill $mover 2>/dev/null; exit $status"],
                                  capture_output=True, text=True, timeout=timeout_s, env=env, check=False)
        except subprocess.TimeoutExpired:
            raise CmtoolError(f"{rrd}: the viewer drew nothing within {timeout_s:.0f} s") from None
    if done.returncode != 0 or not png.is_file():
        tail = (done.stderr or done.stdout).strip().splitlines()[-1:] or ["no output"]
        raise CmtoolError(f"{rrd}: the viewer failed (exit {done.returncode}): {tail[0]}")
    img = cv2.imread(str(png))
    if img.shape[1] != width:  # a HiDPI viewer draws at a multiple of the window size: keep the window's
        cv2.imwrite(str(png), cv2.resize(img, size, interpolation=cv2.INTER_AREA))
    return png


def _rerun() -> list[str] | None:
    found = shutil.which("rerun")
    return [found] if found else None


if __name__ == "__main__":
    if len(sys.argv) != 3:
        sys.exit("usage: python -m cmtool.viz.screenshot RECORDING.rrd OUT.png")
    try:
        print(screenshot(sys.argv[1], sys.argv[2]))
    except CmtoolError as e:
        sys.exit(f"Error: {e}")
