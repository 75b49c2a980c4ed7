"""SD raster: the ControlMap control image, 128 x 128 x 3 uint8 RGB over the 64 m ego frame.

Frame and orientation (docs/data.md: "Frames and rasters"): x forward, y left; row 0 is the front edge (x = +32), column 0
the left edge (y = +32); pixel (i, j) is centred at x = 32 - (i + 0.5) * px, y = 32 - (j + 0.5) * px
with px = frame_m / size (0.5 m). Roads are drawn as polylines 4 px wide, without anti-aliasing, so
every value is exact. Channels:

- R (0), road class: on road pixels ``CLASS_TOP - CLASS_STEP * k`` for the k-th class of the OSM
  hierarchy (:data:`~cmtool.maps.sdmap.ROAD_CLASSES`: motorway 240, trunk 224, primary 208, secondary
  192, tertiary 176, unclassified 160, residential 144, service 128), ``LINK_OFFSET`` (8) less for a
  ramp or slip road (``*_link``), and 255 where the class is unknown (a drawn road); 0 off the road.
- G (1), lane count: ``32 * min(lanes, 7)`` on road pixels where the total lane count is known,
  0 where it is unknown.
- B (2), one-way travel direction: ``1 + round(254 * (theta + pi) / (2 pi))`` on one-way road
  pixels, where theta in [-pi, pi) is the travel heading in the ego frame (0 = straight ahead,
  pi/2 = to the left); 0 on two-way roads and where the direction is unknown.

This is encoding 2 (:data:`ENCODING`). Encoding 1, which weights trained before road classes read, has road
presence in R (255 on every road pixel) and is otherwise the same: :func:`as_encoding` turns a raster of
encoding 2 into one of encoding 1 (the classes dropped), and one of encoding 1 reads as encoding 2 with every
class unknown.

Two-way roads are drawn first and one-way roads over them, so a one-way direction survives at
junctions; within each, minor classes first. A plain black/white road drawing (light roads on dark or dark roads on light) converts to
a raster with R only (:func:`sd_raster_from_image`).
"""

from __future__ import annotations

import os
from itertools import groupby
from operator import itemgetter
from pathlib import Path

import cv2
import numpy as np

from cmtool.core.errors import CmtoolError
from cmtool.core.geometry import CV_SHIFT, ego_to_pixel, to_frame
from cmtool.core.memory import check_fits
from cmtool.maps.sdmap import ROAD_CLASSES, Road, SDMap

SIZE = 128
FRAME_M = 64.0
THICKNESS_PX = 4
ROAD_VALUE = 255  # R of a road whose class is unknown (encoding 1: of every road)
CLASS_TOP, CLASS_STEP, LINK_OFFSET = 240, 16, 8  # R = CLASS_TOP - CLASS_STEP * class index (- LINK_OFFSET: a link)
ENCODING = 2  # the control image's encoding (module doc); weights record the one they read
ENCODINGS = {1: "R road presence, G lane count, B one-way direction",
             2: "R road class, G lane count, B one-way direction"}
LANE_STEP = 32  # G = LANE_STEP * min(lanes, MAX_LANES)
MAX_LANES = 7
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".npy")  # SD pictures read from files


def lane_value(lanes: int | None) -> int:
    """G-channel value of a road with ``lanes`` total lanes (None = unknown)."""
    return 0 if lanes is None else LANE_STEP * min(int(lanes), MAX_LANES)


def class_value(road_class: str | None, link: bool = False) -> int:
    """R-channel value of a road of ``road_class`` (None = unknown), a ramp or slip road when ``link``."""
    if road_class is None:
        return ROAD_VALUE
    return CLASS_TOP - CLASS_STEP * ROAD_CLASSES.index(road_class) - (LINK_OFFSET if link else 0)


CLASS_VALUES = {class_value(c, link): (c, link) for c in ROAD_CLASSES for link in (False, True)}  # R -> class
_CLASS_NAMES = np.array([CLASS_VALUES.get(v, ("", False))[0] for v in range(256)], dtype=object)
_LINKS = np.array([CLASS_VALUES.get(v, ("", False))[1] for v in range(256)])


def road_value(road: Road) -> int:
    """R-channel value of ``road``."""
    return class_value(road.road_class, road.link)


def as_encoding(sd: np.ndarray, encoding: int) -> np.ndarray:
    """SD rasters (..., H, W, 3) of encoding 2 as weights of ``encoding`` read them (module doc)."""
    if encoding == ENCODING:
        return sd
    if encoding != 1:
        raise CmtoolError(f"unknown SD raster encoding {encoding} (this cmtool knows "
                          + "; ".join(f"{k}: {v}" for k, v in ENCODINGS.items()) + ")")
    out = np.array(sd, copy=True)
    out[..., 0] = np.where(out[..., 0] > 0, ROAD_VALUE, 0)
    return out


def direction_value(theta) -> np.ndarray:
    """B-channel value of a one-way travel heading ``theta`` (radians, ego frame)."""
    theta = (np.asarray(theta, dtype=np.float64) + np.pi) % (2.0 * np.pi) - np.pi
    return (1 + np.round(254.0 * (theta + np.pi) / (2.0 * np.pi))).astype(np.uint8)


def decode_direction(value) -> np.ndarray:
    """Inverse of :func:`direction_value` (to within half a step, about 0.7 degrees)."""
    return (np.asarray(value, dtype=np.float64) - 1.0) / 254.0 * 2.0 * np.pi - np.pi


def mirror_sd(sd: np.ndarray) -> np.ndarray:
    """The SD raster of the scene mirrored left-right (y -> -y): columns reversed, one-way headings
    theta -> -theta. Right-hand traffic becomes left-hand traffic and vice versa."""
    out = np.ascontiguousarray(sd[:, ::-1])
    b = out[..., 2].astype(np.int32)
    out[..., 2] = np.where(b > 0, 256 - b, 0).astype(np.uint8)  # value 1 (-pi) maps to 255 (pi): the same heading
    return out


def rasterize_sd(sd: SDMap, x: float, y: float, yaw: float, frame_m: float = FRAME_M, size: int = SIZE) -> np.ndarray:
    """Draw the roads of ``sd`` around the ego pose (x, y, yaw) into a (size, size, 3) uint8 RGB raster."""
    return SDRasterizer(sd)(x, y, yaw, frame_m, size)


class SDRasterizer:
    """Draws SD rasters of one SD map at many poses (:func:`rasterize_sd`; the roads are gathered once)."""

    def __init__(self, sd: SDMap):
        # two-way roads first, one-way roads over them; minor classes first within each
        roads = sorted(sd.roads, key=lambda r: (bool(r.oneway), -ROAD_CLASSES.index(r.road_class)))
        self.lines = [road.travel_polyline() for road in roads]
        self.oneway = [bool(road.oneway) for road in roads]
        self.classes = [road_value(road) for road in roads]
        self.lanes = [lane_value(road.lanes) for road in roads]
        self.lo = np.array([line.min(axis=0) for line in self.lines]).reshape(-1, 2)
        self.hi = np.array([line.max(axis=0) for line in self.lines]).reshape(-1, 2)

    def __call__(self, x: float, y: float, yaw: float, frame_m: float = FRAME_M, size: int = SIZE) -> np.ndarray:
        img = np.zeros((size, size, 3), dtype=np.uint8)
        px = frame_m / size
        half = frame_m / 2.0
        reach = half * np.sqrt(2.0) + THICKNESS_PX * px
        near = np.flatnonzero(~((self.lo > [x + reach, y + reach]).any(axis=1)
                                | (self.hi < [x - reach, y - reach]).any(axis=1)))
        if not len(near):
            return img
        cuts = np.cumsum([len(self.lines[k]) for k in near])[:-1]
        ego = to_frame(np.concatenate([self.lines[k] for k in near]), x, y, yaw)
        strokes = []  # (colour, pixel polyline) in drawing order
        for k, line, pts in zip(near, np.split(ego, cuts), np.split(ego_to_pixel(ego, px, frame_m), cuts)):
            r, g = self.classes[k], self.lanes[k]
            if not self.oneway[k]:
                strokes.append(((r, g, 0), pts))
                continue
            d = np.diff(line, axis=0)
            values = direction_value(np.arctan2(d[:, 1], d[:, 0])).tolist()
            inside = (np.minimum(line[:-1], line[1:]) <= half + 1.0).all(axis=1)
            inside &= (np.maximum(line[:-1], line[1:]) >= -half - 1.0).all(axis=1)
            strokes += [((r, g, values[s]), pts[s:s + 2]) for s in np.flatnonzero(inside)]
        for colour, group in groupby(strokes, key=itemgetter(0)):  # one call per run of one colour
            cv2.polylines(img, [pts for _, pts in group], False, colour, THICKNESS_PX, cv2.LINE_8, CV_SHIFT)
        return img


def is_sd_raster(img: np.ndarray) -> bool:
    """Whether an RGB uint8 picture follows the SD raster convention above (at any size): R is 0 or a class
    value (255 included), G and B are 0 off the road, some G or B is set or some class known, and roads are the
    minority of pixels."""
    if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
        return False
    r, gb = img[..., 0], img[..., 1:]
    road = r > 0
    known = np.isin(r, list(CLASS_VALUES))
    return bool(np.all(known | (r == 0) | (r == ROAD_VALUE)) and not gb[~road].any()
                and (gb[road].any() or known.any()) and road.mean() < 0.5)


def sd_raster_from_image(image) -> np.ndarray:
    """An SD raster from a picture: a path (PNG/JPG/.npy) or an array (RGB, RGBA or grey).

    An RGB image in the SD raster convention (:func:`is_sd_raster`) is returned as is, resampled
    to 128 x 128 (nearest pixel) when it has another size. Anything else is a road drawing, light
    roads on dark or dark roads on light (roads are taken to be the minority of pixels; on a
    transparent background, the opaque strokes): converted to grey, split into road and background
    at full resolution (Otsu's threshold), and resized to 128 x 128, where a pixel is road when at
    least a fifth of it was (so thin strokes survive). Lane count and direction are unknown. A picture
    that is not square is padded to a square first, centred on the raster's background (no road), so
    that its roads keep their shape.
    """
    return convert_sd_image(image)[0]


def read_sd_image(path) -> tuple[np.ndarray, str | None]:
    """Read a picture file as an SD raster; also returns a note on what was converted (or None)."""
    return convert_sd_image(path)


def convert_sd_image(image) -> tuple[np.ndarray, str | None]:
    """:func:`sd_raster_from_image` plus a one-line note saying what was converted (None: nothing)."""
    img = _page(_read_picture(image) if isinstance(image, (str, os.PathLike)) else np.asarray(image))
    (h, w), side = img.shape[:2], max(img.shape[:2])
    fit = (max(1, round(SIZE * w / side)), max(1, round(SIZE * h / side)))  # its width, height in the raster
    pad = ((side - min(h, w)) // 2, (side - min(h, w) + 1) // 2)
    padded = "" if h == w else (f"; padded to {side} x {side} to keep the roads' shape ({pad[0]}"
                                f"{'' if pad[0] == pad[1] else f' and {pad[1]}'} px of background "
                                f"{'left and right' if w < h else 'above and below'})")
    if is_sd_raster(img):
        if (h, w) == (SIZE, SIZE):
            return img.copy(), None
        return (_centred(cv2.resize(img, fit, interpolation=cv2.INTER_NEAREST)),
                f"resampled the {w} x {h} SD raster to {SIZE} x {SIZE} (nearest pixel){padded}")
    out = np.zeros((SIZE, SIZE, 3), dtype=np.uint8)
    mask = drawing_roads(img)
    if mask is None:
        return out, "a blank picture: no roads"
    coverage = cv2.resize(mask.astype(np.float32), fit, interpolation=cv2.INTER_AREA)
    out[..., 0] = _centred(np.where(coverage >= 0.2, ROAD_VALUE, 0).astype(np.uint8))
    return out, (f"converted a {w} x {h} road drawing to an SD raster (road presence only; lane counts and "
                 f"directions unknown){padded}")


def _centred(img: np.ndarray) -> np.ndarray:
    """A picture that fits in ``SIZE`` x ``SIZE`` in the middle of one, on the raster's background (zeros)."""
    out = np.zeros((SIZE, SIZE, *img.shape[2:]), img.dtype)
    top, left = (SIZE - img.shape[0]) // 2, (SIZE - img.shape[1]) // 2
    out[top:top + img.shape[0], left:left + img.shape[1]] = img
    return out


def picture(path) -> tuple[np.ndarray, bool]:
    """A picture file as an RGB or grey uint8 array (see :func:`_page`), and whether it follows the SD raster
    convention (:func:`is_sd_raster`)."""
    img = _page(_read_picture(path))
    return img, is_sd_raster(img)


def _page(img: np.ndarray) -> np.ndarray:
    """A picture as uint8 grey or RGB: a transparent page's opaque strokes as grey, RGBA's colour otherwise."""
    img = _as_uint8(img)
    if img.ndim == 3 and img.shape[2] == 4:
        alpha = img[..., 3]
        img = alpha if alpha.min() < alpha.max() else img[..., :3]  # transparent page: strokes = roads
    if img.ndim not in (2, 3) or (img.ndim == 3 and img.shape[2] != 3) or min(img.shape[:2]) < 1:
        raise CmtoolError(f"SD image: expected a grey (H, W), RGB (H, W, 3) or RGBA (H, W, 4) picture, "
                          f"got shape {img.shape}")
    return img


def drawing_roads(img: np.ndarray) -> np.ndarray | None:
    """The road pixels of a road drawing (grey or RGB; light roads on dark or dark on light, roads being the
    minority of pixels) as a 0/1 uint8 mask, split by Otsu's threshold; None for a blank picture."""
    if img.ndim == 3:
        img = cv2.cvtColor(np.ascontiguousarray(img), cv2.COLOR_RGB2GRAY)
    if img.min() == img.max():
        return None
    _, mask = cv2.threshold(np.ascontiguousarray(img), 0, 1, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    return 1 - mask if mask.mean() > 0.5 else mask


def _read_picture(path) -> np.ndarray:
    """An image file as an RGB(A) or grey array (``.npy``: the stored array, no pickles)."""
    path = Path(path)
    if path.suffix.lower() == ".npy":
        try:
            return np.load(path, allow_pickle=False)
        except (OSError, ValueError) as e:
            raise CmtoolError(f"{path}: cannot read the array ({e})") from None
    size = _header_size(path) if path.is_file() else None
    if size is not None and size[0] * size[1] > MAX_PIXELS:
        raise CmtoolError(f"{path}: a picture of {size[0]} x {size[1]} pixels; cmtool reads up to {MAX_PIXELS:,} "
                          f"pixels (16384 x 16384)")
    if size is not None:
        check_fits(16 * size[0] * size[1], f"{path}: a picture of {size[0]} x {size[1]} pixels")
    try:
        img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED) if path.is_file() else None
    except cv2.error as e:
        raise CmtoolError(f"{path}: cannot decode the picture ({str(e).strip().splitlines()[-1]})") from None
    if img is None or img.size == 0:
        from cmtool.formats.mapfile import what_file

        what = what_file(path) if path.is_file() else None
        if what is None or what.startswith("a picture"):
            raise CmtoolError(f"{path}: cannot read image (missing or empty file, or not a PNG/JPG picture)")
        use = {"an OpenStreetMap file": "; for an OpenStreetMap file use --osm", "an SD map (JSON)": ""}
        raise CmtoolError(f"{path} is {what}; --sd takes a picture (a PNG/JPG SD raster or road drawing)"
                          + use.get(what, "; for a map use --from-hd"))
    if img.ndim == 3 and img.shape[2] == 3:
        return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
    if img.ndim == 3 and img.shape[2] == 4:
        return cv2.cvtColor(img, cv2.COLOR_BGRA2RGBA)
    return img


MAX_PIXELS = 1 << 28


def _header_size(path: Path) -> tuple[int, int] | None:
    """(width, height) that a PNG or JPEG file's header states, read before anything is decoded (None: another
    format, left to OpenCV's own limit)."""
    with open(path, "rb") as f:
        head = f.read(24)
        if head[:8] == b"\x89PNG\r\n\x1a\n" and len(head) == 24:
            return int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")
        if head[:2] != b"\xff\xd8":
            return None
        f.seek(2)
        while True:  # JPEG segments up to the frame header (SOF0-SOF15 but DHT, JPG and DAC)
            marker = f.read(4)
            if len(marker) < 4 or marker[0] != 0xFF:
                return None
            if 0xC0 <= marker[1] <= 0xCF and marker[1] not in (0xC4, 0xC8, 0xCC):
                frame = f.read(5)
                return (int.from_bytes(frame[3:5], "big"), int.from_bytes(frame[1:3], "big")) if len(frame) == 5 \
                    else None
            if int.from_bytes(marker[2:4], "big") < 2:  # a segment length that would not move on
                return None
            f.seek(int.from_bytes(marker[2:4], "big") - 2, 1)


def _as_uint8(img: np.ndarray) -> np.ndarray:
    if img.dtype == np.uint8:
        return img
    if img.dtype == bool:
        return img.astype(np.uint8) * 255
    if img.dtype == np.uint16:
        return (img >> 8).astype(np.uint8)
    if not np.issubdtype(img.dtype, np.number) or not np.all(np.isfinite(img)):
        raise CmtoolError(f"SD image: expected numeric pixel values, got dtype {img.dtype}")
    scale = 255.0 if img.size and img.max() <= 1.0 else 1.0
    return np.clip(img * scale, 0, 255).astype(np.uint8)


def decode_sd(raster: np.ndarray) -> dict[str, np.ndarray]:
    """Split a raster into ``road`` (bool), ``road_class`` (str, "" = off the road or unknown), ``link`` (bool),
    ``lanes`` (int, 0 = unknown) and ``heading`` (radians, NaN where not one-way), for tests and pictures."""
    raster = np.asarray(raster)
    road = raster[..., 0] > 0
    road_class = _CLASS_NAMES[raster[..., 0]]
    link = _LINKS[raster[..., 0]]
    lanes = np.where(road, np.round(raster[..., 1] / LANE_STEP), 0).astype(int)
    heading = np.where(road & (raster[..., 2] > 0), decode_direction(raster[..., 2]), np.nan)
    return {"road": road, "road_class": road_class, "link": link, "lanes": lanes, "heading": heading}
