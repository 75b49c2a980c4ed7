"""Draw sample_data/sketch.png: a road sketch as a person would make it with a pen or a mouse
(black wobbly strokes on white, not to scale), to show `cmtool sample --sd` on a plain drawing.

    python sample_data/draw_sketch.py
"""

from pathlib import Path

import cv2
import numpy as np

rng = np.random.default_rng(3)
canvas = np.full((400, 400), 255, np.uint8)


def stroke(points, width=7):
    """A hand-drawn stroke through ``points``: densified, then displaced by a slow wobble."""
    p = np.asarray(points, np.float64)
    t = np.linspace(0.0, 1.0, 200)
    s = np.linspace(0.0, 1.0, len(p))
    line = np.stack([np.interp(t, s, p[:, 0]), np.interp(t, s, p[:, 1])], axis=1)
    wobble = np.cumsum(rng.normal(0.0, 0.35, line.shape), axis=0)
    wobble -= np.linspace(wobble[0], wobble[-1], len(wobble))  # keep the stroke's ends where drawn
    cv2.polylines(canvas, [np.round(line + wobble).astype(np.int32)], False, 0, width, cv2.LINE_AA)


stroke([(10, 205), (200, 198), (392, 190)])                      # the main road, left to right
stroke([(196, 8), (199, 200), (205, 392)])                        # crossing it, top to bottom
stroke([(200, 198), (260, 150), (330, 120), (392, 112)])          # a road forking off to the right
stroke([(15, 320), (90, 300), (150, 250), (199, 200)])            # and one from the lower left

cv2.imwrite(str(Path(__file__).with_name("sketch.png")), canvas)
