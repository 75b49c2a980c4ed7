"""cmtool: controllable lane-level HD map generation from SD maps (ControlMap).

The package follows the pipeline, and its imports run one way only: a module imports from its own
package and from the layers below it, never from a layer above or beside it (``tests/test_layers.py``
checks every import, those inside functions included): no two packages import each other. From the
bottom:

- ``core``: ground utilities (errors, JSON I/O, what a command may write, memory checks, worker pools,
  geometry, geographic projection, progress, TOML tables, processes under torchrun);
- ``maps``: the map model (HD maps, SD maps, lane graphs, lane neighbours, road graphs);
- ``formats``: importers (Argoverse 2, Lanelet2, nuPlan, Apollo, OpenStreetMap) and exporters (Lanelet2,
  OpenDRIVE, GeoJSON);
- ``data``: procedural cities, SD derivation and jitter, frames, scenes, rasters, the dataset cache;
- ``metrics``: the metric library, validity and repair (imports no model);
- ``model``: RVAE, DiT, ControlMap, checkpoints and the shipped weights;
- ``diffusion``: noise schedule, guidance, samplers, sampler settings;
- ``viz``: pictures, Rerun recordings and layouts, headless screenshots;
- ``train``: recipes, the training loop and stages, the latent cache, reconstruction scores;
- ``sample``: SD inputs, the map generator (the one generate loop), ``cmtool sample``;
- ``eval``: experiments that generate maps: evaluation, ablations, benches;
- ``pipeline``: the whole chain in one command; ``cli``: the ``cmtool`` command.
"""

__version__ = "0.1.0"

# The layers, bottom to top (one package or top-level module each).
LAYERS = ("core", "maps", "formats", "data", "metrics", "model", "diffusion", "viz", "train", "sample", "eval",
          "pipeline", "cli")
