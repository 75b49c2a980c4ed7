"""The weights shipped with the package: checksums, size, sampling with them; `cmtool pack`."""

import json
import os
import re

import numpy as np
import pytest
import torch

from cmtool.core.errors import CmtoolError
from cmtool.core.jsonio import file_mode
from cmtool.data.sd_raster import read_sd_image
from cmtool.maps.lanegraph import read_jsonl
from cmtool.model import checkpoint as ckpt
from cmtool.model.release import BUNDLED, MANIFEST, bundled_checkpoint, verify
from cmtool.sample.generator import MapGenerator
from tests.conftest import REPO, in_process


def absolute_paths(folder) -> list[str]:
    """The absolute paths named in the JSON files under ``folder``."""

    def walk(value):
        if isinstance(value, dict):
            value = list(value.values())
        if isinstance(value, list):
            return [p for v in value for p in walk(v)]
        return [value] if isinstance(value, str) and os.path.isabs(value) else []

    return [p for f in sorted(folder.rglob("*.json")) for p in walk(json.loads(f.read_text()))]


def test_shipped_weights_match_their_checksums_and_size():
    assert verify(BUNDLED) == []
    manifest = (BUNDLED / MANIFEST).read_text()
    assert "controlmap/model.safetensors.index.json" in manifest and "rvae/model.safetensors" in manifest
    files = [p for p in BUNDLED.rglob("*") if p.is_file()]
    assert sum(p.stat().st_size for p in files) <= 40e6 and max(p.stat().st_size for p in files) <= 16 * 2**20
    assert absolute_paths(BUNDLED) == []  # no folder of the machine that packed them


def test_shipped_weights_sample_lane_graphs_for_each_city(tmp_path, capsys):
    for city in ("LAV", "PIT", "SGP"):
        out = tmp_path / city
        code, stdout, err = in_process(capsys, "sample", "--sd", REPO / "sample_data" / f"sd_{city.lower()}.png",
                                       "--city", city, "--steps", "10", "--no-log", "--quiet", "--out", out)
        assert code == 0, err
        (graph,) = read_jsonl(out / f"sd_{city.lower()}.json")
        # the package's weights, named so wherever it is installed
        assert graph.city == city and graph.meta["checkpoint"] == "cmtool/weights/controlmap"
        assert len(graph.lanes) > 0
        assert all(np.isfinite(lane).all() and np.abs(lane).max() <= 40.0 for lane in graph.lanes)
        assert all(0 <= i < len(graph.lanes) and 0 <= j < len(graph.lanes) for i, j in graph.successors)
        assert 0.0 <= graph.meta["validity"] <= 1.0


def test_info_without_a_path_describes_the_shipped_models(capsys):
    code, out, err = in_process(capsys, "info")
    assert code == 0, err
    assert "controlmap (complete" in out and "DiT trained" in out
    assert "trained for this decoder by `cmtool train encoder`" in out  # the shipped RVAE encodes too
    assert out.count("trained ") >= 2 and "recipes/tiny-cpu/pipeline/controlnet.toml" in out
    assert "decoder=graph" in out  # the RVAE's decoder predicts successor links
    assert "cmtool/weights/controlmap\n" in out and not re.search(r"[\s(]/\w", out)  # no machine paths


def test_pack_writes_float16_weights_that_sample_like_the_original(sampling_ckpt, tmp_path, capsys):
    code, out, err = in_process(capsys, "pack", "--ckpt", sampling_ckpt["controlmap"], "--out", tmp_path / "w")
    assert code == 0, err
    assert verify(tmp_path / "w") == []
    assert os.path.isabs(ckpt.load_config(sampling_ckpt["controlmap"])["dit"]) and absolute_paths(tmp_path / "w") == []
    # the packed ControlMap records the float16 decoder it ships with, which it samples with
    packed = ckpt.load_config(tmp_path / "w" / "controlmap")
    assert packed["rvae_weights"] == ckpt.weights_digest(tmp_path / "w" / "rvae")
    assert json.loads((tmp_path / "w" / MANIFEST).read_text())["controlmap"] == "controlmap"  # the folder packed
    weights = ckpt.read_weights(tmp_path / "w" / "rvae")
    assert weights and not any(k.startswith(("trunk.", "to_latent.")) for k in weights)
    assert all(v.dtype == torch.float16 for v in weights.values())

    original, packed = MapGenerator.load(sampling_ckpt["controlmap"]), MapGenerator.load(tmp_path / "w" / "controlmap")
    noise = torch.randn(1, *original.model.latent_shape, generator=torch.Generator().manual_seed(0))
    sd = read_sd_image(REPO / "sample_data" / "sd_lav.png")[0][None]
    a = original.sample(sd, [original.label("LAV")], cfg=1.0, steps=5, sampler="ddim", noise=noise)
    b = packed.sample(sd, [packed.label("LAV")], cfg=1.0, steps=5, sampler="ddim", noise=noise)
    assert torch.allclose(a, b, atol=0.05 * float(a.abs().max()))
    with pytest.raises(CmtoolError, match="decoder only"):
        packed.rvae.encode(torch.zeros(1, packed.rvae.config.in_channels, 128, 128))

    (tmp_path / "w" / "rvae" / ckpt.WEIGHTS).write_bytes(b"tampered")
    assert verify(tmp_path / "w") == ["rvae/model.safetensors: checksum differs from MANIFEST.json"]


def test_packing_the_shipped_weights_again_keeps_their_encoder(tmp_path, capsys):
    """A branch trained on the shipped RVAE (train.rvae = cmtool/weights/rvae) packs with the encoder that ships,
    and its record, without --encoder: here the shipped ControlMap itself, whose RVAE is the shipped one."""
    code, _, err = in_process(capsys, "pack", "--ckpt", BUNDLED / "controlmap", "--out", tmp_path / "w")
    assert code == 0, err
    shipped, packed = ckpt.load_config(BUNDLED / "rvae"), ckpt.load_config(tmp_path / "w" / "rvae")
    assert packed["weights"] == "full" and packed["encoder_trained"] == shipped["encoder_trained"]
    assert json.loads((tmp_path / "w" / MANIFEST).read_text())["encoder"] == shipped["encoder_trained"]["path"]
    a, b = ckpt.read_weights(BUNDLED / "rvae"), ckpt.read_weights(tmp_path / "w" / "rvae")
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


def test_pack_refuses_other_checkpoints(sampling_ckpt, tmp_path, capsys):
    code, _, err = in_process(capsys, "pack", "--ckpt", sampling_ckpt["dit"], "--out", tmp_path / "w")
    assert code == 1 and "pack takes a ControlMap" in err


def test_pack_splits_weights_into_files_under_the_limit(sampling_ckpt, tmp_path, capsys, monkeypatch):
    import cmtool.model.release

    code, _, err = in_process(capsys, "pack", "--ckpt", sampling_ckpt["controlmap"], "--out", tmp_path / "whole")
    assert code == 0, err
    monkeypatch.setattr(cmtool.model.release, "MAX_FILE_BYTES", 64 * 1024)
    code, _, err = in_process(capsys, "pack", "--ckpt", sampling_ckpt["controlmap"], "--out", tmp_path / "split")
    assert code == 0, err
    assert verify(tmp_path / "split") == []
    cm = tmp_path / "split" / "controlmap"
    shards = sorted(cm.glob("model-*-of-*.safetensors"))
    assert len(shards) >= 2 and all(p.stat().st_size <= 64 * 1024 for p in shards)
    # the usual permissions of new files (safetensors itself makes them 0600: unreadable to others once installed)
    assert {p.stat().st_mode & 0o777 for p in cm.iterdir()} == {file_mode()}
    assert not (cm / ckpt.WEIGHTS).exists() and (cm / ckpt.INDEX).is_file()
    whole = ckpt.read_weights(tmp_path / "whole" / "controlmap")
    split = ckpt.read_weights(cm)
    assert whole.keys() == split.keys() and all(torch.equal(whole[k], split[k]) for k in whole)
    assert ckpt.weights_digest(cm) != ckpt.weights_digest(tmp_path / "whole" / "controlmap")
    code, _, err = in_process(capsys, "sample", "--ckpt", cm, "--sd", REPO / "sample_data" / "sd_lav.png", "--steps", 2,
                              "--no-log", "--quiet", "--out", tmp_path / "s")
    assert code == 0, err
    # a missing file is named, not a stack trace
    shards[-1].unlink()
    assert any("missing" in p for p in verify(tmp_path / "split"))
    with pytest.raises(CmtoolError, match="not a checkpoint"):
        ckpt.resolve(cm)


def test_a_weight_larger_than_the_file_limit_is_refused(tmp_path):
    with pytest.raises(CmtoolError, match="exceeds the file limit"):
        ckpt.save_checkpoint(tmp_path / "c", {"kind": "dit"}, {"w": torch.zeros(64, 64)}, max_file_bytes=8192)
