"""What JAX compiled in a block of code, and how long it took.

Every program XLA builds costs tens of milliseconds even when it is one
addition, and an eager ``jax.numpy`` operation on concrete values is such a
program.  `counting` lists the programs compiled (or loaded from the
persistent cache) in a block and the wall time spent tracing, lowering and
compiling them, from JAX's own monitoring events, so that a command can say
how much of its time went to compilation and a test can pin how many
programs a run builds::

    with lierk.app.compilations.counting() as c:
        sim = lierk.app.simulation.simulate(scene)
    c.count, c.seconds, c.names   # 3, 0.9, ['jit(piece)', 'jit(_compute)', ...]

Programs that JAX finds in its in-memory caches (a second call with the same
shapes) are neither compiled nor counted.
"""

from __future__ import annotations

import contextlib
import dataclasses
import threading
from collections.abc import Iterator

__all__ = ["Compilations", "counting"]

_COMPILE = "/jax/core/compile/backend_compile_duration"
_PHASES = (
    "/jax/core/compile/jaxpr_trace_duration",
    "/jax/core/compile/jaxpr_to_mlir_module_duration",
    _COMPILE,
)


@dataclasses.dataclass
class Compilations:
    """What `counting` saw.

    Attributes:
        names: the name of each program XLA compiled or loaded from the
            persistent cache, in order (``"jit(piece)"``, ``"jit(add)"``).
        spans: ``(start, end)`` wall-clock times (s, `time.time`) of each
            tracing, lowering and compilation phase; nested phases (a jitted
            function traced inside another) overlap.
    """

    names: list[str] = dataclasses.field(default_factory=list)
    spans: list[tuple[float, float]] = dataclasses.field(default_factory=list)

    @property
    def count(self) -> int:
        """The number of XLA programs compiled (or loaded)."""
        return len(self.names)

    @property
    def seconds(self) -> float:
        """Wall time (s) spent tracing, lowering and compiling: the length of
        the union of `spans`, so nested phases count once."""
        total, end = 0.0, float("-inf")
        for a, b in sorted(self.spans):
            if b > end:
                total += b - max(a, end)
                end = b
        return total


@contextlib.contextmanager
def counting() -> Iterator[Compilations]:
    """Record the compilations of the block (all threads) in the
    `Compilations` yielded; listening stops when the block ends."""
    import jax.monitoring

    seen = Compilations()
    lock = threading.Lock()

    def on_span(event: str, start: float, end: float, **kwargs) -> None:
        if event not in _PHASES:
            return
        with lock:
            seen.spans.append((start, end))
            if event == _COMPILE:
                seen.names.append(str(kwargs.get("fun_name", "?")))

    jax.monitoring.register_event_time_span_listener(on_span)
    try:
        yield seen
    finally:
        jax.monitoring.unregister_event_time_span_listener(on_span)
