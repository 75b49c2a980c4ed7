"""The ``cmtool`` command line.

Commands are thin: they parse options, call the library and print. Library modules are imported
inside each command so ``cmtool --help`` stays fast. Every user error (a :class:`CmtoolError` or a
bad option) ends with one ``Error: ...`` line on stderr and a non-zero exit, never a traceback.

The commands live in one module per command group (data, train, sample, baseline, evaluate: metrics and eval,
maps: validate, export and convert, ablate, bench, release: info and pack); this module holds the root group and
:func:`main`, the entry point.
"""

from __future__ import annotations

import errno
import sys

import click

from cmtool import __version__
from cmtool.cli import ablate, baseline, bench, data, evaluate, maps, release, sample, train
from cmtool.core.errors import CmtoolError

__all__ = ["cli", "main"]


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="cmtool")
def cli():
    """cmtool: controllable lane-level HD map generation from SD maps (ControlMap)."""


for _command in (data.data, train.train_cmd, sample.sample, baseline.baseline, evaluate.metrics, evaluate.eval_cmd,
                 maps.validate, maps.export, maps.convert, ablate.ablate, bench.bench, release.info, release.pack):
    cli.add_command(_command)


def main(argv=None) -> None:
    """Entry point: run the CLI, reducing user errors to one line and a non-zero exit."""
    try:
        cli.main(args=argv, prog_name="cmtool", standalone_mode=False)
    except CmtoolError as e:
        click.echo(f"Error: {e}", err=True)
        sys.exit(1)
    except click.exceptions.Abort:
        click.echo("Aborted.", err=True)
        sys.exit(130)
    except click.UsageError as e:
        hint = f" (see '{e.ctx.command_path} --help')" if e.ctx is not None else ""
        click.echo(f"Error: {e.format_message()}{hint}", err=True)
        sys.exit(2)
    except click.ClickException as e:
        click.echo(f"Error: {e.format_message()}", err=True)
        sys.exit(e.exit_code)
    except OSError as e:  # a path the user gave that cannot be made, read or written (the command did not say which)
        if e.filename is None and e.errno not in (errno.ENOSPC, errno.EFBIG, errno.EDQUOT):
            raise
        from cmtool.core.jsonio import os_reason

        where = f"{e.filename}: " if e.filename is not None else "cannot write: "
        click.echo(f"Error: {where}{os_reason(e)}", err=True)
        sys.exit(1)
