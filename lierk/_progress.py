"""Progress on stderr for long integrations and sweeps, drawn by `tqdm`.

Compilation is its own phase: `Progress.compiling` reports how long it took
and restarts the clock, so the rate and the time left describe the run alone.
"""

from __future__ import annotations

import contextlib
import sys
import time

__all__ = ["Progress"]

# Elapsed and left on one clock (m:ss, h:mm:ss past an hour), the rate with
# an SI prefix and a space before its unit: "12.3k members/s", "83.1 s/s".
_METER = (
    "{desc}: {percentage:3.0f}%{bar} {n_fmt}/{total_fmt}{unit} [{elapsed} elapsed, {remaining} left, {rate_noinv_fmt}]"
)


class Progress:
    """Progress of a run from 0 to ``total`` (in ``unit``) on ``stream``
    (default stderr).

    On a terminal a `tqdm` bar is redrawn in place.  Otherwise (a log file, a
    pipe, a batch job) one line is written each time the run passes another
    ``1/lines`` of ``total``, and at the end: each line has a larger
    percentage than the one before, with the elapsed time, the time left and
    the rate.  `lierk.sweep` (``progress=True``) and the ``lierk`` command
    report through it; a loop of your own can too.

    Example:
        >>> bar = lierk.Progress("tee: t", 100.0, "s")
        >>> with bar.compiling():
        ...     run = jax.jit(piece).lower(*args).compile()
        >>> for k in range(10):
        ...     state = run(state)
        ...     bar.update(10.0 * (k + 1))

    Args:
        label: what runs, e.g. ``"tee: t"``.
        total: the value of `update`'s ``done`` at the end (> 0).
        unit: the unit of ``total`` (``"s"``, ``"members"``).
        quiet: write nothing.
        stream: a text stream; default ``sys.stderr``.
        lines: off a terminal, at most this many progress lines (default 10).
        clock: seconds as a float (default `time.perf_counter`); tests pass a
            fake one.
    """

    def __init__(
        self,
        label: str,
        total: float,
        unit: str = "",
        quiet: bool = False,
        stream=None,
        lines: int = 10,
        clock=time.perf_counter,
    ):
        self.label, self.total, self.unit, self.quiet = label, float(total), unit.strip(), quiet
        self.stream = sys.stderr if stream is None else stream
        self.tty = hasattr(self.stream, "isatty") and self.stream.isatty()
        self.lines, self.clock = lines, clock
        self.done, self.next_line = 0.0, 1
        self.start = clock()
        self.bar = None
        self._unit = f" {self.unit}" if self.unit else ""  # tqdm's, which it writes after numbers
        if not quiet and self.tty:
            from tqdm import tqdm  # (here: `import lierk` loads no tqdm)

            self.bar = tqdm(
                total=self.total,
                desc=label,
                unit=self._unit,
                unit_scale=True,
                file=self.stream,
                mininterval=0.2,
                bar_format=_METER.replace("{bar}", "|{bar}|"),
                dynamic_ncols=True,
            )

    @contextlib.contextmanager
    def compiling(self):
        """The block compiles (e.g. ``jax.jit(f).lower(...).compile()``): say
        so, then how long it took, and start the run's clock afterwards."""
        if self.quiet:
            yield
            return
        t = self.clock()
        if self.bar is not None:
            self.bar.set_description_str(f"{self.label} (compiling)")
        else:
            self._write(f"{self.label}: compiling")
        yield
        text = f"{self.label}: compiled in {self.clock() - t:.1f} s"
        self.start = self.clock()
        if self.bar is not None:
            self.bar.set_description_str(self.label)
            self.bar.write(text, file=self.stream)
            self.bar.reset(total=self.total)
            self.bar.update(self.done)
        else:
            self._write(text)

    def update(self, done: float) -> None:
        """The run has reached ``done`` (of ``total``)."""
        if self.quiet:
            return
        delta, self.done = done - self.done, float(done)
        if self.bar is not None:
            self.bar.update(delta)
            if self.done >= self.total:
                self.bar.close()
            return
        frac = self.done / self.total if self.total > 0 else 1.0
        if frac * self.lines + 1e-9 < self.next_line:
            return
        while self.next_line <= frac * self.lines + 1e-9:
            self.next_line += 1
        from tqdm import tqdm

        self._write(
            tqdm.format_meter(
                min(self.done, self.total),
                self.total,
                self.clock() - self.start,
                prefix=self.label,
                unit=self._unit,
                unit_scale=True,
                bar_format=_METER.replace("{bar}", ""),
            )
        )

    def _write(self, text: str) -> None:
        self.stream.write(text + "\n")
        self.stream.flush()
