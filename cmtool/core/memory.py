"""Sizes asked for by a number (an option, a recipe field, a file header) checked against this machine's memory
before anything is allocated."""

from __future__ import annotations

import os

from cmtool.core.errors import CmtoolError


def available_bytes() -> int:
    """Memory this process can still get: MemAvailable of /proc/meminfo, else the free physical pages."""
    try:
        with open("/proc/meminfo", encoding="ascii") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")


def check_fits(nbytes: float, what: str) -> None:
    """Refuse, in one line naming ``what``, work that needs more than the memory available now."""
    free = available_bytes()
    if nbytes > free:
        raise CmtoolError(f"{what}: needs about {nbytes / 2**30:.1f} GiB of memory, {free / 2**30:.1f} GiB are free")
