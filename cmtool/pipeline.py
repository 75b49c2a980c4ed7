"""``cmtool train pipeline``: the whole chain from one recipe, each stage resumed or skipped.

A pipeline recipe names a recipe per stage, paths relative to it (``recipes/tiny-cpu/pipeline.toml``)::

    [pipeline]
    data = "../data_cpu.toml"        # cmtool data build
    rvae = "pipeline/rvae.toml"      # stage 1
    decoder = ""                     # optional: the RVAE's decoder trained further on its latents
    dit = "pipeline/dit.toml"        # stage 2
    controlnet = "pipeline/controlnet.toml"   # stage 3
    precision = "bf16"               # of every training stage ("": each recipe's own)
    [pipeline.eval]                  # cmtool eval of the packed weights
    n = 512

The stages run in order, each into ``OUT/<stage>`` and reading the earlier stages' folders (the
stage recipes' own ``data``/``rvae``/``dit``/``out`` paths are replaced); then the ControlMap (with
the fine-tuned decoder when there is one) is packed into ``OUT/weights`` and evaluated into
``OUT/eval``. ``OUT/pipeline.json`` records each stage's fingerprint (a hash of its recipe and of
the fingerprints of the stages it reads): a finished stage with the same fingerprint is skipped, an
unfinished one resumes from its last checkpoint, and one whose recipe or inputs changed is refused
with what to do, never silently reused.

Under ``torchrun`` every process trains; the data, pack and eval stages run on the first process while
the others wait for ``pipeline.json`` to record them.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import sys
import time
from pathlib import Path

import torch

from cmtool.core.errors import CmtoolError
from cmtool.core.jsonio import read_json, write_json
from cmtool.core.launch import launch
from cmtool.core.tables import read_toml
from cmtool.model import checkpoint as ckpt
from cmtool.train.recipe import Recipe, load_recipe

FORMAT = "cmtool.pipeline"
TRAINED = ("rvae", "decoder", "dit", "controlnet")
STAGES = ("data", *TRAINED, "pack", "eval")
READS = {"data": (), "rvae": ("data",), "decoder": ("data", "rvae"), "dit": ("rvae",),
         "controlnet": ("data", "rvae", "dit"), "pack": ("controlnet", "decoder"), "eval": ("pack", "data")}
# train settings that do not change what a stage makes (paths are the pipeline's; a run may move to a GPU)
UNHASHED = ("data", "rvae", "dit", "out", "precision", "workers", "ckpt_every", "keep", "log_every", "preview_every",
            "preview_steps")
WAIT_S = 5.0  # how often the other torchrun processes look whether the first finished its stage


def stage_recipes(recipe: Recipe) -> dict[str, Path]:
    """The stage recipe files a pipeline recipe names (the decoder only when given), checked to exist."""
    base = recipe.path.parent if recipe.path else Path.cwd()
    files = {}
    for name in ("data", *TRAINED):
        value = getattr(recipe.pipeline, name)
        if not value:
            if name == "decoder":
                continue
            raise CmtoolError(f"{recipe.path}: pipeline.{name}: missing (the recipe of the {name} stage)")
        path = base / value
        if not path.is_file():
            raise CmtoolError(f"{recipe.path}: pipeline.{name}: no such recipe file {path}")
        if "pipeline" in read_toml(path, "recipe"):  # itself, or another pipeline: stages would never end
            raise CmtoolError(f"{recipe.path}: pipeline.{name}: {path} is a pipeline recipe, not the recipe of the "
                              f"{name} stage")
        files[name] = path
    return files


class Pipeline:
    """Runs the stages of a pipeline recipe into ``out`` (see the module docstring)."""

    def __init__(self, recipe: Recipe, out: Path, device: torch.device, progress: bool = True,
                 data_dir: Path | None = None, serve: int | None = None, log: bool = True):
        self.recipe, self.out, self.device, self.progress, self.serve = recipe, Path(out), device, progress, serve
        self.log = log  # False: no training recordings, no eval.rrd
        self.files = stage_recipes(recipe)
        self.data_dir = data_dir  # a dataset built before: the data stage takes it instead of building
        self.rank = launch()[0]
        self.stages = [s for s in STAGES if s != "decoder" or "decoder" in self.files]
        self.state_path = self.out / "pipeline.json"
        self.fingerprints: dict[str, str] = {}
        self.report: list[dict] = []

    # -- bookkeeping -------------------------------------------------------------------------------
    def _state(self) -> dict:
        if not self.state_path.is_file():
            return {"format": FORMAT, "stages": {}}
        state = read_json(self.state_path)
        if not isinstance(state, dict) or state.get("format") != FORMAT:
            raise CmtoolError(f"{self.state_path}: not a cmtool pipeline record")
        return state

    def _record(self, name: str, **entry) -> None:
        state = self._state()
        state["stages"][name] = {**state["stages"].get(name, {}), **entry}
        write_json(self.state_path, state)

    def folder(self, name: str) -> Path:
        return self.out / ("weights" if name == "pack" else name)

    def _fingerprint(self, name: str, content) -> str:
        reads = {s: self.fingerprints[s] for s in READS[name] if s in self.fingerprints}
        blob = json.dumps({"stage": name, "content": content, "reads": reads}, sort_keys=True, default=str)
        return hashlib.sha256(blob.encode()).hexdigest()[:16]

    def stage_recipe(self, name: str) -> Recipe:
        """A training stage's recipe with its paths pointed at this pipeline's folders."""
        rec = load_recipe(self.files[name])
        if rec.train.stage and rec.train.stage != name:
            raise CmtoolError(f"{self.files[name]}: a recipe for the {rec.train.stage} stage, named as pipeline.{name}")
        rec.train.stage = name
        rec.train.data = str(self.data_dir or self.folder("data"))
        rec.train.rvae = str(self.folder("rvae"))
        rec.train.dit = str(self.folder("dit"))
        rec.train.out = str(self.folder(name))
        if self.recipe.pipeline.precision:
            rec.train.precision = self.recipe.pipeline.precision
        return rec

    def _content(self, name: str):
        """What a stage's fingerprint hashes besides the stages it reads."""
        if name == "data":
            if self.data_dir is not None:
                return {"dataset": read_json(self.data_dir / "manifest.json").get("recipe")}
            return load_recipe(self.files["data"]).to_dict()["data"]
        if name in TRAINED:
            values = self.stage_recipe(name).to_dict()
            values["train"] = {k: v for k, v in values["train"].items() if k not in UNHASHED}
            return values
        if name == "eval":
            return dataclasses.asdict(self.recipe.pipeline.eval)
        return {}

    # -- running -----------------------------------------------------------------------------------
    def run(self) -> list[dict]:
        """Run (or resume, or skip) every stage; returns the per-stage report."""
        if self.rank == 0:
            self.out.mkdir(parents=True, exist_ok=True)
        for k, name in enumerate(self.stages, start=1):
            self.fingerprints[name] = self._fingerprint(name, self._content(name))
            self._check(name)
            entry = self._state()["stages"].get(name, {})
            if entry.get("done"):
                self._say(f"pipeline: stage {k}/{len(self.stages)} {name}: done before, skipped")
                self.report.append({"stage": name, "status": "skipped (done)", **entry})
                continue
            self._say(f"pipeline: stage {k}/{len(self.stages)} {name}" + (f" ({self.files[name]})" if name in
                                                                           self.files else ""))
            start = time.perf_counter()
            if name in TRAINED:
                if self.rank == 0:
                    self._record(name, fingerprint=self.fingerprints[name], done=False)
                result = self._train(name)
            elif self.rank == 0:
                self._record(name, fingerprint=self.fingerprints[name], done=False)
                result = getattr(self, f"_{name}")()
            else:
                self._wait(name)
                continue
            entry = {"fingerprint": self.fingerprints[name], "done": True,
                     "seconds": round(time.perf_counter() - start, 1), "result": result}
            if self.rank == 0:
                self._record(name, **entry)
            self.report.append({"stage": name, "status": "ran", **entry})
        return self.report

    def _check(self, name: str) -> None:
        """Refuse a stage folder made from other inputs, or not by this pipeline."""
        entry = self._state()["stages"].get(name)
        given = name == "data" and self.data_dir is not None  # --data: a dataset built before, not ours
        folder = self.data_dir if given else self.folder(name)
        if entry is not None and not folder.exists():  # removed to be made again
            if self.rank == 0:
                state = self._state()
                del state["stages"][name]
                write_json(self.state_path, state)
            entry = None
        if entry is None:
            if not given and folder.exists() and any(folder.iterdir()):
                raise CmtoolError(f"{folder}: exists but was not made by this pipeline; remove it or choose "
                                  "another --out")
            return
        if entry.get("fingerprint") != self.fingerprints[name]:
            later = self.stages[self.stages.index(name):]
            raise CmtoolError(f"{folder}: made from another recipe or other inputs than this pipeline now gives "
                              f"the {name} stage; run the pipeline with its earlier recipes, or remove "
                              f"{', '.join(str(self.folder(s)) for s in later if self.folder(s).exists() and (s != 'data' or not given))} "
                              "to make them again")

    def _say(self, line: str) -> None:
        if self.rank == 0:
            print(line, file=sys.stderr, flush=True)

    def _wait(self, name: str) -> None:
        """Other torchrun processes: wait until the first one records ``name`` done."""
        while not self._state()["stages"].get(name, {}).get("done"):
            time.sleep(WAIT_S)

    def _data(self) -> dict:
        from cmtool.data.cache import build_dataset

        if self.data_dir is not None:
            manifest = read_json(self.data_dir / "manifest.json")
            if not manifest.get("complete"):
                raise CmtoolError(f"{self.data_dir}: an unfinished dataset; finish it with `cmtool data build`")
            return {"dataset": str(self.data_dir), "scenes": {s: v["scenes"] for s, v in manifest["splits"].items()}}
        summary = build_dataset(load_recipe(self.files["data"]), self.folder("data"), progress=self.progress)
        return {"scenes": {s: v["scenes"] for s, v in summary["splits"].items()}}

    def _train(self, name: str) -> dict:
        from cmtool.train.loop import train
        from cmtool.train.stages import STAGES as TRAIN_STAGES

        rec = self.stage_recipe(name)
        run_dir = self.folder(name)
        final = train(TRAIN_STAGES[name](rec, self.device), run_dir, resume=bool(ckpt.run_checkpoints(run_dir)),
                      progress=self.progress, serve=self.serve, log=self.log)
        config = ckpt.load_config(final)
        result = {"checkpoint": str(final), "steps": config["step"],
                  "train_seconds": round(config["training"]["time_s"], 1)}
        if "reconstruction" in config:
            result["reconstruction_f1"] = round(config["reconstruction"]["f1"], 4)
        return result

    def _pack(self) -> dict:
        from cmtool.model.release import pack

        decoder = self.folder("decoder") if "decoder" in self.files else None
        manifest = pack(self.folder("controlnet"), self.folder("pack"), rvae=decoder)
        return {"weights": str(self.folder("pack")), "megabytes": round(manifest["total_bytes"] / 1e6, 2)}

    def _eval(self) -> dict:
        from cmtool.eval.evaluation import EvalSettings, run_eval
        from cmtool.metrics.features import FeatureExtractor
        from cmtool.sample.generator import MapGenerator

        e = self.recipe.pipeline.eval
        gen = MapGenerator.load(self.folder("pack") / "controlmap", self.device)
        gen.schedule.timesteps(e.steps)
        data = self.data_dir or self.folder("data")
        settings = EvalSettings(data=str(Path(data).resolve()), split=e.split, n=e.n, cfg=e.cfg, steps=e.steps,
                                sampler=e.sampler, seed=e.seed, batch=e.batch)
        extractor = FeatureExtractor("resnet50-seeded", None, self.device) if e.features else None
        report = run_eval(gen, settings, self.folder("eval"), extractor, rrd_samples=e.rrd_samples,
                          progress=self.progress, record=self.log)
        cm = report["methods"]["controlmap"]
        keys = ("validity", "dangling", "crossings", "lane_f1", "sd_coverage", "legal_oneway")
        out = {k: round(cm["geometry"][k]["mean"], 4) for k in keys
               if math.isfinite(cm["geometry"].get(k, {}).get("mean", math.nan))}
        if "gt_recall" in cm:
            out["gt_recall"] = round(cm["gt_recall"]["recall"], 4)
        return out


def summary(report: list[dict]) -> str:
    """The per-stage table printed at the end of a pipeline run."""
    lines = [f"{'stage':<11} {'status':<15} {'time':>8}  result"]
    for row in report:
        result = ", ".join(f"{k} {v}" for k, v in row.get("result", {}).items() if k != "checkpoint")
        lines.append(f"{row['stage']:<11} {row['status']:<15} {row.get('seconds', 0.0):>7.0f}s  {result}")
    return "\n".join(lines)
