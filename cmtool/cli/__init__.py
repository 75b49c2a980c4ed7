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
import os
import signal
import sys
import threading

import click

from cmtool import __version__
from cmtool.cli import ablate, baseline, bench, data, evaluate, maps, release, sample, train
from cmtool.core.errors import CmtoolError, Terminated
from cmtool.core.launch import launch

__all__ = ["cli", "main"]


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="cmtool")
def cli():
    """cmtool: controllable lane-level HD map generation from SD maps (ControlMap)."""
    launch()  # a torchrun environment that does not fit together is refused before any command reads it


for _command in (data.data, train.train_cmd, sample.sample, baseline.baseline, evaluate.metrics, evaluate.eval_cmd,
                 maps.validate, maps.export, maps.convert, ablate.ablate, bench.bench, release.info, release.pack):
    cli.add_command(_command)


def main(argv=None) -> None:
    """Entry point: run the CLI, reducing user errors to one line and a non-zero exit. SIGTERM stops a command as
    Ctrl-C does (exit 143, Ctrl-C 130): files being written are removed, worker processes stopped."""
    from cmtool.core import outputs

    on_main_thread = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGTERM, _terminate) if on_main_thread else None
    watchdog = _Watchdog() if on_main_thread else None
    try:
        cli.main(args=argv, prog_name="cmtool", standalone_mode=False)
    except CmtoolError as e:
        click.echo(f"Error: {e}", err=True)
        sys.exit(1)
    except click.exceptions.Abort:
        _stopped()
        click.echo("Aborted.", err=True)
        sys.exit(130)
    except Terminated:
        click.echo("Terminated.", err=True)
        sys.exit(143)
    except (MemoryError, RuntimeError) as e:  # a size no check foresaw: numpy and torch say what did not fit
        if isinstance(e, RuntimeError) and "can't allocate memory" not in str(e):  # torch's CPU allocator
            raise
        why = str(e).strip().splitlines()[-1] if str(e).strip() else ""
        click.echo(f"Error: out of memory{f' ({why})' if why else ''}: an option, recipe or input asks for more "
                   f"than this machine has", err=True)
        sys.exit(1)
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
        from cmtool.core.outputs import os_reason

        where = f"{e.filename}: " if e.filename is not None else "cannot write: "
        click.echo(f"Error: {where}{os_reason(e)}", err=True)
        sys.exit(1)
    finally:
        outputs.release()
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)
        if watchdog is not None:
            watchdog.stop()


def _terminate(signum, frame):
    signal.signal(signal.SIGTERM, signal.SIG_DFL)  # a second SIGTERM ends the process at once
    _stopped()
    raise Terminated


def _stopped() -> None:
    """From a stop on, the finalizers of what it left half made fail unprinted (a Rerun stream whose constructor
    the stop interrupted has no ``inner`` for its ``__del__``: seen in the test suite)."""
    sys.unraisablehook = lambda unraisable: None


class _Watchdog:
    """Ends the process GRACE_S after a SIGTERM or Ctrl-C that the command has not yet acted on: Python runs signal
    handlers between bytecodes, so a long call into C (GEOS on a huge map) would delay the clean stop for minutes.
    Outputs stay whole either way (they are renamed into place only when complete). A forked child (a pool's
    worker) shares the pipe, so it stops writing its own signals there: a worker the pool terminates would
    otherwise read as the user's SIGTERM."""

    GRACE_S = 10.0

    def __init__(self):
        self.read, write = os.pipe()
        os.set_blocking(write, False)
        self.previous = signal.set_wakeup_fd(write, warn_on_full_buffer=False)
        self.write, self.done = write, threading.Event()
        threading.Thread(target=self._watch, daemon=True).start()

    def _watch(self) -> None:
        while True:
            got = os.read(self.read, 64)  # the C-level handler writes each signal's number here, at once
            if not got or self.done.is_set():
                return
            if any(n in (signal.SIGTERM, signal.SIGINT) for n in got) and not self.done.wait(self.GRACE_S):
                sys.stderr.write("Terminated (the command did not stop in time).\n")
                os._exit(143 if signal.SIGTERM in got else 130)

    @staticmethod
    def forget_in_child() -> None:
        try:
            signal.set_wakeup_fd(-1)
        except ValueError:  # not Python's main thread: signals are not handled here at all
            pass

    def stop(self) -> None:
        self.done.set()
        signal.set_wakeup_fd(self.previous)
        os.close(self.write)  # the watching thread reads the end of the pipe and ends


os.register_at_fork(after_in_child=_Watchdog.forget_in_child)
