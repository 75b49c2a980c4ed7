"""WGS84 latitude/longitude -> local metres, with a transverse Mercator projection.

Both OpenStreetMap and Lanelet2 files give WGS84 coordinates. Like Lanelet2's own UTM projector we
use a transverse Mercator projection (Krüger's series, accurate to well under a millimetre within
a few hundred kilometres of the central meridian), but centred on an origin near the data: the
origin maps to (0, 0), x points east and y north. Longitudes are taken the short way round from the origin, so data
across the antimeridian (+-180) projects as one piece, and longitudes come back within [-180, 180].
"""

from __future__ import annotations

import math

import numpy as np

_A = 6378137.0  # WGS84 semi-major axis (m)
_F = 1.0 / 298.257223563  # WGS84 flattening
_N = _F / (2.0 - _F)
_RECT = _A / (1.0 + _N) * (1.0 + _N**2 / 4.0 + _N**4 / 64.0)  # rectifying radius
_ALPHA = (
    _N / 2.0 - 2.0 * _N**2 / 3.0 + 5.0 * _N**3 / 16.0,
    13.0 * _N**2 / 48.0 - 3.0 * _N**3 / 5.0,
    61.0 * _N**3 / 240.0,
)
_E2N = 2.0 * math.sqrt(_N) / (1.0 + _N)  # used in the conformal latitude


def wrap_lon(lon, ref=0.0):
    """Longitudes (degrees) moved by whole turns to within 180 of ``ref`` (unchanged where they are)."""
    lon = np.asarray(lon, np.float64)
    return lon - 360.0 * np.round((lon - ref) / 360.0)


def centre_of(latlon) -> tuple[float, float]:
    """The mean latitude and longitude of (N, 2) [lat, lon] points (degrees), the longitudes taken the short way round
    from the first (an extract across the antimeridian has its centre there, not halfway round the globe)."""
    latlon = np.array(latlon, np.float64)
    latlon[:, 1] = wrap_lon(latlon[:, 1], latlon[0, 1])
    lat, lon = latlon.mean(axis=0)
    return float(lat), float(wrap_lon(lon))


class LocalProjection:
    """Transverse Mercator projection with its origin at ``(lat0, lon0)`` (degrees)."""

    def __init__(self, lat0: float, lon0: float):
        if not (-90.0 <= lat0 <= 90.0 and -180.0 <= lon0 <= 180.0):
            raise ValueError(f"origin out of range: lat={lat0}, lon={lon0}")
        self.lat0, self.lon0 = float(lat0), float(lon0)
        self._x0, self._y0 = 0.0, 0.0
        self._x0, self._y0 = self._raw(np.array([lat0]), np.array([lon0]))
        self._x0, self._y0 = float(self._x0[0]), float(self._y0[0])

    def _raw(self, lat, lon):
        phi = np.radians(lat)
        lam = np.radians(wrap_lon(lon, self.lon0) - self.lon0)
        t = np.sinh(np.arctanh(np.sin(phi)) - _E2N * np.arctanh(_E2N * np.sin(phi)))
        xi = np.arctan2(t, np.cos(lam))
        eta = np.arctanh(np.sin(lam) / np.sqrt(1.0 + t * t))
        north, east = xi.copy(), eta.copy()
        for j, a in enumerate(_ALPHA, start=1):
            north = north + a * np.sin(2 * j * xi) * np.cosh(2 * j * eta)
            east = east + a * np.cos(2 * j * xi) * np.sinh(2 * j * eta)
        return _RECT * east - self._x0, _RECT * north - self._y0

    def to_metres(self, lat, lon) -> np.ndarray:
        """Project latitude/longitude arrays (degrees) to (..., 2) arrays of [east, north] metres."""
        x, y = self._raw(np.asarray(lat, dtype=np.float64), np.asarray(lon, dtype=np.float64))
        return np.stack([x, y], axis=-1)

    def to_latlon(self, xy) -> np.ndarray:
        """Inverse of :meth:`to_metres`: (..., 2) [east, north] metres -> (..., 2) [lat, lon] degrees.

        Newton's method on the forward projection (with a numerical Jacobian), started from the
        local equirectangular guess; converges to well under a millimetre in a few iterations.
        """
        xy = np.asarray(xy, dtype=np.float64)
        target = xy.reshape(-1, 2)
        m_per_deg = np.radians(1.0) * _A
        guess = np.stack([self.lat0 + target[:, 1] / m_per_deg,
                          self.lon0 + target[:, 0] / (m_per_deg * math.cos(math.radians(self.lat0)))], axis=-1)
        h = 1e-7  # degrees, for the finite-difference Jacobian
        for _ in range(8):
            f = self.to_metres(guess[:, 0], guess[:, 1]) - target
            d_lat = (self.to_metres(guess[:, 0] + h, guess[:, 1]) - f - target) / h
            d_lon = (self.to_metres(guess[:, 0], guess[:, 1] + h) - f - target) / h
            jac = np.stack([d_lat, d_lon], axis=-1)  # (N, 2 metres, 2 degrees)
            guess = guess - np.linalg.solve(jac, f[..., None])[..., 0]
            if np.abs(f).max(initial=0.0) < 1e-5:
                break
        guess[:, 1] = wrap_lon(guess[:, 1])
        return guess.reshape(xy.shape)


def scene_to_latlon(points, lat0: float, lon0: float, heading: float = 0.0) -> np.ndarray:
    """Scene-frame metres (..., 2) (x forward, y left) -> (..., 2) [lat, lon], with the scene origin
    at ``(lat0, lon0)`` and its forward axis pointing to the compass ``heading`` (degrees, 0 = north)."""
    yaw = math.radians(90.0 - heading)  # the forward axis in east/north coordinates
    rot = np.array([[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]])
    return LocalProjection(lat0, lon0).to_latlon(np.asarray(points, np.float64) @ rot.T)


def distance_m(lat0: float, lon0: float, lat1: float, lon1: float) -> float:
    """Great-circle distance between two points (degrees) on a sphere of the Earth's mean radius, metres."""
    p0, p1 = math.radians(lat0), math.radians(lat1)
    h = math.sin((p1 - p0) / 2) ** 2 + math.cos(p0) * math.cos(p1) * math.sin(math.radians(lon1 - lon0) / 2) ** 2
    return 2 * 6371008.8 * math.asin(min(1.0, math.sqrt(h)))


def swap_hint(lat: float, lon: float, lat0: float, lon0: float, reach_m: float) -> str:
    """"; did you swap latitude and longitude? ..." when the point ``(lat, lon)`` is off the globe or farther than
    ``reach_m`` from ``(lat0, lon0)`` while ``(lon, lat)`` lies within it; else ""."""
    def near(a, b):
        return -90.0 <= a <= 90.0 and -180.0 <= b <= 180.0 and distance_m(a, b, lat0, lon0) <= reach_m

    if near(lon, lat) and not near(lat, lon):
        return f"; did you swap latitude and longitude? (LAT,LON: {lon:g},{lat:g})"
    return ""
