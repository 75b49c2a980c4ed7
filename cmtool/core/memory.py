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


def in_batches(n: int, search, pairs: int = 1 << 20, most: int = 4096, until=None) -> int:
    """Call ``search(lo, hi)`` on consecutive ranges covering ``range(n)``, each sized from the count of pairs the
    one before found (``search`` returns it) so that about ``pairs`` come back at once: from 16 items on, at most
    doubling, at most ``most`` items; stop early once ``until()`` holds. Returns how many items were searched. A
    crowded map's candidate pairs thus never all meet in memory."""
    done, size = 0, 16
    while done < n and not (until is not None and until()):
        hi = min(done + size, n)
        found = search(done, hi)
        size, done = int(min(most, 2 * size, max(1, (hi - done) * pairs // max(found, 1)))), hi
    return done
