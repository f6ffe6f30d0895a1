"""A progress bar on stderr, shared by long integrations and sweeps."""

from __future__ import annotations

import sys
import time

__all__ = ["Progress"]


class Progress:
    """A progress bar on stderr: redrawn in place on a terminal, otherwise a
    line at every quarter so logs stay short."""

    def __init__(self, label: str, total: float, unit: str = "", quiet: bool = False, stream=None):
        self.label, self.total, self.unit, self.quiet = label, float(total), unit, quiet
        self.stream = sys.stderr if stream is None else stream
        self.tty = hasattr(self.stream, "isatty") and self.stream.isatty()
        self.start = time.perf_counter()
        self.next_quarter = 0.25

    def update(self, done: float) -> None:
        if self.quiet:
            return
        frac = min(max(done / self.total, 0.0), 1.0) if self.total > 0 else 1.0
        if not self.tty and frac < self.next_quarter - 1e-12:
            return
        while self.next_quarter <= frac + 1e-12:
            self.next_quarter += 0.25
        width = 30
        bar = "#" * int(round(frac * width)) + "." * (width - int(round(frac * width)))
        text = (
            f"{self.label} [{bar}] {100 * frac:5.1f}%  {done:g}/{self.total:g}{self.unit}"
            f"  {time.perf_counter() - self.start:.1f} s"
        )
        self.stream.write(("\r" + text) if self.tty else text + "\n")
        if self.tty and frac >= 1.0:
            self.stream.write("\n")
        self.stream.flush()
