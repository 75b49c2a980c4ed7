"""What a command may write: never over one of its own inputs, never in place of a device, FIFO, socket or
link, and never into an output folder that another run is writing.

The CLI names each command's inputs (:func:`note_input`) and output folders (:func:`claim_folder`, which removes
the temporary files a killed run left there) as it parses its options; every writer of :mod:`cmtool.core.jsonio`
asks :func:`target` where a write may go, and says why a file could not be read or written with :func:`os_reason`.
:func:`release` ends a command: it forgets the inputs, unlocks the folders and removes those it made and left empty.
"""

from __future__ import annotations

import errno
import fcntl
import os
import stat
from pathlib import Path

from cmtool.core.errors import CmtoolError
from cmtool.core.launch import launch

_inputs: dict[tuple[int, int] | str, Path] = {}  # identity (device, inode; or the real path) -> the path as given
_locks: dict[str, int] = {}  # real path of a claimed folder -> its open descriptor (flock held)
_made: list[Path] = []  # folders a claim created, removed again at release when still empty


def _identity(path: Path) -> tuple[int, int] | str:
    try:
        st = os.stat(path)
        return st.st_dev, st.st_ino
    except OSError:
        return os.path.realpath(path)


def note_input(path: str | os.PathLike) -> None:
    """Remember ``path`` as an input of the running command: :func:`target` refuses to write over it."""
    path = Path(path)
    _inputs[_identity(path)] = path


def is_input(path: str | os.PathLike) -> Path | None:
    """The input (as given) that ``path`` names the same file as, if any."""
    return _inputs.get(_identity(Path(path)))


def target(path: str | os.PathLike) -> Path:
    """Where a file written to ``path`` goes: the file a link points at (the link stays a link). Refused with a
    :class:`CmtoolError`: an input of the command, and anything but a regular file or nothing (a device, FIFO or
    socket, such as /dev/null or /dev/stdout)."""
    path = Path(path)
    try:
        st = os.stat(path)
    except OSError:
        st = None
    if st is not None and not (stat.S_ISREG(st.st_mode) or stat.S_ISDIR(st.st_mode)):
        raise CmtoolError(f"{path}: not a regular file (a device, FIFO or socket): cmtool writes files, "
                          f"give a file path")
    same = is_input(path)
    if same is not None:
        raise CmtoolError(f"{path}: is an input of this command ({same}); write the output to another path")
    return Path(os.path.realpath(path)) if path.is_symlink() else path


def os_reason(e: OSError) -> str:
    """Why an operating-system call failed, in words that name what the user can fix."""
    if e.errno in (errno.ENOTDIR, errno.EEXIST) and e.filename:
        for parent in Path(e.filename).parents if e.errno == errno.ENOTDIR else [Path(e.filename)]:
            if parent.is_file():
                return f"{parent} is a file, not a folder"
    if e.errno == errno.EFBIG:
        return "file too large (the file size limit, or a full disk)"
    return e.strerror.lower() if e.strerror else str(e)


def claim_folder(path: str | os.PathLike) -> None:
    """Make the output folder ``path`` (with its parents) and lock it for this run, so that a second run on the same
    folder fails at once with one line instead of mixing its files with this run's; the temporary files a killed run
    left in it are removed. Under torchrun only the first process claims (the others write into the folder it holds).
    """
    path = Path(path)
    if launch()[0] != 0:
        return
    key = os.path.realpath(path)
    if key in _locks:
        return
    missing = [p for p in (path, *path.parents) if not p.exists()]
    try:
        path.mkdir(parents=True, exist_ok=True)
        fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY)
    except OSError as e:
        raise CmtoolError(f"cannot write {path}: {os_reason(e)}") from None
    _made.extend(reversed(missing))
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError as e:
        os.close(fd)
        if e.errno in (errno.EWOULDBLOCK, errno.EAGAIN):
            raise CmtoolError(f"{path}: another cmtool run is writing into this folder; wait for it to finish or "
                              f"give another output folder") from None
        raise
    _locks[key] = fd
    _remove_leftovers(path)


def _remove_leftovers(folder: Path) -> None:
    """Remove the temporary files (``.cmtool-*.tmp``, :func:`cmtool.core.jsonio.temporary`) that a killed run left
    in ``folder``, here or in a hidden subfolder (an area's tile cache): the folder is claimed, so no run is writing
    them."""
    for tmp in [*folder.glob(".cmtool-*.tmp"), *folder.glob(".*/.cmtool-*.tmp")]:
        try:
            if tmp.is_file() and not tmp.is_symlink():
                tmp.unlink()
        except OSError:
            pass


def release() -> None:
    """End a command: forget its inputs, unlock its folders, remove the folders it made that stayed empty."""
    _inputs.clear()
    for fd in _locks.values():
        os.close(fd)
    _locks.clear()
    for folder in reversed(_made):
        try:
            folder.rmdir()
        except OSError:
            pass
    _made.clear()
