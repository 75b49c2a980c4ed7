"""The training stages: RVAE (1), its decoder fine-tuned on a frozen encoder (1b), an encoder for a frozen
decoder (1c), DiT baseline (2), ControlMap's control branch (3)."""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from cmtool.core.errors import CmtoolError
from cmtool.data.cache import load_dataset, load_manifest
from cmtool.data.layouts import scene_layout_rasters
from cmtool.data.sd_raster import ENCODINGS
from cmtool.diffusion.samplers import sample
from cmtool.diffusion.schedule import NoiseSchedule
from cmtool.maps.hdmap import drives_on
from cmtool.model import checkpoint as ckpt
from cmtool.model.controlmap import NO_LAYOUT, SD_CHANNELS, ControlMap, control_images, sd_tensor
from cmtool.model.dit import DiT, DiTConfig
from cmtool.model.rvae import ENCODER_PREFIXES, RVAE, decoded_elements, same_encoder
from cmtool.model.rvae_loss import denoise_input, rvae_loss
from cmtool.train.data import CachedPosteriors, Latents, SceneRasters, scene_raster, shift_sideways
from cmtool.train.latents import data_latents, latent_dir, mirrored_latents, read_latents, write_latents
from cmtool.train.loop import Stage
from cmtool.train.reconstruction import reconstruction_scores
from cmtool.viz.recording import log_lanes, log_sd

PREVIEWS = 4  # scenes shown in the training recording's previews
RECON_EVAL = 512  # held-out scenes scored after RVAE training


def _path(value: str, key: str, where) -> Path:
    """The folder the recipe's ``train.KEY`` names; a run or checkpoint that is not there yet names the stage that
    makes it."""
    if not value:
        raise CmtoolError(f"{where}: train.{key} is not set (the recipe must name it)")
    path = Path(value)
    if key in ("rvae", "dit") and not path.exists():
        raise CmtoolError(f"{path}: no such run (train.{key} of {where}); train the {key} stage into it first: "
                          f"`cmtool train {key} --recipe RECIPE --out {path}`")
    return path


def _brief(config: dict) -> str:
    return f"depth {config['depth']}, hidden {config['hidden']}, heads {config['heads']}"


def _train_scenes(data_dir, latents, cache):
    """The train split of ``data_dir``, checked to line up scene by scene with the latent cache."""
    scenes = load_dataset(data_dir, "train")
    if len(scenes) != len(latents.mean) or not np.array_equal(scenes.arrays["pose"], latents.pose):
        raise CmtoolError(f"{data_dir}: its train split does not match the latent cache {cache} "
                          "(train.data must be the dataset the RVAE was trained on)")
    return scenes


def _check_queries(model: dict, data_dir, where, fix: str) -> None:
    """Refuse an RVAE with fewer line or light queries than the dataset's scenes have slots: the matching would
    leave the lines beyond them unmatched, unseen by the loss."""
    data = load_manifest(data_dir)["recipe"]
    for key in ("num_lines", "num_lights"):
        m, n = model[key], data[key]
        if m < n:
            raise CmtoolError(f"{where}: rvae.{key} {m} is fewer than the dataset's {key} {n} ({data_dir}): a scene's "
                              f"lines beyond {m} would go unmatched; {fix.format(key=key, m=m, n=n)}")


def _preview_split(data_dir) -> str:
    return "test" if "test" in load_manifest(data_dir)["splits"] else "train"


class RVAEStage(Stage):
    """Stage 1: HD raster -> latent -> lane vectors."""

    kind = "rvae"

    def __init__(self, recipe, device):
        super().__init__(recipe, device)
        self.data_dir = _path(recipe.train.data, "data", recipe.path)
        manifest = load_manifest(self.data_dir)
        px = round(manifest["frame_m"] / manifest["px_m"])
        if px != recipe.rvae.raster_px or manifest["frame_m"] != recipe.rvae.frame_m:
            raise CmtoolError(f"{recipe.path}: rvae.raster_px {recipe.rvae.raster_px} / frame_m {recipe.rvae.frame_m} "
                              f"do not match the dataset {self.data_dir} ({px} px over {manifest['frame_m']} m)")
        _check_queries(dataclasses.asdict(recipe.rvae), self.data_dir, recipe.path,
                       "set rvae.{key} = {n} in [rvae], or build the data with data.{key} = {m}")
        self._preview = None

    def model(self, weights=True):
        return RVAE(self.recipe.rvae)

    def dataset(self):
        return SceneRasters(load_dataset(self.data_dir, "train"))

    def loss(self, model, batch):
        weights = self.recipe.rvae_loss
        decoded, mean, logvar = model(batch["raster"], aux=weights.aux_weight > 0,
                                      denoise=denoise_input(batch, weights))
        return rvae_loss(decoded, mean, logvar, batch, self.recipe.rvae_loss)

    def config(self):
        return {"kind": self.kind, "model": dataclasses.asdict(self.recipe.rvae),
                "loss": dataclasses.asdict(self.recipe.rvae_loss), "data": str(self.data_dir.resolve())}

    def preview(self, model, rec):
        if self._preview is None:
            scenes = load_dataset(self.data_dir, _preview_split(self.data_dir))
            self._preview = [(scene_raster(scenes, i), scenes.lines[i][scenes.line_mask[i]])
                             for i in range(min(PREVIEWS, len(scenes)))]
        raster = torch.stack([raster for raster, _ in self._preview]).to(self.device)
        with torch.no_grad():
            mean, _ = model.encode(raster)
            elements = decoded_elements(model.decode(mean))
        for k, ((_, truth), el) in enumerate(zip(self._preview, elements)):
            log_lanes(rec, f"train/preview/sample_{k}/truth/", truth)
            log_lanes(rec, f"train/preview/sample_{k}/decoded/", el["lines"], el["green"], el["red"])

    def preview_views(self):
        return [(f"scene {k}: {title}", f"sample_{k}", [f"{part}/**"]) for k in range(PREVIEWS)
                for title, part in (("ground truth", "truth"), ("decoded", "decoded"))]

    def finish(self, model, run_dir):
        scale = write_latents(model, self.data_dir, run_dir / "latents", self.device,
                              ckpt.weights_digest(ckpt.resolve(run_dir)))
        recon = reconstruction_scores(model, self.data_dir, _preview_split(self.data_dir), self.device, RECON_EVAL)
        print(f"rvae: latent scale {scale:.4f}; held-out reconstruction at 1 m: precision {recon['precision']:.3f} "
              f"recall {recon['recall']:.3f} F1 {recon['f1']:.3f} ({recon['scenes']} scenes)")
        return {"latent_scale": scale, "latents": "latents", "reconstruction": recon}


class DecoderStage(RVAEStage):
    """Stage 1b: train the decoder of a finished RVAE further, its encoder frozen.

    The decoder learns from the parent run's latent cache (a posterior sample per scene and step),
    so the latent space, and with it every DiT and ControlMap trained on that cache, stays valid:
    the result is an RVAE checkpoint they can decode with (``cmtool pack --rvae``). The model is
    the parent's (the recipe's ``[rvae]`` section is not used); ``[rvae_loss]`` weighs the loss.
    """

    name = "decoder"

    def __init__(self, recipe, device):
        Stage.__init__(self, recipe, device)
        self.data_dir = _path(recipe.train.data, "data", recipe.path)
        self.parent_run = _path(recipe.train.rvae, "rvae", recipe.path).resolve()
        self.parent_config = ckpt.load_config(self.parent_run)
        if self.parent_config["kind"] != "rvae" or "latent_scale" not in self.parent_config:
            raise CmtoolError(f"{self.parent_run}: train.rvae must be a finished RVAE run (with its latent cache)")
        self.latents = latent_dir(self.parent_run, self.parent_config).resolve()
        _check_queries(self.parent_config["model"], self.data_dir, self.parent_run,
                       "the decoder keeps its RVAE's queries: train it on data built with data.{key} = {m}")
        self._preview = None

    def model(self, weights=True):
        model = ckpt.load_model(self.parent_run, "cpu")[0] if weights else ckpt.build_model(self.parent_config)
        if model.trunk is None:
            raise CmtoolError(f"{self.parent_run}: a decoder-only RVAE; the decoder stage needs the full run")
        for p in (*model.trunk.parameters(), *model.to_latent.parameters()):
            p.requires_grad_(False)
        return model

    def dataset(self):
        lat = read_latents(self.latents, "train")
        scenes = _train_scenes(self.data_dir, lat, self.latents)
        return CachedPosteriors(lat.mean, lat.logvar, scenes)

    def loss(self, model, batch):
        weights = self.recipe.rvae_loss
        decoded, mean, logvar = model(None, posterior=(batch["mean"], batch["logvar"]), aux=weights.aux_weight > 0,
                                      denoise=denoise_input(batch, weights))
        return rvae_loss(decoded, mean, logvar, batch, self.recipe.rvae_loss)

    def config(self):
        return {"kind": self.kind, "model": self.parent_config["model"],
                "loss": dataclasses.asdict(self.recipe.rvae_loss), "data": str(self.data_dir.resolve()),
                "encoder_from": str(ckpt.resolve(self.parent_run))}

    def finish(self, model, run_dir):
        if not same_encoder(model.state_dict(), ckpt.read_weights(ckpt.resolve(self.parent_run))):
            raise CmtoolError(f"{run_dir}: the encoder changed during decoder training (it must stay frozen)")
        recon = reconstruction_scores(model, self.data_dir, _preview_split(self.data_dir), self.device, RECON_EVAL)
        before = self.parent_config.get("reconstruction", {}).get("f1", float("nan"))
        print(f"decoder: held-out reconstruction at 1 m: precision {recon['precision']:.3f} recall "
              f"{recon['recall']:.3f} F1 {recon['f1']:.3f} ({recon['scenes']} scenes; "
              f"the parent RVAE: F1 {before:.3f})")
        return {"latent_scale": self.parent_config["latent_scale"], "latents": str(self.latents),
                "reconstruction": recon}


class EncoderStage(RVAEStage):
    """Stage 1c: train an encoder for a frozen decoder, e.g. the shipped decoder-only weights.

    The decoder (and with it the latent space every DiT and ControlMap trained on it reads) is the
    parent's, loaded and frozen; a fresh encoder learns to map HD rasters into that space under the
    RVAE loss. The parent's latent scale is kept, so the result encodes maps for the parent's DiT and
    ControlMap (SDEdit from a layout, inpainting, a latent cache for a new control branch). The model
    is the parent's (``[rvae]`` is not used); ``[rvae_loss]`` weighs the loss.
    """

    name = "encoder"

    def __init__(self, recipe, device):
        Stage.__init__(self, recipe, device)
        self.data_dir = _path(recipe.train.data, "data", recipe.path)
        self.parent = ckpt.resolve(_path(recipe.train.rvae, "rvae", recipe.path)).resolve()
        self.parent_config = ckpt.load_config(self.parent)
        if self.parent_config["kind"] != "rvae" or "latent_scale" not in self.parent_config:
            raise CmtoolError(f"{self.parent}: train.rvae must be an RVAE checkpoint with a latent scale "
                              "(a finished RVAE run, or packed weights such as cmtool/weights/rvae)")
        _check_queries(self.parent_config["model"], self.data_dir, self.parent,
                       "the encoder keeps its decoder's queries: train it on data built with data.{key} = {m}")
        self._preview = None

    def model(self, weights=True):
        model = ckpt.build_model({**self.parent_config, "weights": "full"}, str(self.parent))
        if weights:
            self._load_decoder(model)
        for name, p in model.named_parameters():
            p.requires_grad_(name.startswith(ENCODER_PREFIXES))
        return model

    def _load_decoder(self, model: RVAE) -> None:
        """The parent's decoder weights into ``model``, checked to fit it."""
        decoder = {k: v for k, v in ckpt.read_weights(self.parent).items() if not k.startswith(ENCODER_PREFIXES)}
        own = model.state_dict()
        missing = sorted(k for k in own if not k.startswith(ENCODER_PREFIXES) and k not in decoder)
        shaped = sorted(k for k, v in decoder.items() if k in own and v.shape != own[k].shape)
        if missing or set(decoder) - set(own) or shaped:
            problem = "unexpected weights"
            if missing:
                problem = f"missing {missing[0]}"
            elif shaped:
                problem = f"{shaped[0]} of shape {tuple(decoder[shaped[0]].shape)}, not {tuple(own[shaped[0]].shape)}"
            raise CmtoolError(f"{self.parent}: its decoder weights do not match its config ({problem})")
        model.load_state_dict({k: v.to(own[k].dtype) for k, v in decoder.items()}, strict=False)

    def config(self):
        return {"kind": self.kind, "model": self.parent_config["model"],
                "loss": dataclasses.asdict(self.recipe.rvae_loss), "data": str(self.data_dir.resolve()),
                "decoder_from": str(self.parent)}

    def finish(self, model, run_dir):
        parent = ckpt.read_weights(self.parent)
        own = model.state_dict()
        if any(not torch.equal(v.to(own[k].dtype).cpu(), own[k].cpu()) for k, v in parent.items()
               if not k.startswith(ENCODER_PREFIXES)):
            raise CmtoolError(f"{run_dir}: the decoder changed during encoder training (it must stay frozen)")
        scale = write_latents(model, self.data_dir, run_dir / "latents", self.device,
                              ckpt.weights_digest(ckpt.resolve(run_dir)))
        kept = float(self.parent_config["latent_scale"])
        recon = reconstruction_scores(model, self.data_dir, _preview_split(self.data_dir), self.device, RECON_EVAL)
        print(f"encoder: the latent scale of its train means {scale:.4f} (the decoder's, kept: {kept:.4f}); "
              f"held-out reconstruction at 1 m: precision {recon['precision']:.3f} recall {recon['recall']:.3f} "
              f"F1 {recon['f1']:.3f} ({recon['scenes']} scenes)")
        return {"latent_scale": kept, "own_latent_scale": scale, "latents": "latents", "reconstruction": recon}


class _DiffusionStage(Stage):
    """Shared by stages 2 and 3: epsilon-prediction DDPM loss on scaled RVAE latents."""

    def __init__(self, recipe, device):
        super().__init__(recipe, device)
        self.rvae_run = _path(recipe.train.rvae, "rvae", recipe.path).resolve()
        self.rvae_config = ckpt.load_config(self.rvae_run)
        if self.rvae_config["kind"] != "rvae" or "latent_scale" not in self.rvae_config:
            raise CmtoolError(f"{self.rvae_run}: not a finished RVAE run (no latent scale); finish it with "
                              "`cmtool train rvae --resume`")
        self.scale = float(self.rvae_config["latent_scale"])
        self.rvae_weights = ckpt.weights_digest(ckpt.resolve(self.rvae_run))  # its latents' key; checked in sampling
        self.latent_dir = latent_dir(self.rvae_run, self.rvae_config)
        self.schedule = NoiseSchedule(recipe.diffusion)
        self.shift_px = 0  # train.sd_shift_m in SD raster pixels (controlnet stage)
        self._rvae = None

    def rvae(self) -> RVAE:
        if self._rvae is None:
            self._rvae, _ = ckpt.load_model(self.rvae_run, self.device)
        return self._rvae

    def labels(self, cities: np.ndarray) -> np.ndarray:
        lookup = {c: i for i, c in enumerate(self.cities)}
        return np.array([lookup.get(str(c), len(self.cities)) for c in cities], np.int64)

    def mirror_labels(self, cities: np.ndarray) -> np.ndarray:
        """Per scene, the label of a city driving on the other side (cycling through them when several)."""
        sides = {side: [i for i, c in enumerate(self.cities) if drives_on(c) == side] for side in ("left", "right")}
        if not all(sides.values()):
            raise CmtoolError(f"train.mirror needs train cities driving on each side; {', '.join(self.cities)} "
                              f"all drive on the {'left' if sides['left'] else 'right'}")
        out = np.empty(len(cities), np.int64)
        for i, city in enumerate(cities):
            other = sides["right" if drives_on(str(city)) == "left" else "left"]
            out[i] = other[i % len(other)]
        return out

    def mirrored(self, data_dir, cities: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``train.mirror``: the train scenes' posteriors mirrored left-right (encoded once into the latent
        cache) and the labels they take."""
        flipped = mirrored_latents(self.rvae, data_dir, self.latent_dir, self.device)
        return flipped.mean, flipped.logvar, self.mirror_labels(cities)

    def diffusion_loss(self, model, batch, **extra):
        mean, logvar, y = batch["mean"], batch["logvar"], batch["label"]
        keep_label = torch.zeros_like(y, dtype=torch.bool)
        if "mirror_mean" in batch:  # train.mirror: swap in mirrored scenes, whose labels are never dropped
            keep_label = torch.rand(len(y), device=y.device) < self.recipe.train.mirror
            pick = lambda a, b: torch.where(keep_label.view(-1, *[1] * (a.dim() - 1)), b, a)  # noqa: E731
            mean, logvar, y = pick(mean, batch["mirror_mean"]), pick(logvar, batch["mirror_logvar"]), \
                pick(y, batch["mirror_label"])
            if "control" in extra:
                extra["control"] = pick(extra["control"], batch["mirror_sd"])
        if self.shift_px:
            extra["control"] = shift_sideways(extra["control"], self.shift_px)
        z = (mean + torch.exp(0.5 * logvar) * torch.randn_like(mean)) * self.scale
        t = torch.randint(0, self.schedule.config.train_steps, (len(z),), device=z.device)
        noise = torch.randn_like(z)
        drop = (torch.rand(len(y), device=y.device) < self.recipe.train.label_dropout) & ~keep_label
        y = torch.where(drop, torch.full_like(y, len(self.cities)), y)
        eps = model(self.schedule.q_sample(z, t, noise), t, y, **extra)
        gamma = self.recipe.train.min_snr_gamma
        if not gamma:
            return F.mse_loss(eps.float(), noise), {}
        per_scene = (eps.float() - noise).square().flatten(1).mean(1)
        return (self.schedule.min_snr_weight(t, gamma) * per_scene).mean(), {"mse": float(per_scene.mean())}

    def decode(self, latents: torch.Tensor) -> list[dict]:
        with torch.no_grad():
            return decoded_elements(self.rvae().decode(latents / self.scale))

    def common_config(self):
        return {"cities": self.cities, "schedule": dataclasses.asdict(self.recipe.diffusion),
                "latent_scale": self.scale, "rvae": str(self.rvae_run), "rvae_weights": self.rvae_weights}


class DiTStage(_DiffusionStage):
    """Stage 2: the SLEDGE baseline, a DiT over latents conditioned on the city label."""

    kind = "dit"

    def __init__(self, recipe, device):
        super().__init__(recipe, device)
        data = _path(recipe.train.data, "data", recipe.path) if recipe.train.data else None
        if data is not None and data.resolve() != Path(self.rvae_config.get("data", "")).resolve():
            # other data than the RVAE's (e.g. the shipped DiT trained further on real roads): encoded once
            self.latents, self.latent_dir = data_latents(self.rvae, self.rvae_weights, data, self.device)
        else:
            self.latents = read_latents(self.latent_dir, "train")
        self.init_from = ckpt.resolve(recipe.train.init_from).resolve() if recipe.train.init_from else None
        # a DiT trained further keeps its labels (a city it does not know trains its null label); else the data's
        self.cities = ckpt.load_config(self.init_from)["cities"] if self.init_from else \
            sorted({str(c) for c in self.latents.city})
        self.dit_config = dataclasses.replace(recipe.dit, num_classes=len(self.cities)).resolved()

    def model(self, weights=True):
        model = DiT(self.dit_config)
        if weights and self.init_from is not None:
            model.load_state_dict(self.init_weights())
        return model

    def init_weights(self) -> dict[str, torch.Tensor]:
        """The DiT weights of ``train.init_from`` (a DiT, or a ControlMap's frozen base), checked to fit."""
        path, config = self.init_from, ckpt.load_config(self.init_from)
        if config["kind"] not in ("dit", "controlmap"):
            raise CmtoolError(f"{path}: a {config['kind']} checkpoint; train.init_from needs a DiT or a ControlMap")
        if config["model"] != ckpt.as_stored(self.dit_config):
            raise CmtoolError(f"{path}: its DiT ({_brief(config['model'])}) is not the one this recipe builds "
                              f"({_brief(dataclasses.asdict(self.dit_config))})")
        if config.get("latent_scale") != self.scale:
            print(f"warning: {path} was trained on other latents (latent scale {config.get('latent_scale')}, this "
                  f"RVAE's {self.scale}); its weights are only a starting point", file=sys.stderr)
        tensors = ckpt.read_weights(path)
        if config["kind"] == "controlmap":
            tensors = {k[len("base."):]: v for k, v in tensors.items() if k.startswith("base.")}
        return {k: v.float() for k, v in tensors.items()}

    def init_record(self) -> dict:
        """How the DiT of ``train.init_from`` was trained (recorded in this run's config)."""
        source = ckpt.load_config(self.init_from)
        dit = source if source["kind"] == "dit" else \
            source.get("dit_training") or ckpt.load_config(ckpt.linked(self.init_from, source["dit"]))
        return {"path": str(self.init_from), "latent_scale": source["latent_scale"],
                **{k: v for k, v in dit.items() if k in ckpt.DIT_RECORD}}

    def dataset(self):
        lat = self.latents
        mirrored = None
        if self.recipe.train.mirror > 0:  # the scenes, for drawing them mirrored: train.data or the RVAE's
            data_dir = Path(self.recipe.train.data or self.rvae_config["data"])
            _train_scenes(data_dir, lat, self.latent_dir)
            mirrored = self.mirrored(data_dir, lat.city)
        return Latents(lat.mean, lat.logvar, self.labels(lat.city), mirrored=mirrored)

    def loss(self, model, batch):
        return self.diffusion_loss(model, batch)

    def config(self):
        return {"kind": self.kind, "model": dataclasses.asdict(self.dit_config), **self.common_config(),
                **({"init_from": self.init_record()} if self.init_from else {})}

    def preview(self, model, rec):
        y = torch.arange(PREVIEWS, device=self.device) % (len(self.cities) + 1)
        gen = torch.Generator(self.device).manual_seed(0)
        z = sample(model, self.schedule, y, steps=self.recipe.train.preview_steps, generator=gen)
        for k, el in enumerate(self.decode(z)):
            log_lanes(rec, f"train/preview/sample_{k}/", el["lines"], el["green"], el["red"])

    def preview_views(self):
        names = [*self.cities, "no city"]
        return [(f"sample {k}: {names[k % len(names)]}", f"sample_{k}", ["**"]) for k in range(PREVIEWS)]


class ControlNetStage(_DiffusionStage):
    """Stage 3: ControlMap's control branch on the frozen DiT, conditioned on the SD raster."""

    kind = "controlmap"

    def __init__(self, recipe, device):
        super().__init__(recipe, device)
        self.dit_path = ckpt.resolve(_path(recipe.train.dit, "dit", recipe.path)).resolve()
        dit_config = ckpt.load_config(self.dit_path)
        if dit_config["kind"] not in ("dit", "controlmap"):
            raise CmtoolError(f"{self.dit_path}: a {dit_config['kind']} checkpoint, train.dit needs a DiT (or a "
                              "ControlMap, whose frozen DiT it takes)")
        self.dit_config = dit_config
        self.cities = dit_config["cities"]
        wanted = dataclasses.asdict(dataclasses.replace(recipe.dit, num_classes=len(self.cities)).resolved())
        have = dataclasses.asdict(DiTConfig(**dit_config["model"]).resolved())
        if wanted != have:
            raise CmtoolError(f"{recipe.path}: the [dit] section ({_brief(wanted)}) does not match the DiT "
                              f"checkpoint {self.dit_path} ({_brief(have)})")
        if dataclasses.asdict(recipe.diffusion) != dit_config["schedule"]:
            raise CmtoolError(f"{recipe.path}: the [diffusion] schedule differs from the DiT checkpoint's "
                              f"({dit_config['schedule']}); the control branch must train on the DiT's schedule")
        self.data_dir = _path(recipe.train.data, "data", recipe.path)
        manifest = load_manifest(self.data_dir)
        px_m = manifest["frame_m"] / recipe.control.image_px
        drawn = manifest.get("sd_encoding", 1)  # datasets built before the road class came into the SD raster: 1
        if drawn < recipe.control.sd_encoding:
            raise CmtoolError(f"{self.data_dir}: its SD rasters are of encoding {drawn} ({ENCODINGS[drawn]}); this "
                              f"branch reads encoding {recipe.control.sd_encoding} "
                              f"({ENCODINGS[recipe.control.sd_encoding]}): build the data again with `cmtool data "
                              "build` into a new folder")
        self.shift_px = round(recipe.train.sd_shift_m / px_m)
        if Path(self.rvae_config.get("data", "")).resolve() != self.data_dir.resolve():  # not the RVAE's own data
            self.latents, self.latent_dir = data_latents(self.rvae, self.rvae_weights, self.data_dir, self.device)
        else:
            self.latents = read_latents(self.latent_dir, "train")
        self.branch_from = ckpt.resolve(recipe.train.branch_from).resolve() if recipe.train.branch_from else None
        self.layout = recipe.control.layout
        if self.layout != NO_LAYOUT and recipe.train.mirror > 0:
            raise CmtoolError(f"{recipe.path}: train.mirror does not mirror layout channels; leave it at 0 with "
                              "control.layout")
        if recipe.train.layout_dropout and self.layout == NO_LAYOUT:
            raise CmtoolError(f"{recipe.path}: train.layout_dropout needs control.layout")
        self._preview = self._preview_control = None

    def model(self, weights=True):
        dit = ckpt.load_model(self.dit_path, "cpu")[0] if weights else ckpt.build_model(self.dit_config)
        model = ControlMap(dit.base if isinstance(dit, ControlMap) else dit, self.recipe.control)
        if weights and self.branch_from is not None:
            self.load_branch(model)
        model.freeze_base()
        return model

    def load_branch(self, model: ControlMap) -> None:
        """Copy the control branch (everything but the base DiT) of ``train.branch_from`` into ``model``. A branch
        without layout channels starts one that reads them: their input weights start at zero, so the new branch
        computes what the old one did until training moves them."""
        path = self.branch_from
        config = ckpt.load_config(path)
        control = dataclasses.asdict(self.recipe.control)
        source = {"in_channels": SD_CHANNELS, "layout": NO_LAYOUT, **(config.get("control") or {}),
                  "sd_encoding": control["sd_encoding"]}  # a branch of the old encoding starts one of the new
        if source["layout"] == NO_LAYOUT:
            control |= {"in_channels": SD_CHANNELS, "layout": NO_LAYOUT}
        wanted = ckpt.as_stored({"control": control, "model": self.dit_config["model"]})
        if config["kind"] != "controlmap" or {"control": source, "model": config.get("model")} != wanted:
            raise CmtoolError(f"{path}: train.branch_from needs a ControlMap with this recipe's [control] (or the "
                              f"same without a layout) and DiT size")
        branch = {k: v for k, v in ckpt.read_weights(path).items() if not k.startswith("base.")}
        own = {k: v for k, v in model.state_dict().items() if not k.startswith("base.")}
        if set(branch) != set(own):
            raise CmtoolError(f"{path}: its control branch does not match the model this recipe builds")
        for key, value in branch.items():
            if value.shape != own[key].shape:  # the first convolution: zero weights for the layout channels
                value = torch.cat([value, value.new_zeros(own[key].shape[0], own[key].shape[1] - value.shape[1],
                                                          *value.shape[2:])], dim=1)
            branch[key] = value.to(own[key].dtype)
        model.load_state_dict(branch, strict=False)

    def dataset(self):
        lat = self.latents
        scenes = _train_scenes(self.data_dir, lat, self.latent_dir)
        mirrored = self.mirrored(self.data_dir, lat.city) if self.recipe.train.mirror > 0 else None
        images = self.control_images(scenes, "train", scenes.arrays["sd"])
        return Latents(lat.mean, lat.logvar, self.labels(lat.city), images, mirrored)

    def control_images(self, scenes, split: str, sd: np.ndarray) -> np.ndarray:
        """The control images of the first scenes of a split, whose SD rasters are ``sd``: with the layout channels
        when the branch reads them."""
        layouts = None if self.layout == NO_LAYOUT else scene_layout_rasters(self.data_dir, split, scenes, self.layout)
        return control_images(self.recipe.control, sd, layouts)

    def loss(self, model, batch):
        control = batch["sd"]
        if self.recipe.train.layout_dropout:
            drop = torch.rand(len(control), device=control.device) < self.recipe.train.layout_dropout
            control = torch.cat([control[:, :SD_CHANNELS], control[:, SD_CHANNELS:] * ~drop.view(-1, 1, 1, 1)], 1)
        return self.diffusion_loss(model, batch, control=control)

    def config(self):
        return {"kind": self.kind, "model": self.dit_config["model"], "control": dataclasses.asdict(self.recipe.control),
                **self.common_config(), "dit": str(self.dit_path),
                **({"branch_from": str(self.branch_from)} if self.branch_from else {})}

    def preview(self, model, rec):
        if self._preview is None:
            split = _preview_split(self.data_dir)
            scenes = load_dataset(self.data_dir, split)
            self._preview = [scenes.scene(i) for i in range(min(PREVIEWS, len(scenes)))]
            self._preview_control = self.control_images(self._preview, split, np.stack([s.sd for s in self._preview]))
        control = torch.stack([sd_tensor(c) for c in self._preview_control]).to(self.device)
        y = torch.full((len(control),), len(self.cities), device=self.device)
        gen = torch.Generator(self.device).manual_seed(0)
        z = sample(model, self.schedule, y, control=control, cfg=1.0, steps=self.recipe.train.preview_steps,
                   generator=gen)
        for k, (scene, el) in enumerate(zip(self._preview, self.decode(z))):
            log_sd(rec, f"train/preview/sample_{k}/", scene.sd, scene.frame_m)
            log_lanes(rec, f"train/preview/sample_{k}/generated/", el["lines"], el["green"], el["red"])

    def preview_views(self):
        return [(f"scene {k}: SD and generated", f"sample_{k}", ["**"]) for k in range(PREVIEWS)]


STAGES = {"rvae": RVAEStage, "decoder": DecoderStage, "encoder": EncoderStage, "dit": DiTStage,
          "controlnet": ControlNetStage}
