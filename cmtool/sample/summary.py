"""The table of the maps a run made that ``cmtool sample`` and ``cmtool baseline`` print."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from cmtool.core.geometry import polyline_length
from cmtool.metrics.suite import weighted_mean
from cmtool.sample.scores import SCORES, SCORES_NOTE

if TYPE_CHECKING:
    from cmtool.sample.job import SampledMap


def summary_table(maps: list[SampledMap]) -> str:
    """Per map: lanes, successor links, mean lane length, lights and the scores (:data:`SCORES_NOTE`: "-" without
    them); then the means over the maps, what the guarantee changed, the time the maps took and what the scores
    are."""
    head = (f"{'map':<24} {'city':<5} {'lanes':>5} {'successors':>10} {'mean lane m':>11} {'lights':>6} "
            + " ".join(f"{name:>10}" for name in SCORES.values()))
    rows = [head]
    dash = lambda v: "-" if v is None else f"{v:.3f}"  # noqa: E731
    for m in maps:
        g = m.graph
        mean = np.mean([polyline_length(l) for l in g.lanes]) if g.lanes else 0.0
        rows.append(f"{m.job.name[:24]:<24} {g.city or 'none':<5} {len(g.lanes):>5} {len(g.successors):>10} "
                    f"{mean:>11.1f} {len(g.green_lights) + len(g.red_lights):>6} "
                    + " ".join(f"{dash(g.meta.get(key)):>10}" for key in SCORES))
    if len(maps) > 1:
        shares = [m.graph.meta.get("legal_oneway") for m in maps]
        legal = weighted_mean([math.nan if v is None else v for v in shares],
                              [m.graph.meta.get("oneway_judged_m", 0.0) for m in maps])
        covered = [m.graph.meta["sd_coverage"] for m in maps if m.graph.meta.get("sd_coverage") is not None]
        rows.append(f"{len(maps)} maps: mean validity {np.mean([m.graph.meta['validity'] for m in maps]):.3f}, "
                    f"lane length on one-way SD roads running the legal way {dash(legal)}, SD road with a lane "
                    f"within 3 m {dash(float(np.mean(covered)) if covered else None)}")
    raw = [m.graph.meta["raw"] for m in maps if "raw" in m.graph.meta]
    if raw:
        composed = [m.graph.meta["composed"] for m in maps if "composed" in m.graph.meta]
        turned = sum(m.graph.meta["guarantee"]["turned"] for m in maps if "guarantee" in m.graph.meta)
        made = [c["movements"].get("model", 0) for c in composed]
        moves = [sum(c["movements"].values()) for c in composed]
        dropped = sum(c["dropped"] for c in composed)
        done = ([f"{len(composed)} composed from the SD map ({dropped} of the model's lanes left out where it has no "
                 f"road; {sum(made)} of {sum(moves)} junction movements the model's)"] if composed else []) \
            + ([f"{turned} lanes turned round"] if turned else [])
        mean = lambda k: dash(float(np.mean([r[k] for r in raw if k in r])) if any(k in r for r in raw) else None)  # noqa: E731
        rows.append(f"the guarantee: {'; '.join(done) or 'nothing changed'}; the model's own maps: validity "
                    f"{mean('validity')}, one-way ok {mean('legal_oneway')}, SD covered {mean('sd_coverage')}")
    seconds = sum(m.seconds for m in maps)
    rows.append(f"time to generate and check: {seconds:.1f} s"
                + (f" for {len(maps)} maps, {seconds / len(maps):.2f} s a map" if len(maps) > 1 else ""))
    return "\n".join(rows + [SCORES_NOTE])
