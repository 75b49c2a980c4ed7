"""Procedural cities: the default HD map source.

``generate_city("PIT", seed=3)`` builds a city-scale :class:`~cmtool.maps.hdmap.HDMap` in the style of
one of the four nuPlan cities (see :mod:`.styles`): first a planar road network (:mod:`.network`),
then lanes, intersection connectors, traffic lights and crosswalks (:mod:`.lanes`).
"""

from __future__ import annotations

import math

import numpy as np

from cmtool.core.errors import CmtoolError
from cmtool.data.synth.lanes import build_lanes
from cmtool.data.synth.network import build_network
from cmtool.data.synth.styles import STYLES, Style
from cmtool.maps.hdmap import HDMap, drives_on

CITIES = ("LAV", "PIT", "SGP", "BOS")

__all__ = ["CITIES", "STYLES", "Style", "generate_city"]


def generate_city(city: str, seed: int = 0, extent: float = 800.0) -> HDMap:
    """A procedural HD map in the style of ``city`` covering the square (0, 0)-(extent, extent) m.

    Deterministic per (city, seed, extent).
    """
    if city not in CITIES:
        raise CmtoolError(f"unknown city {city!r} (choose from {', '.join(CITIES)})")
    if not isinstance(seed, (int, np.integer)) or isinstance(seed, bool) or seed < 0:
        raise CmtoolError(f"seed must be a non-negative integer, got {seed!r}")
    if not isinstance(extent, (int, float, np.number)) or not math.isfinite(extent) or extent < 200.0:
        raise CmtoolError(f"extent must be a number of metres >= 200, got {extent!r}")
    style = STYLES[city]
    rng = np.random.default_rng([int(seed), CITIES.index(city)])
    net = build_network(style, rng, float(extent))
    hd = HDMap(city=city, drives_on=drives_on(city), source=f"procedural:{city}:seed={seed}",
               meta={"style": style.to_meta(), "seed": int(seed), "extent": float(extent)})
    build_lanes(net, hd, rng)
    return hd
