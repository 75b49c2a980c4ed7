"""``cmtool ablate``: the guidance weight, the city label, DiTs side by side, what the RVAE keeps."""

from __future__ import annotations

from pathlib import Path

import click

from cmtool.cli.common import (CITY_CFG_HELP, PRECISION_OPTION, SEED, SMOOTH_OPTION, DatasetDir, Finite, InPath,
                               OutPath, _device, _generator, sampler_options)
from cmtool.core.errors import CmtoolError


@click.group()
def ablate():
    """Ablations on fixed SD maps and seeds: the guidance weight, the city label; what the RVAE keeps."""


def _ablation_setup(ckpt, data_dir, split, n, device, smooth, precision, dit_ok=False):
    from cmtool.data.cache import load_dataset

    gen = _generator(ckpt, device, smooth, precision)
    if not gen.has_control and not dit_ok:
        raise CmtoolError(f"{gen.path}: the guidance sweep needs a ControlMap checkpoint")
    data = load_dataset(data_dir, split)
    return gen, [data.scene(i) for i in range(min(n, len(data)))]


def _floats(value: str, option: str) -> list[float]:
    import math

    try:
        out = [float(v) for v in value.split(",") if v.strip()]
    except ValueError:
        raise CmtoolError(f"{option} {value!r}: expected numbers separated by commas") from None
    if not out or any(not math.isfinite(v) or v < 0 for v in out):
        raise CmtoolError(f"{option} {value!r}: expected finite numbers >= 0")
    return out


_ABLATE_COMMON = [
    click.option("--ckpt", type=InPath(),
                 help="ControlMap checkpoint or run folder [default: the weights shipped with cmtool]."),
    click.option("--data", "data_dir", required=True, type=DatasetDir(),
                 help="Dataset cache whose scenes give the SD maps."),
    click.option("--split", default="test", show_default=True),
    click.option("--n", default=64, show_default=True, type=click.IntRange(min=1), help="Scenes (the first N)."),
    sampler_options,
    SMOOTH_OPTION,
    click.option("--out", required=True, type=OutPath(file_okay=False), help="Output folder."),
    click.option("--device", help="torch device [default: cuda when available, else cpu]."),
    PRECISION_OPTION,
    click.option("--quiet", is_flag=True, help="No progress line."),
]


def _ablate_options(fn):
    for option in reversed(_ABLATE_COMMON):
        fn = option(fn)
    return fn


@ablate.command("cfg")
@_ablate_options
@click.option("--w", "weights", default="0,0.3,0.5,0.7,1.0", show_default=True, help="Guidance weights to sweep.")
@click.option("--seeds", default=2, show_default=True, type=click.IntRange(1, 100), help="Maps per scene (diversity).")
@click.option("--backbone", default="resnet50-seeded", show_default=True,
              type=click.Choice(["resnet50-seeded", "resnet50-imagenet"]), help="Feature network of GT Recall.")
@click.option("--weights-file", type=InPath(dir_okay=False), help="ImageNet ResNet-50 weights.")
@click.option("--no-features", is_flag=True, help="Skip GT Recall.")
def ablate_cfg(ckpt, data_dir, split, n, steps, sampler, smooth, out, device, precision, quiet, weights, seeds, backbone,
               weights_file, no_features):
    """Sweep the guidance weight w: SD adherence, GT Recall and diversity against w."""
    from cmtool.eval.ablations import cfg_sweep, layouts_of
    from cmtool.metrics.features import FeatureExtractor

    ws = _floats(weights, "--w")
    gen, scenes = _ablation_setup(ckpt, data_dir, split, n, device, smooth, precision)
    extractor = None if no_features else FeatureExtractor(backbone, weights_file, gen.device)
    cfg_sweep(gen, scenes, ws, seeds, steps, extractor, out, progress=not quiet, sampler=sampler,
              layouts=layouts_of(gen, data_dir, split, scenes))
    click.echo((out / "ablate_cfg.md").read_text().rstrip())
    click.echo(f"wrote {out / 'ablate_cfg.md'}, {out / 'ablate_cfg.png'}, {out / 'ablate_cfg.rrd'}")


@ablate.command("city-swap")
@_ablate_options
@click.option("--labels", default="SGP,LAV", show_default=True, help="City labels to compare (or none).")
@click.option("--cfg", default=1.0, show_default=True, type=Finite(min=0), help="Guidance weight.")
@click.option("--city-cfg", default=1.0, show_default=True, type=Finite(min=0), help=CITY_CFG_HELP)
@click.option("--seed", default=0, show_default=True, type=SEED, help="Random seed (the same noise for every label).")
def ablate_city_swap(ckpt, data_dir, split, n, steps, sampler, smooth, out, device, precision, quiet, labels, cfg,
                     city_cfg, seed):
    """Swap the city label on the same SD maps: the driving side per label (SGP drives on the left).

    --ckpt may also name a DiT: its maps ignore the SD maps, whose two-way roads still judge them
    where they happen to meet (the oncoming-lane columns judge every map)."""
    from cmtool.eval.ablations import city_swap, layouts_of
    from cmtool.maps.hdmap import drives_on
    from cmtool.model.controlmap import NO_LAYOUT

    names = [v.strip() for v in labels.split(",") if v.strip()]
    gen, scenes = _ablation_setup(ckpt, data_dir, split, n, device, smooth, precision, dit_ok=True)
    for name in names:
        gen.label(name)  # unknown labels fail before any work
    layouts = None
    if gen.layout != NO_LAYOUT:  # each label's maps read the layout of its own driving side
        layouts = {name: layouts_of(gen, data_dir, split, scenes, None if name.lower() == "none" else drives_on(name))
                   for name in names}
    city_swap(gen, scenes, names, steps, cfg, seed, out, progress=not quiet, sampler=sampler, city_cfg=city_cfg,
              layouts=layouts)
    click.echo((out / "ablate_city_swap.md").read_text().rstrip())
    click.echo(f"wrote {out / 'ablate_city_swap.md'}, {out / 'ablate_city_swap.png'}")


@ablate.command("dit")
@click.option("--ckpt", "ckpts", multiple=True, required=True, type=InPath(),
              help="DiT (or ControlMap, sampled without control) checkpoint or run folder (repeatable).")
@click.option("--data", "data_dir", required=True, type=DatasetDir(),
              help="Dataset cache whose scenes give the city labels and the reference maps.")
@click.option("--split", default="test", show_default=True)
@click.option("--n", default=128, show_default=True, type=click.IntRange(min=2), help="Scenes (the first N).")
@sampler_options
@click.option("--seed", default=0, show_default=True, type=SEED,
              help="Random seed (the same noise for every checkpoint).")
@SMOOTH_OPTION
@click.option("--out", required=True, type=OutPath(file_okay=False), help="Output folder.")
@click.option("--device", help="torch device [default: cuda when available, else cpu].")
@PRECISION_OPTION
@click.option("--quiet", is_flag=True, help="No progress line.")
def ablate_dit(ckpts, data_dir, split, n, steps, sampler, seed, smooth, out, device, precision, quiet):
    """Compare DiTs on the same city labels and noise: topology Fréchet distances to the scenes' ground
    truth, validity, lanes joined to nothing and crossings per map, driving side by oncoming lanes."""
    from cmtool.data.cache import load_dataset
    from cmtool.eval.ablations import dit_compare

    gens = {}
    for path in ckpts:
        gen = _generator(path, device, smooth, precision)
        name = gen.path.parent.parent.name if gen.path.parent.name == "checkpoints" else gen.path.name
        gens[name if name not in gens else str(path)] = gen
    data = load_dataset(data_dir, split)
    dit_compare(gens, [data.scene(i) for i in range(min(n, len(data)))], steps, seed, out, progress=not quiet,
                sampler=sampler)
    click.echo((out / "ablate_dit.md").read_text().rstrip())
    click.echo(f"wrote {out / 'ablate_dit.md'}, {out / 'ablate_dit.png'}")


@ablate.command("rvae")
@click.option("--rvae", "rvae_path", type=InPath(),
              help="RVAE checkpoint or run folder [default: the decoder shipped with cmtool].")
@click.option("--encoder", "encoder_path", type=InPath(),
              help="RVAE run whose encoder makes the latents [default: the RVAE's own]; needed for a decoder "
                   "without one, such as the shipped decoder (its encoder does not ship; `cmtool train encoder` "
                   "trains one for it).")
@click.option("--data", "data_dir", required=True, type=DatasetDir(),
              help="Dataset cache.")
@click.option("--split", "splits", multiple=True, help="Split to measure (repeatable) [default: every split].")
@click.option("--n", default=64, show_default=True, type=click.IntRange(min=1), help="Scenes per split and city.")
@click.option("--tol", default=1.0, show_default=True, type=Finite(min=0, min_open=True),
              help="Lane F1 tolerance (m).")
@click.option("--out", required=True, type=OutPath(file_okay=False), help="Output folder.")
@click.option("--device", help="torch device [default: cuda when available, else cpu].")
@click.option("--quiet", is_flag=True, help="No progress line.")
def ablate_rvae(rvae_path, encoder_path, data_dir, splits, n, tol, out, device, quiet):
    """What the RVAE keeps: lane F1 (at --tol m and at 0.5 m), successor precision, recall and F1 (lanes
    matched within --tol m) and validity of its reconstructions, and the driving side of the ground
    truth and of the reconstructions, per split and city (the ceiling of the city swap)."""
    from cmtool.model import checkpoint as ckpt
    from cmtool.model.release import BUNDLED
    from cmtool.train.reconstruction import reconstruction_report

    dev = _device(device)
    decoder, path = _rvae(rvae_path or BUNDLED / "rvae", "--rvae", dev)
    encoder = decoder
    if encoder_path is not None:
        encoder, enc_path = _rvae(encoder_path, "--encoder", dev)
        if encoder.trunk is None:
            raise CmtoolError(f"--encoder {enc_path}: holds no encoder (a packed decoder); give a `cmtool train "
                              "rvae` or `cmtool train encoder` run")
        if (encoder.config.latent_channels, encoder.config.latent_size) != (decoder.config.latent_channels,
                                                                       decoder.config.latent_size):
            raise CmtoolError(f"--encoder {enc_path}: its latents do not fit the decoder {path}")
        scales = [float(ckpt.load_config(p).get("latent_scale", "nan")) for p in (enc_path, path)]
        if abs(scales[0] - scales[1]) > 1e-6:
            click.echo(f"warning: the decoder was trained on other latents (latent scale {scales[1]:.4f}, the "
                       f"encoder's {scales[0]:.4f}); the numbers measure this pair", err=True)
    elif decoder.trunk is None:
        raise CmtoolError(f"{path}: a decoder without its encoder (the shipped weights hold none); give --encoder "
                          "RUN, the RVAE run it was trained on")
    reconstruction_report(encoder, decoder, data_dir, dev, n, out, progress=not quiet, tol=tol,
                          splits=list(splits) or None)
    click.echo((out / "ablate_rvae.md").read_text().rstrip())
    click.echo(f"wrote {out / 'ablate_rvae.md'}, {out / 'ablate_rvae.json'}")


def _rvae(path: Path, option: str, device):
    from cmtool.model import checkpoint as ckpt

    path = ckpt.resolve(path)
    model, config = ckpt.load_model(path, device)
    if config["kind"] != "rvae":
        raise CmtoolError(f"{option} {path}: a {config['kind']} checkpoint, not an RVAE")
    return model, path
