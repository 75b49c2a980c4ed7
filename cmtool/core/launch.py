"""Which process of a ``torchrun`` launch this is, read from the variables torchrun sets (RANK, WORLD_SIZE,
LOCAL_RANK, MASTER_ADDR, MASTER_PORT): all of them, or none of the first three (a process on its own). Kept apart
from :mod:`cmtool.core.dist`, which imports torch, so that every command can ask before it starts."""

from __future__ import annotations

import os

from cmtool.core.errors import CmtoolError

TORCHRUN = ("RANK", "WORLD_SIZE", "LOCAL_RANK", "MASTER_ADDR", "MASTER_PORT")


def launch() -> tuple[int, int, int]:
    """(rank, world size, local rank) of this process, (0, 1, 0) on its own; an environment with only some of
    torchrun's variables, with numbers that do not fit together, or without an address and port torch can read, is
    refused."""
    given = {k: os.environ[k] for k in TORCHRUN if k in os.environ}
    if not given.keys() & set(TORCHRUN[:3]):
        return 0, 1, 0
    shown = " ".join(f"{k}={v}" for k, v in given.items())
    missing = [k for k in TORCHRUN if k not in given]
    if missing:
        raise CmtoolError(f"{shown}: not a torchrun launch ({', '.join(missing)} not set); start it with torchrun "
                          f"or unset {', '.join(given)}")
    try:
        rank, world, local = (int(given[k]) for k in TORCHRUN[:3])
    except ValueError:
        raise CmtoolError(f"{shown}: RANK, WORLD_SIZE and LOCAL_RANK must be whole numbers") from None
    if not 0 <= local <= rank < world:
        raise CmtoolError(f"{shown}: expected 0 <= LOCAL_RANK <= RANK < WORLD_SIZE")
    if not given["MASTER_ADDR"].strip():
        raise CmtoolError(f"{shown}: MASTER_ADDR is empty; give the address of the first process's machine")
    if not given["MASTER_PORT"].strip().isdigit() or not 0 < int(given["MASTER_PORT"]) < 65536:
        raise CmtoolError(f"{shown}: MASTER_PORT must be a port number, 1 to 65535")
    return rank, world, local
