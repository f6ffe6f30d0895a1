"""How adaptive solves are differentiated.

Fixed-step solves run through `lax.scan`, which supports forward and reverse
mode alike, and ignore this choice.  Adaptive solves run a while loop whose
trip count is data-dependent; which loop is built decides which autodiff mode
works (the same trade-off as diffrax's adjoints, built on
``equinox.internal.while_loop``):

- `RecursiveCheckpointAdjoint` (default): reverse mode (`jax.grad`,
  `jax.jacrev`) through a checkpointed loop bounded by ``max_steps``; memory
  O(checkpoints), recomputation O(steps log steps).  Forward mode is not
  supported.
- `ForwardMode`: a plain `lax.while_loop`; `jax.jvp`/`jax.jacfwd` only.
- `DirectAdjoint`: a bounded loop of nested scans; both modes, at a run-time
  cost that grows with ``max_steps`` (every member runs the bounded loop),
  plus one forward solve that decides the steps the loop replays.
"""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx

__all__ = ["AbstractAdjoint", "RecursiveCheckpointAdjoint", "ForwardMode", "DirectAdjoint"]


class AbstractAdjoint(eqx.Module):
    kind: eqx.AbstractClassVar[str]

    @property
    def checkpoints(self) -> int | None:
        return None


class RecursiveCheckpointAdjoint(AbstractAdjoint):
    """Reverse-mode autodiff with online recursive checkpointing.

    Attributes:
        checkpoints: number of checkpoints (None: derived from ``max_steps``).
    """

    kind: ClassVar[str] = "checkpointed"
    checkpoints: int | None = eqx.field(default=None, static=True)  # type: ignore[assignment]


class ForwardMode(AbstractAdjoint):
    """Forward-mode autodiff (`jax.jacfwd`) through a plain `lax.while_loop`."""

    kind: ClassVar[str] = "lax"


class DirectAdjoint(AbstractAdjoint):
    """Both modes, through a bounded loop of nested scans.

    An adaptive solve with this adjoint runs twice: an undifferentiated solve
    decides the steps (sizes, accepted or rejected), and the differentiated
    loop replays those decisions, so every recomputation in its backward pass
    takes the steps that were taken.  Cost: one more forward solve, plus the
    bounded loop's ``max_steps`` iterations per member.
    """

    kind: ClassVar[str] = "bounded"
