"""A trained checkpoint set ready to generate maps: ControlMap (or a plain DiT) plus its RVAE.

``Generator.load(ckpt)`` reads a ControlMap or DiT checkpoint (a run folder or one checkpoint
folder), finds the RVAE it was trained on (the path its config records, absolute or relative to
the checkpoint) and checks that the pieces fit. ``sample`` denoises latents for a batch of SD
rasters and city labels; ``decode`` turns them into polylines (smoothed into Bézier curves unless
``smooth`` is 0) and ``lane_graph`` into the lane graph format.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from cmtool import checkpoint as ckpt
from cmtool.data.lanegraph import LaneGraph, infer_successors, join_successors
from cmtool.data.neighbours import find_neighbours, lane_widths
from cmtool.errors import CmtoolError
from cmtool.geometry import bezier_fit_matrix
from cmtool.model.config import ScheduleConfig
from cmtool.model.controlmap import ControlMap, sd_tensor
from cmtool.model.rvae import ELEMENTS, decoded_elements
from cmtool.recipe import from_table
from cmtool.sample import DEFAULT_SAMPLER, DEFAULT_SMOOTH
from cmtool.sample.diffusion import NoiseSchedule, sample, scene_seed, step_generator

NONE = "none"  # the --city value for the null label
PRECISIONS = ("fp32", "bf16")  # of the denoising model and the step previews (maps are decoded in fp32)


class Generator:
    """Sampling with a loaded checkpoint: labels, control rasters in, latents and lane graphs out."""

    def __init__(self, model, rvae, config: dict, path: Path, device: torch.device, smooth: int = DEFAULT_SMOOTH,
                 precision: str = "fp32"):
        self.model, self.rvae, self.config, self.path, self.device = model, rvae, config, path, device
        if precision not in PRECISIONS:
            raise CmtoolError(f"--precision: {precision!r} (choose {', '.join(PRECISIONS)})")
        self.precision = precision
        points = rvae.cfg.num_points
        if smooth != 0 and not 2 <= smooth <= points:
            raise CmtoolError(f"--smooth: 0 (the decoder's raw points) or 2..{points} control points, got {smooth}")
        self.smooth = smooth
        self._fit = bezier_fit_matrix(points, smooth) if smooth else None
        self.cities: list[str] = list(config["cities"])
        self.scale = float(config["latent_scale"])
        self.schedule = NoiseSchedule(from_table(ScheduleConfig, config["schedule"], f"{path}: ", "schedule."))

    @classmethod
    def load(cls, path, device="cpu", smooth: int = DEFAULT_SMOOTH, precision: str = "fp32") -> "Generator":
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
        model, _ = ckpt.load_model(path, device)
        rvae_path = ckpt.linked(path, config["rvae"])
        rvae, rvae_config = ckpt.load_model(rvae_path, device)
        if rvae_config["kind"] != "rvae":
            raise CmtoolError(f"{path}: its rvae {rvae_path} is a {rvae_config['kind']} checkpoint")
        have = (rvae.cfg.latent_channels, rvae.cfg.latent_size, rvae.cfg.latent_size)
        if have != tuple(model.latent_shape):
            raise CmtoolError(f"{path}: the model's latent {tuple(model.latent_shape)} does not match its RVAE "
                              f"{rvae_path} ({have})")
        return cls(model, rvae, config, path, device, smooth, precision)

    @property
    def has_control(self) -> bool:
        return isinstance(self.model, ControlMap)

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
        ``seed``, and the generator of the samplers' step noise: both from ``scene_seed(seed, first)`` alone, so a
        batch's maps depend neither on the batches before it nor on the process that makes them."""
        base = scene_seed(seed, first)
        noise = torch.randn((n, *self.model.latent_shape), generator=torch.Generator().manual_seed(base))
        return noise.to(self.device), step_generator(base, self.device)

    def sample(self, sd: np.ndarray | None, labels, *, cfg: float, steps: int, sampler: str = DEFAULT_SAMPLER,
               city_cfg: float = 1.0, eta: float = 0.0, generator: torch.Generator | None = None,
               noise: torch.Tensor | None = None, callback=None) -> torch.Tensor:
        """Clean latents (B, C, H, W) in the DiT's scaled space for SD rasters ``sd`` (B, 128, 128, 3)
        uint8 (None: no control) and label indices ``labels`` (B,); ``noise``: the initial latent;
        ``city_cfg``: guidance on the city label (1: none)."""
        y = torch.as_tensor(np.asarray(labels, np.int64), device=self.device)
        control = None
        if sd is not None:
            if not self.has_control:
                raise CmtoolError(f"{self.path}: a DiT checkpoint has no control branch; give a ControlMap "
                                  "checkpoint or leave out the SD input")
            control = torch.stack([sd_tensor(s) for s in sd]).to(self.device)
        with torch.autocast(self.device.type, dtype=torch.bfloat16, enabled=self.precision == "bf16"):
            return sample(self.model, self.schedule, y, control=control, cfg=cfg, city_cfg=city_cfg, steps=steps,
                          sampler=sampler, eta=eta, generator=generator, noise=noise, callback=callback)

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

    def lane_graph(self, elements: dict[str, np.ndarray], city: str | None, meta: dict) -> LaneGraph:
        """A decoded latent as a lane graph: successors as the graph decoder predicted them, else inferred
        from endpoint proximity (``meta["successors"]`` says which)."""
        lanes = [np.asarray(l, np.float64) for l in elements["lines"]]
        predicted = "successors" in elements
        successors = [(int(i), int(j)) for i, j in elements["successors"]] if predicted else infer_successors(lanes)
        meta = meta | {"successors": "predicted" if predicted else "endpoint proximity"}
        left, oncoming = find_neighbours(lanes)
        return LaneGraph(lanes=lanes, successors=successors, left_neighbors=left, oncoming=oncoming,
                         widths=lane_widths(lanes, left).round(2).tolist(),
                         green_lights=[np.asarray(l, np.float64) for l in elements["green"]],
                         red_lights=[np.asarray(l, np.float64) for l in elements["red"]],
                         city=city, frame_m=float(self.rvae.cfg.frame_m), meta=meta)
