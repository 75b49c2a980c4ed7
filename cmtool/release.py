"""The model set that ships inside the package, so that ``cmtool sample`` works without training.

``cmtool pack --ckpt RUN`` turns a trained ControlMap (whose config names its RVAE and DiT) into
``cmtool/weights/``::

    controlmap/   config.json + model.safetensors   frozen DiT + control branch, float16
    rvae/         config.json + model.safetensors   the RVAE's decoder only (latent -> lanes), float16
    MANIFEST.json                                   SHA-256 and size of every file, where they came from

Each config keeps its stage's recipe and training record (the DiT's is kept in the ControlMap
config as ``dit_training``), so ``cmtool info`` shows how the shipped models were made.
:func:`verify` checks the files against the manifest.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

from cmtool import checkpoint as ckpt
from cmtool.data.jsonio import read_json, write_text_atomic
from cmtool.errors import CmtoolError

BUNDLED = Path(__file__).parent / "weights"
MANIFEST = "MANIFEST.json"
ENCODER_PREFIXES = ("trunk.", "to_latent.")  # RVAE parts only training and latent caching use


def bundled_checkpoint() -> Path:
    """The shipped ControlMap checkpoint (its config points at the shipped RVAE decoder)."""
    path = BUNDLED / "controlmap"
    if not (path / ckpt.CONFIG).is_file():
        raise CmtoolError(f"no bundled weights in {BUNDLED} (a source checkout without them?); "
                          "pass --ckpt, or make them with `cmtool pack`")
    return path


def pack(controlmap, out: Path) -> dict:
    """Write the float16 release set of the ControlMap checkpoint ``controlmap`` into ``out``;
    returns the manifest."""
    src = ckpt.resolve(controlmap)
    config = ckpt.load_config(src)
    if config["kind"] != "controlmap":
        raise CmtoolError(f"{src}: a {config['kind']} checkpoint; pack takes a ControlMap")
    rvae_src = ckpt.resolve(ckpt.linked(src, config["rvae"]))
    rvae_config = ckpt.load_config(rvae_src)
    dit_training = None
    if config.get("dit"):
        try:
            dit_training = {k: v for k, v in ckpt.load_config(ckpt.linked(src, config["dit"])).items()
                            if k in ("training", "recipe_path", "step", "steps")}
        except CmtoolError:
            pass  # the DiT run is gone; its weights are inside the ControlMap anyway

    out = Path(out)
    half = {k: v.half() if v.is_floating_point() else v for k, v in ckpt.load_tensors(src / ckpt.WEIGHTS).items()}
    cm_config = {k: v for k, v in config.items() if k not in ("format", "version")}
    cm_config.update(rvae="../rvae", packed_from=str(src), dit_training=dit_training)
    ckpt.save_checkpoint(out / "controlmap", cm_config, half)

    decoder = {k: v.half() for k, v in ckpt.load_tensors(rvae_src / ckpt.WEIGHTS).items()
               if not k.startswith(ENCODER_PREFIXES)}
    rvae_out = {k: v for k, v in rvae_config.items() if k not in ("format", "version")}
    rvae_out.update(weights="decoder", packed_from=str(rvae_src))
    ckpt.save_checkpoint(out / "rvae", rvae_out, decoder)

    files = sorted(p for p in out.rglob("*") if p.is_file() and p.name != MANIFEST)
    manifest = {"files": {p.relative_to(out).as_posix(): {"sha256": _sha256(p), "bytes": p.stat().st_size}
                          for p in files},
                "controlmap": str(src), "rvae": str(rvae_src)}
    manifest["total_bytes"] = sum(f["bytes"] for f in manifest["files"].values())
    write_text_atomic(out / MANIFEST, json.dumps(manifest, indent=1) + "\n")
    return manifest


def verify(root: Path = BUNDLED) -> list[str]:
    """Mismatches between the files under ``root`` and its manifest (empty when all match)."""
    manifest = read_json(Path(root) / MANIFEST)
    problems = []
    for name, want in manifest["files"].items():
        path = Path(root) / name
        if not path.is_file():
            problems.append(f"{name}: missing")
        elif _sha256(path) != want["sha256"]:
            problems.append(f"{name}: checksum differs from {MANIFEST}")
    return problems


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()

