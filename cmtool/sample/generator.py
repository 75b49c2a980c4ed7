"""A trained checkpoint set ready to generate maps: ControlMap (or a plain DiT) plus its RVAE.

``MapGenerator.load(ckpt)`` reads a ControlMap or DiT checkpoint (a run folder or one checkpoint
folder), finds the RVAE it was trained on (the path its config records, absolute or relative to
the checkpoint) and checks that the pieces fit. ``generate`` is the one generate loop of the package
(``cmtool sample``, ``eval``, ``ablate``, ``bench``): a batch's noise, its denoising (``sample``), the
decoded polylines (``decode``, smoothed into Bézier curves unless ``smooth`` is 0) and their lane graphs
(``lane_graph``).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch

from cmtool.core.errors import CmtoolError
from cmtool.core.geometry import bezier_fit_matrix
from cmtool.core.tables import from_table
from cmtool.core.workers import model_threads
from cmtool.data.hd_raster import rasterize_scene
from cmtool.diffusion.noise import batch_noise
from cmtool.diffusion.samplers import sample
from cmtool.diffusion.schedule import NoiseSchedule
from cmtool.diffusion.settings import DEFAULT_SAMPLER, SamplerSettings
from cmtool.maps.lanegraph import LaneGraph, infer_successors, join_successors
from cmtool.maps.neighbours import with_neighbours
from cmtool.model import checkpoint as ckpt
from cmtool.model.config import ScheduleConfig
from cmtool.model.controlmap import NO_LAYOUT, ControlMap, control_images, sd_tensor
from cmtool.model.rvae import ELEMENTS, decoded_elements
from cmtool.sample import DEFAULT_SMOOTH

NONE = "none"  # the --city value for the null label
PRECISIONS = ("fp32", "bf16")  # of the denoising model and the step previews (maps are decoded in fp32)


class MapGenerator:
    """Sampling with a loaded checkpoint: labels, control rasters in, latents and lane graphs out."""

    def __init__(self, model, rvae, config: dict, path: Path, device: torch.device, smooth: int = DEFAULT_SMOOTH,
                 precision: str = "fp32"):
        self.model, self.rvae, self.config, self.path, self.device = model, rvae, config, path, device
        if precision not in PRECISIONS:
            raise CmtoolError(f"--precision: {precision!r} (choose {', '.join(PRECISIONS)})")
        self.precision = precision
        points = rvae.config.num_points
        if smooth != 0 and not 2 <= smooth <= points:
            raise CmtoolError(f"--smooth: 0 (the decoder's raw points) or 2..{points} control points, got {smooth}")
        self.smooth = smooth
        self._fit = bezier_fit_matrix(points, smooth) if smooth else None
        self.cities: list[str] = list(config["cities"])
        self.scale = float(config["latent_scale"])
        self.schedule = NoiseSchedule(from_table(ScheduleConfig, config["schedule"], f"{path}: ", "schedule."))
        self.encoder = self.encoder_path = None  # another RVAE's encoder into this latent space (attach_encoder)
        self.rvae_checkpoint: Path | None = None  # the RVAE checkpoint it decodes with (load: checked against config)
        self.rvae_path: Path | None = None  # the RVAE checkpoint, when it holds an encoder that encode loads

    @classmethod
    def load(cls, path, device="cpu", smooth: int = DEFAULT_SMOOTH, precision: str = "fp32") -> "MapGenerator":
        """The checkpoint at ``path`` and its RVAE; ``smooth``: Bézier control points of decoded polylines
        (0: raw); ``precision``: "bf16" runs the denoising model and the decoding of step previews under bf16
        autocast (maps are decoded in fp32)."""
        path = ckpt.resolve(path)
        config = ckpt.load_config(path)
        if config["kind"] == "rvae":
            raise CmtoolError(f"{path}: an RVAE checkpoint; sampling needs a ControlMap (or DiT) checkpoint")
        for key in ("cities", "latent_scale", "schedule", "rvae"):
            if key not in config:
                raise CmtoolError(f"{path / ckpt.CONFIG}: no {key!r}; not a finished {config['kind']} checkpoint")
        device = torch.device(device)
        if device.type == "cuda":  # full fp32 in matmuls and convolutions: a seed names one map on every device
            torch.backends.cuda.matmul.allow_tf32 = torch.backends.cudnn.allow_tf32 = False
        model, _ = ckpt.load_model(path, device)
        rvae_path = ckpt.rvae_of(path, config)
        rvae, rvae_config = ckpt.load_model(rvae_path, device, encoder=False)  # its encoder: on first use (encode)
        if rvae_config["kind"] != "rvae":
            raise CmtoolError(f"{path}: its rvae {rvae_path} is a {rvae_config['kind']} checkpoint")
        have = (rvae.config.latent_channels, rvae.config.latent_size, rvae.config.latent_size)
        if have != tuple(model.latent_shape):
            raise CmtoolError(f"{path}: the model's latent {tuple(model.latent_shape)} does not match its RVAE "
                              f"{rvae_path} ({have})")
        gen = cls(model, rvae, config, path, device, smooth, precision)
        gen.rvae_checkpoint = rvae_path
        gen.rvae_path = rvae_path if rvae_config.get("weights") != "decoder" else None
        return gen

    @property
    def has_control(self) -> bool:
        return isinstance(self.model, ControlMap)

    @property
    def layout(self) -> str:
        """The layout (``cmtool.data.layouts.LAYOUTS``) whose lanes the control branch reads beside the SD raster,
        or ``"none"``."""
        return self.model.config.layout if self.has_control else NO_LAYOUT

    @property
    def control_blocks(self) -> int:
        """Number of DiT blocks that receive control residuals (0 for a plain DiT)."""
        return len(self.model.copies) if self.has_control else 0

    def label(self, city: str | None) -> int:
        """The label index of ``city`` (None or "none": the null label); unknown names are an error."""
        if city is None or city.lower() == NONE:
            return len(self.cities)
        for i, name in enumerate(self.cities):
            if name.upper() == city.upper():
                return i
        raise CmtoolError(f"unknown city {city!r} for {self.path.name} (choose from {', '.join(self.cities)}, {NONE})")

    def known_label(self, city: str | None) -> int:
        """The label of ``city`` when the checkpoint knows it, else the null label (never an error)."""
        known = {name.upper(): i for i, name in enumerate(self.cities)}
        return known.get((city or "").upper(), len(self.cities))

    def city_name(self, label: int) -> str | None:
        return self.cities[label] if label < len(self.cities) else None

    def batch_noise(self, n: int, seed: int, first: int) -> tuple[torch.Tensor, torch.Generator]:
        """The initial latents of a batch of ``n`` maps whose first is map (or scene) ``first`` of a run seeded
        ``seed``, and the generator of its step noise (:func:`cmtool.diffusion.noise.batch_noise`)."""
        return batch_noise((n, *self.model.latent_shape), seed, first, self.device)

    def generate(self, sd: np.ndarray | None, labels, settings: SamplerSettings, first: int = 0, *,
                 city_cfg: float = 1.0, eta: float = 0.0, init: torch.Tensor | None = None, strength: float = 1.0,
                 layouts: list | None = None, metas: list[dict] | None = None, callback=None,
                 found: bool = True) -> list[LaneGraph]:
        """The lane graphs of one batch: maps ``first, first + 1, ...`` of a run sampled as ``settings`` say, for SD
        rasters ``sd`` (B, 128, 128, 3) uint8 (None: the DiT alone) and label indices ``labels`` (B,); ``init``,
        ``strength``: start from these latents (:meth:`encode`); ``layouts``: each map's layout raster
        (:func:`cmtool.data.layouts.layout_raster`, None: none) when the branch reads one (:attr:`layout`);
        ``metas``: each map's meta entries; ``callback``: called with every step's
        :class:`~cmtool.diffusion.samplers.StepInfo`; ``found``: False leaves the lanes' neighbours to be found
        later (:func:`~cmtool.maps.neighbours.with_neighbours`). The noise depends on ``settings.seed`` and ``first``
        alone, and the model runs on a fixed number of threads (:func:`~cmtool.core.workers.model_threads`): a seed
        gives one map whatever the cores, torch's threads or the worker processes."""
        noise, steps = self.batch_noise(len(labels), settings.seed, first)
        with model_threads():
            z = self.sample(sd, labels, cfg=settings.cfg, city_cfg=city_cfg, steps=settings.steps,
                            sampler=settings.sampler, eta=eta, noise=noise, generator=steps, init=init,
                            strength=strength, layouts=layouts, callback=callback)
            elements = self.decode(z)
        metas = metas or [{} for _ in labels]
        return [self.lane_graph(el, self.city_name(y), meta, found) for el, y, meta in zip(elements, labels, metas)]

    def generate_all(self, sds: np.ndarray | None, labels, settings: SamplerSettings, metas: list[dict] | None = None,
                     city_cfg: float = 1.0, init: torch.Tensor | None = None, strength: float = 1.0,
                     layouts: list | None = None) -> list[LaneGraph]:
        """:meth:`generate` over all maps, ``settings.batch`` at a time, in one process."""
        maps = []
        for b0 in range(0, len(labels), settings.batch):
            part = slice(b0, b0 + settings.batch)
            maps += self.generate(None if sds is None else sds[part], labels[part], settings, b0, city_cfg=city_cfg,
                                  init=None if init is None else init[part], strength=strength,
                                  layouts=None if layouts is None else layouts[part],
                                  metas=None if metas is None else metas[part])
        return maps

    def sample(self, sd: np.ndarray | None, labels, *, cfg: float, steps: int, sampler: str = DEFAULT_SAMPLER,
               city_cfg: float = 1.0, eta: float = 0.0, generator: torch.Generator | None = None,
               noise: torch.Tensor | None = None, init: torch.Tensor | None = None, strength: float = 1.0,
               layouts: list | None = None, callback=None) -> torch.Tensor:
        """Clean latents (B, C, H, W) in the DiT's scaled space for SD rasters ``sd`` (B, 128, 128, 3)
        uint8 (None: no control) and label indices ``labels`` (B,); ``noise``: the initial latent;
        ``city_cfg``: guidance on the city label (1: none); ``init``, ``strength``: start from these scaled
        latents, noised ``strength`` of the way (:func:`cmtool.diffusion.samplers.sample`); ``layouts``: as
        :meth:`generate`'s."""
        y = torch.as_tensor(np.asarray(labels, np.int64), device=self.device)
        control = None
        if sd is not None:
            if not self.has_control:
                raise CmtoolError(f"{self.path}: a DiT checkpoint has no control branch; give a ControlMap "
                                  "checkpoint or leave out the SD input")
            images = control_images(self.model.config, sd, layouts)
            control = torch.stack([sd_tensor(c) for c in images]).to(self.device)
        with torch.autocast(self.device.type, dtype=torch.bfloat16, enabled=self.precision == "bf16"):
            return sample(self.model, self.schedule, y, control=control, cfg=cfg, city_cfg=city_cfg, steps=steps,
                          sampler=sampler, eta=eta, generator=generator, noise=noise, init=init, strength=strength,
                          callback=callback)

    def attach_encoder(self, path) -> None:
        """Encode with the encoder of the RVAE checkpoint at ``path``, which must have been trained into this
        checkpoint's latent space (its decoder's, e.g. by ``cmtool train encoder``: the same latent scale)."""
        path = ckpt.resolve(path)
        rvae, config = ckpt.load_model(path, self.device)
        if config["kind"] != "rvae" or rvae.trunk is None:
            raise CmtoolError(f"--encoder {path}: not an RVAE with an encoder (a `cmtool train encoder` or `train "
                              "rvae` run)")
        if abs(float(config.get("latent_scale", math.nan)) - self.scale) > 1e-6:
            raise CmtoolError(f"--encoder {path}: its latent scale {config.get('latent_scale')} is not the "
                              f"checkpoint's {self.scale}: it encodes into another latent space")
        self.encoder, self.encoder_path = rvae, path

    @torch.no_grad()
    def encode(self, scenes) -> torch.Tensor:
        """Scaled latents (N, C, H, W) of scenes (:class:`~cmtool.data.scene.Scene`): their HD rasters through the
        encoder's posterior mean, in the DiT's scaled space."""
        if self.encoder is None and self.rvae.trunk is None and self.rvae_path is not None:
            self.rvae, _ = ckpt.load_model(self.rvae_path, self.device)  # with its encoder, the first time it is used
        encoder = self.encoder if self.encoder is not None else self.rvae
        if encoder.trunk is None:
            raise CmtoolError(f"{self.path}: its RVAE holds no encoder (weights packed without --encoder); give "
                              "--encoder RUN (`cmtool train encoder` trains one for it)")
        if not scenes:
            return torch.zeros((0, *self.model.latent_shape), device=self.device)
        px = self.rvae.config.frame_m / self.rvae.config.raster_px
        rasters = np.stack([rasterize_scene(s.lines, s.line_mask, s.green, s.green_mask, s.red, s.red_mask, px_m=px,
                                            frame_m=self.rvae.config.frame_m) for s in scenes])
        with model_threads():  # as generate's
            mean, _ = encoder.encode(torch.from_numpy(rasters).to(self.device))
        return mean.float() * self.scale

    @torch.no_grad()
    def decode(self, latents: torch.Tensor, threshold: float = 0.5,
               preview: bool = False) -> list[dict[str, np.ndarray]]:
        """Scaled latents (N, C, H, W) -> per latent ``{"lines", "green", "red"}`` polylines (metres), each
        replaced by its least-squares Bézier curve unless ``smooth`` is 0; a graph decoder's predicted
        ``"successors"`` come along, their lanes joined at shared points (after the smoothing). The decoder runs
        in fp32, but for a ``preview`` (a denoising step's estimate in a recording) at the model's precision."""
        with torch.autocast(self.device.type, dtype=torch.bfloat16, enabled=preview and self.precision == "bf16"):
            decoded = self.rvae.decode(latents.to(self.device).float() / self.scale)
        elements = decoded_elements(decoded, threshold)
        for el in elements:
            for name in ELEMENTS:
                if self._fit is not None:
                    el[name] = (self._fit @ el[name]).astype(el[name].dtype)
            if "successors" in el:
                el["lines"] = np.array(join_successors(el["lines"], el["successors"]), np.float32).reshape(
                    el["lines"].shape)
        return elements

    def lane_graph(self, elements: dict[str, np.ndarray], city: str | None, meta: dict,
                   found: bool = True) -> LaneGraph:
        """A decoded latent as a lane graph: successors as the graph decoder predicted them, else inferred
        from endpoint proximity (``meta["successors"]`` says which); points rounded to the millimetre, as the
        file keeps them, so that what is scored here is what a reader of the file scores; ``found``: as
        :meth:`generate`'s."""
        lanes = [np.round(np.asarray(l, np.float64), 3) for l in elements["lines"]]
        predicted = "successors" in elements
        successors = [(int(i), int(j)) for i, j in elements["successors"]] if predicted else infer_successors(lanes)
        meta = meta | {"successors": "predicted" if predicted else "endpoint proximity"}
        graph = LaneGraph(lanes=lanes, successors=successors,
                          green_lights=[np.round(np.asarray(l, np.float64), 3) for l in elements["green"]],
                          red_lights=[np.round(np.asarray(l, np.float64), 3) for l in elements["red"]],
                          city=city, frame_m=float(self.rvae.config.frame_m), meta=meta)
        return with_neighbours(graph) if found else graph
