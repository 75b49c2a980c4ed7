"""The model set that ships inside the package, so that ``cmtool sample`` works without training.

``cmtool pack --ckpt RUN`` turns a trained ControlMap (whose config names its RVAE and DiT) into
``cmtool/weights/``::

    controlmap/   config.json + model.safetensors   frozen DiT + control branch, float16
    rvae/         config.json + model.safetensors   the RVAE's decoder (latent -> lanes), float16, and with
                                                    ``--encoder`` an encoder into its latent space (HD -> latent)
    MANIFEST.json                                   SHA-256 and size of every file, where they came from

Weights over 16 MiB are split into files of at most that size (``model-00001-of-00002.safetensors``
... with ``model.safetensors.index.json``), so every file fits the limits of file hosts and copies.

Each config keeps its stage's recipe and training record (the DiT's is kept in the ControlMap
config as ``dit_training``), so ``cmtool info`` shows how the shipped models were made; the paths in
them and in the manifest lose the folders of the machine that packed them (:func:`ckpt.portable`).
:func:`verify` checks the files against the manifest.
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import torch

from cmtool.core.errors import CmtoolError
from cmtool.core.jsonio import read_json, write_text_atomic
from cmtool.model import checkpoint as ckpt
from cmtool.model.rvae import ENCODER_PREFIXES, same_encoder

BUNDLED = Path(__file__).parents[1] / "weights"
MANIFEST = "MANIFEST.json"
MAX_FILE_BYTES = 16 * 2**20


def bundled_checkpoint() -> Path:
    """The shipped ControlMap checkpoint (its config points at the shipped RVAE decoder)."""
    path = BUNDLED / "controlmap"
    if not (path / ckpt.CONFIG).is_file():
        raise CmtoolError(f"no bundled weights in {BUNDLED} (a source checkout without them?); "
                          "pass --ckpt, or make them with `cmtool pack`")
    return path


def pack(controlmap, out: Path, rvae=None, encoder=None) -> dict:
    """Write the float16 release set of the ControlMap checkpoint ``controlmap`` into ``out``;
    returns the manifest. ``rvae``: an RVAE to ship instead of the ControlMap's own, which must
    share its encoder (a decoder fine-tune of it) so that it reads the same latent space. ``encoder``: an RVAE
    whose encoder ships too, one trained for the shipped decoder (``cmtool train encoder``: the same decoder
    weights and latent scale), so that the weights encode maps (``sample --init``) by themselves; an RVAE packed
    with an encoder (the shipped one) keeps it without."""
    src = ckpt.resolve(controlmap)
    config = ckpt.load_config(src)
    if config["kind"] != "controlmap":
        raise CmtoolError(f"{src}: a {config['kind']} checkpoint; pack takes a ControlMap")
    rvae_src = ckpt.rvae_of(src, config)
    if rvae is not None:
        rvae_src = _same_latent_space(rvae_src, ckpt.resolve(rvae))
    rvae_config = ckpt.load_config(rvae_src)
    dit_training = None
    if config.get("dit"):
        try:
            dit = ckpt.load_config(ckpt.linked(src, config["dit"]))
            if dit["kind"] == "controlmap":  # a branch trained on another ControlMap's frozen DiT
                dit = dit.get("dit_training") or {}
            dit_training = {k: v for k, v in dit.items() if k in ckpt.DIT_RECORD}
        except CmtoolError:
            pass  # the DiT run is gone; its weights are inside the ControlMap anyway

    out = Path(out)
    stage = out.with_name(f".{out.name}.pack-{os.getpid()}")  # written whole, then swapped in for the old set
    shutil.rmtree(stage, ignore_errors=True)
    try:
        manifest = _write_set(src, config, rvae_src, rvae_config, dit_training, encoder, stage)
    except CmtoolError as e:  # a full disk: named as the folder the user gave
        shutil.rmtree(stage, ignore_errors=True)
        raise CmtoolError(str(e).replace(str(stage), str(out))) from None
    except BaseException:
        shutil.rmtree(stage, ignore_errors=True)
        raise
    ckpt.replace_folder(stage, out)
    return manifest


def _write_set(src: Path, config: dict, rvae_src: Path, rvae_config: dict, dit_training, encoder, out: Path) -> dict:
    """Write the release set into the folder ``out``; returns its manifest."""
    half = {k: v.half() if v.is_floating_point() else v for k, v in ckpt.read_weights(src).items()}
    cm_config = {k: v for k, v in config.items() if k not in ("format", "version")}
    cm_config.update(rvae="../rvae", packed_from=config.get("packed_from", str(src)),
                     dit_training=config.get("dit_training", dit_training))
    cm_config = _portable_paths(cm_config)

    decoder = {k: v.half() for k, v in ckpt.read_weights(rvae_src).items()
               if not k.startswith(ENCODER_PREFIXES)}
    rvae_out = {k: v for k, v in rvae_config.items() if k not in ("format", "version")}
    rvae_out.update(weights="decoder", packed_from=rvae_config.get("packed_from", str(rvae_src)))
    if encoder is None and rvae_config.get("encoder_trained"):  # a packed set's RVAE keeps the encoder it ships
        encoder = rvae_src
    if encoder is not None:
        enc_src, enc_config, trunk = _encoder_for(ckpt.resolve(encoder), rvae_config, decoder)
        decoder |= trunk
        rvae_out.update(weights="full", encoder_trained=enc_config.get("encoder_trained") or {
            "path": enc_config.get("packed_from", str(enc_src)),
            **{k: enc_config[k] for k in ("own_latent_scale", "reconstruction", "step", "recipe_path", "training")
               if k in enc_config}})
    rvae_out = _portable_paths(rvae_out)
    ckpt.save_checkpoint(out / "rvae", rvae_out, decoder, max_file_bytes=MAX_FILE_BYTES)
    cm_config["rvae_weights"] = ckpt.weights_digest(out / "rvae")  # the float16 decoder it ships with
    ckpt.save_checkpoint(out / "controlmap", cm_config, half, max_file_bytes=MAX_FILE_BYTES)

    files = sorted(p for p in out.rglob("*") if p.is_file() and p.name != MANIFEST)
    manifest = {"files": {p.relative_to(out).as_posix(): {"sha256": ckpt.file_sha256(p), "bytes": p.stat().st_size}
                          for p in files},
                "controlmap": cm_config["packed_from"], "rvae": rvae_out["packed_from"],
                **({"encoder": rvae_out["encoder_trained"]["path"]} if encoder is not None else {})}
    manifest["total_bytes"] = sum(f["bytes"] for f in manifest["files"].values())
    write_text_atomic(out / MANIFEST, json.dumps(manifest, indent=1) + "\n")
    return manifest


def _portable_paths(value):
    """``value`` (a config or part of one) with every absolute path in it made portable."""
    if isinstance(value, dict):
        return {k: _portable_paths(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_portable_paths(v) for v in value]
    return ckpt.portable(value) if isinstance(value, str) and os.path.isabs(value) else value


def _encoder_for(src: Path, decoder_config: dict, decoder: dict) -> tuple[Path, dict, dict]:
    """The float16 encoder weights of the RVAE ``src`` (and its path and config), checked to encode into the latent
    space of ``decoder``: the same latent scale and decoder weights (as float16)."""
    config = ckpt.load_config(src)
    if config["kind"] != "rvae" or config.get("weights") == "decoder":
        raise CmtoolError(f"--encoder {src}: not an RVAE with an encoder (a `cmtool train encoder` run)")
    weights = ckpt.read_weights(src)
    same = all(k in weights and torch.equal(weights[k].half(), v) for k, v in decoder.items())
    if not same or config.get("latent_scale") != decoder_config.get("latent_scale"):
        raise CmtoolError(f"--encoder {src}: its decoder or latent scale is not the one that ships; train one for it "
                          "with `cmtool train encoder` (train.rvae = that decoder)")
    return src, config, {k: v.half() for k, v in weights.items() if k.startswith(ENCODER_PREFIXES)}


def _same_latent_space(trained_on: Path, other: Path) -> Path:
    """``other`` if its encoder and latent scale equal those of ``trained_on``, else an error. A packed
    decoder (``other`` holding no encoder, e.g. the shipped one) is judged by its latent scale alone."""
    a, b = ckpt.load_config(trained_on), ckpt.load_config(other)
    if b["kind"] != "rvae":
        raise CmtoolError(f"{other}: a {b['kind']} checkpoint; --rvae takes an RVAE")
    same = b.get("weights") == "decoder" or \
        same_encoder(*(ckpt.read_weights(p) for p in (trained_on, other)))
    if not same or a.get("latent_scale") != b.get("latent_scale"):
        raise CmtoolError(f"{other}: its encoder or latent scale differs from {trained_on}, the RVAE the ControlMap "
                          "was trained on; only a `cmtool train decoder` run on that RVAE reads the same latents")
    return other


def verify(root: Path = BUNDLED) -> list[str]:
    """Mismatches between the files under ``root`` and its manifest (empty when all match)."""
    manifest = read_json(Path(root) / MANIFEST)
    problems = []
    for name, want in manifest["files"].items():
        path = Path(root) / name
        if not path.is_file():
            problems.append(f"{name}: missing")
        elif ckpt.file_sha256(path) != want["sha256"]:
            problems.append(f"{name}: checksum differs from {MANIFEST}")
    return problems

