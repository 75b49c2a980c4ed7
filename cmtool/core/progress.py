"""A tiny progress reporter for long loops: one status line on stderr with items/s and ETA.

On a terminal the line is redrawn in place; elsewhere (logs, CI) a new line is printed every
``log_every_s`` seconds. Extra values (a loss, a learning rate) can ride along::

    with Progress(total=len(units), label="build", unit="scenes") as bar:
        for n in work():
            bar.update(n)
    bar.update(1, loss=0.12)  # shown as "loss=0.12"
"""

from __future__ import annotations

import sys
import time


def format_seconds(s: float) -> str:
    """``75`` -> ``"1m15s"``; ``3700`` -> ``"1h01m"``."""
    s = int(round(s))
    if s < 60:
        return f"{s}s"
    if s < 3600:
        return f"{s // 60}m{s % 60:02d}s"
    return f"{s // 3600}h{(s % 3600) // 60:02d}m"


class Progress:
    """Counts done items and reports rate and remaining time.

    ``total`` may be None when unknown (no percentage, no ETA); ``first``: items done before this count began (a
    resumed run: the count goes on from there, the rate and ETA from this run's own). Output goes to ``stream``
    (stderr by default); ``enabled=False`` silences it while still counting.
    """

    def __init__(self, total: int | None, label: str = "", unit: str = "items", stream=None,
                 enabled: bool = True, refresh_s: float = 0.2, log_every_s: float = 10.0, first: int = 0):
        self.total, self.label, self.unit, self.first = total, label, unit, first
        self.stream = stream if stream is not None else sys.stderr
        self.enabled = enabled
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self.interval = refresh_s if self.tty else log_every_s
        self.done = first
        self.info: dict = {}
        self.start = time.perf_counter()
        self._last_draw = -float("inf")
        self._stale = True  # counts or values changed since the last line drawn

    @property
    def elapsed(self) -> float:
        return time.perf_counter() - self.start

    @property
    def rate(self) -> float:
        return (self.done - self.first) / max(self.elapsed, 1e-9)

    def line(self) -> str:
        """The current status line (without line ending)."""
        parts = [self.label] if self.label else []
        if self.total:
            parts.append(f"{self.done}/{self.total} {self.unit} ({100.0 * self.done / self.total:.0f}%)")
        else:
            parts.append(f"{self.done} {self.unit}")
        rate = self.rate
        if 0 < rate < 0.1:  # slow items: time per item reads better than 0.0 per second
            parts.append(f"{1.0 / rate:.0f} s per {self.unit.rstrip('s')}")
        else:
            parts.append(f"{rate:.1f} {self.unit}/s")
        parts.append(f"elapsed {format_seconds(self.elapsed)}")
        if self.total and self.first < self.done < self.total:
            parts.append(f"ETA {format_seconds((self.total - self.done) / self.rate)}")
        parts += [f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in self.info.items()]
        return "  ".join(parts)

    def update(self, n: int = 1, **info) -> None:
        """Add ``n`` done items (and update the extra values shown)."""
        self.done += n
        self.info.update(info)
        self._stale = True
        now = time.perf_counter()
        if now - self._last_draw >= self.interval:
            self._draw()
            self._last_draw = now

    def close(self) -> None:
        """Print the final line, unless the last line drawn shows the final counts already (then end that one)."""
        if self._stale:
            self._draw(final=True)
        elif self.enabled and self.tty:
            self.stream.write("\n")
            self.stream.flush()

    def _draw(self, final: bool = False) -> None:
        if not self.enabled:
            return
        self._stale = False
        if self.tty:
            self.stream.write("\r\033[K" + self.line() + ("\n" if final else ""))
        else:
            self.stream.write(self.line() + "\n")
        self.stream.flush()

    def __enter__(self) -> "Progress":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
