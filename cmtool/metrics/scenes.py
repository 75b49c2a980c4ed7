"""The per-scene work behind :func:`cmtool.metrics.suite.evaluate`, over several processes for large sets.

Each scene's topology statistics, lane distances, validity check, SD adherence, driving side and legal
one-way share are Python loops over shapely, SciPy and NumPy calls, about 15 ms a scene; a paper-sized
set (3,904 scenes) is a minute of one core. :func:`scene_scores` splits the scenes into chunks that a
pool of processes scores in order, so the results are those of one process, value for value. The
pool's workers are started afresh ("spawn": they share nothing with a parent that may hold torch's or
OpenCV's threads) and import only this module's dependencies, not torch.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from cmtool.core.workers import pool
from cmtool.metrics.geometric import chamfer_of, driving_side, legal_oneway, sd_adherence
from cmtool.metrics.lanes import pair_distances, scores_at
from cmtool.metrics.topology import STATISTICS, keypoint_graph, scene_statistics
from cmtool.metrics.validity import check

CHUNK = 32  # scenes a worker scores per task
POOL_MIN_SCENES = 256  # fewer scenes are scored in this process: starting workers costs about a second
PLAIN_KEYS = ("chamfer_m", "lane_precision", "lane_recall", "lane_f1", "validity", "dangling", "crossings", "routable")
SD_KEYS = ("sd_coverage", "lane_on_sd", "driving_side", "legal_oneway")
SIDES = ("generated", "reference")


@dataclass
class SceneScores:
    """What :func:`scene_scores` gathers, in scene order."""

    rows: dict[str, list]  # per-scene values, PLAIN_KEYS (and SD_KEYS with SD controls)
    judged: list[float]  # per scene, the lane length judged for legal one-way (with SD controls)
    statistics: dict[str, dict[str, np.ndarray]]  # per side of SIDES, the topology statistics pooled over scenes
    seconds: dict[str, float]  # per family of scores, summed over the processes


def scene_scores(generated, reference, controls: np.ndarray | None, sides: list[str], workers: int = 1,
                 done: Callable[[int], None] = lambda n: None) -> SceneScores:
    """The per-scene scores of ``generated`` against ``reference`` (and ``controls``, SD rasters or None) and both
    sets' topology statistics. ``sides``: each scene's driving side; ``workers``: processes (one below
    ``POOL_MIN_SCENES`` scenes; more than one, from a script, needs the ``if __name__ == "__main__":`` guard of
    ``multiprocessing``); ``done(n)`` is called as chunks of ``n`` scenes finish, in order."""
    n = len(generated)
    chunks = [(generated[i:i + CHUNK], reference[i:i + CHUNK], None if controls is None else controls[i:i + CHUNK],
               sides[i:i + CHUNK]) for i in range(0, n, CHUNK)]
    workers = min(workers, len(chunks))
    rows: dict[str, list] = {k: [] for k in PLAIN_KEYS + (SD_KEYS if controls is not None else ())}
    judged: list[float] = []
    statistics: dict[str, dict[str, list]] = {side: {k: [] for k in STATISTICS} for side in SIDES}
    seconds: dict[str, float] = {}

    def collect(parts) -> None:
        for part_rows, part_judged, part_statistics, part_seconds in parts:
            for k, values in part_rows.items():
                rows[k] += values
            judged.extend(part_judged)
            for side in SIDES:
                for k, values in part_statistics[side].items():
                    statistics[side][k] += values
            for k, v in part_seconds.items():
                seconds[k] = seconds.get(k, 0.0) + v
            done(len(part_rows["validity"]))

    if workers > 1 and n >= POOL_MIN_SCENES:
        with pool(workers, "spawn") as processes:
            collect(processes.imap(_score_chunk, chunks))
    else:
        collect(map(_score_chunk, chunks))
    pooled = {side: {k: np.concatenate(v) if v else np.zeros(0) for k, v in statistics[side].items()}
              for side in SIDES}
    return SceneScores(rows, judged, pooled, seconds)


def _score_chunk(chunk):
    """The rows, judged lengths, per-scene topology statistics and family seconds of one chunk of scenes (run in a
    worker or in-process)."""
    generated, reference, controls, sides = chunk
    rows: dict[str, list] = {k: [] for k in PLAIN_KEYS + (SD_KEYS if controls is not None else ())}
    judged: list[float] = []
    statistics: dict[str, dict[str, list]] = {side: {k: [] for k in STATISTICS} for side in SIDES}
    seconds: dict[str, float] = {}

    def lap(family: str, began: float) -> float:
        now = time.perf_counter()
        seconds[family] = seconds.get(family, 0.0) + now - began
        return now

    for i, (g, r) in enumerate(zip(generated, reference)):
        began = time.perf_counter()
        for side, graph in zip(SIDES, (g, r)):
            for k, v in scene_statistics(keypoint_graph(len(graph.lanes), graph.successors)).items():
                statistics[side][k].append(v)
        began = lap("topology", began)
        distances = pair_distances(g.lanes, r.lanes)
        rows["chamfer_m"].append(chamfer_of(distances))
        scores = scores_at(distances, 1.0)
        for k in ("precision", "recall", "f1"):
            rows[f"lane_{k}"].append(scores[k])
        began = lap("lane distances", began)
        report = check(g)
        counts = report.counts()
        rows["validity"].append(report.score)
        rows["dangling"].append(counts.get("dangling", 0))
        rows["crossings"].append(counts.get("crossing", 0))
        rows["routable"].append(report.routable_with_changes)
        began = lap("validity", began)
        if controls is not None:
            for k, v in sd_adherence(g.lanes, controls[i]).items():
                rows[k].append(v)
            began = lap("SD adherence", began)
            rows["driving_side"].append(driving_side(g.lanes, controls[i], sides[i])[0])
            began = lap("driving side", began)
            share, length = legal_oneway(g.lanes, controls[i])
            rows["legal_oneway"].append(share)
            judged.append(length)
            lap("legal one-way", began)
    return rows, judged, statistics, seconds
