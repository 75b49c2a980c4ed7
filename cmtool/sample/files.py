"""The files of sampled maps, staged in an output set: per map its lane graph JSON, its ground truth JSON when
known and its picture (SD input | the map | ground truth); and a grid of all pictures."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from cmtool.core.jsonio import OutputSet, json_text
from cmtool.maps.lanegraph import LaneGraph
from cmtool.viz.draw import graph_panel, legend, sd_panel, title_strip
from cmtool.viz.show import png_bytes, write_png

if TYPE_CHECKING:
    from cmtool.sample.job import Job, SampledMap

PANEL = 256
MAP_FILES = (".json", ".gt.json", ".png")  # the files of a map named NAME: NAME.json, NAME.gt.json, NAME.png


class MapFiles:
    """Stages the files of sampled maps in ``outputs`` (:meth:`stage`): each map's lane graph JSON, its ground truth
    JSON when known and (``pictures``) its picture, headed ``title`` (``{city}``: the map's city); with ``grid``,
    :meth:`finish` stacks all pictures into that PNG. :meth:`contents` makes the files' bytes without writing them
    (in a worker process), :meth:`add` stages them."""

    def __init__(self, out: Path, title: str, outputs: OutputSet, pictures: bool = True, grid: Path | None = None):
        self.out, self.title, self.outputs, self.pictures, self.grid = out, title, outputs, pictures, grid
        self.bodies: list[np.ndarray] = []  # the pictures for the grid

    def contents(self, jobs: list[Job], graphs: list[LaneGraph]) -> tuple[list[tuple[Path, bytes]], list[np.ndarray]]:
        """The maps' files as (path, bytes), and their pictures for the grid (none without ``grid``)."""
        files, bodies = [], []
        for job, graph in zip(jobs, graphs):
            files.append((self.out / f"{job.name}.json", json_text(graph.to_json()).encode("utf-8")))
            if job.source.truth is not None:
                files.append((self.out / f"{job.name}.gt.json", json_text(job.source.truth.to_json()).encode("utf-8")))
            if self.pictures:
                body = _picture_body(job, graph, self.title.format(city=graph.city or "no city"))
                path = self.out / f"{job.name}.png"
                files.append((path, png_bytes(path, np.concatenate([body, legend(body.shape[1])], axis=0))))
                if self.grid is not None:
                    bodies.append(body)
        return files, bodies

    def add(self, files: list[tuple[Path, bytes]], bodies: list[np.ndarray]) -> None:
        """Stage files and grid pictures made by :meth:`contents`."""
        for path, data in files:
            self.outputs.write_bytes(path, data)
        self.bodies += bodies

    def stage(self, jobs: list[Job], graphs: list[LaneGraph]) -> None:
        self.add(*self.contents(jobs, graphs))

    def finish(self) -> None:
        if self.grid is not None and self.bodies:
            gap = np.full((4, self.bodies[0].shape[1], 3), 12, np.uint8)
            stacked = np.concatenate([x for body in self.bodies for x in (body, gap)][:-1], axis=0)
            write_png(self.grid, np.concatenate([stacked, legend(stacked.shape[1])], axis=0), self.outputs)


def write_maps(out: Path, maps: list[SampledMap], title: str, outputs: OutputSet, grid: Path | None = None) -> None:
    """Stage every map's files and pictures (:class:`MapFiles`) and, when ``grid`` is given, all their pictures
    stacked into one PNG."""
    files = MapFiles(out, title, outputs, grid=grid)
    files.stage([m.job for m in maps], [m.graph for m in maps])
    files.finish()


def _picture_body(job: Job, graph: LaneGraph, title: str) -> np.ndarray:
    """A map's picture without its legend: SD input | the map | ground truth (those known), each titled."""
    truth = job.source.truth
    panels = []
    if job.source.sd is not None:
        panels.append((f"SD input: {job.source.name}", sd_panel(job.source.sd, PANEL)))
    panels.append((title, graph_panel(graph, PANEL)))
    if truth is not None:
        panels.append(("ground truth", graph_panel(truth, PANEL)))
    tiles = [np.concatenate([title_strip(t, PANEL), img], axis=0) for t, img in panels]
    gap = np.full((tiles[0].shape[0], 4, 3), 12, np.uint8)
    return np.concatenate([x for tile in tiles for x in (tile, gap)][:-1], axis=1)
