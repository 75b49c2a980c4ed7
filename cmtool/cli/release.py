"""``cmtool info`` and ``cmtool pack``: what checkpoints hold, and the weights shipped with cmtool."""

from __future__ import annotations

import click

from cmtool.cli.common import InPath, OutPath


@click.command()
@click.argument("path", required=False, type=InPath())
@click.option("--json", "as_json", is_flag=True, help="Print the checkpoint's full config as JSON.")
def info(path, as_json):
    """What a checkpoint (or run folder) holds, or the model sizes a recipe defines.

    Without PATH: the models shipped with cmtool.
    """
    from cmtool.model import checkpoint as ckpt
    from cmtool.model.release import BUNDLED, bundled_checkpoint
    from cmtool.train.info import describe

    if path is None:
        click.echo(describe(bundled_checkpoint(), as_json=as_json))
        click.echo("")
        click.echo(describe(BUNDLED / "rvae", as_json=as_json))
        return
    if path.suffix != ".toml":  # the weights' headers, which describing a checkpoint never reads
        for f in ckpt.weight_files(ckpt.resolve(path)):
            ckpt.check_tensors(f)
    click.echo(describe(path, as_json=as_json))


@click.command()
@click.option("--ckpt", required=True, type=InPath(), help="ControlMap checkpoint or run folder.")
@click.option("--rvae", default=None, type=InPath(),
              help="RVAE to ship instead of the one the ControlMap was trained on: a `cmtool train decoder` run "
                   "on that RVAE (same encoder, so the same latent space), or an already packed decoder "
                   "with the same latent scale (e.g. cmtool/weights/rvae).")
@click.option("--encoder", default=None, type=InPath(),
              help="Ship this RVAE's encoder too: a `cmtool train encoder` run for the decoder that ships (same "
                   "decoder weights and latent scale), so that `sample --init` needs no --encoder. An RVAE "
                   "packed with an encoder (cmtool/weights/rvae) keeps it without.")
@click.option("--out", default=None, type=OutPath(file_okay=False),
              help="Folder to write [default: the package's own cmtool/weights].")
def pack(ckpt, rvae, encoder, out):
    """Pack a trained ControlMap (and its RVAE's decoder, with --encoder an encoder too) as float16 weights to ship
    with cmtool."""
    from cmtool.core.errors import CmtoolError
    from cmtool.model.release import BUNDLED, MANIFEST
    from cmtool.model.release import pack as pack_release

    if not ckpt.exists():
        raise CmtoolError(f"--ckpt {ckpt}: no such run or checkpoint; train a ControlMap first (`cmtool train "
                          f"controlnet --recipe RECIPE --out {ckpt}`, or the whole chain: `cmtool train pipeline`)")
    out = out or BUNDLED
    manifest = pack_release(ckpt, out, rvae=rvae, encoder=encoder)
    for name, f in manifest["files"].items():
        click.echo(f"{out / name}  {f['bytes'] / 1e6:.2f} MB  sha256 {f['sha256'][:16]}...")
    click.echo(f"total {manifest['total_bytes'] / 1e6:.2f} MB; checksums in {out / MANIFEST}")
