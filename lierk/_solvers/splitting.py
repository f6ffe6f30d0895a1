"""Splitting methods: torque kicks around the exact torque-free flow.

Write the motion as the torque-free body plus the torques,

    d(R, m)/dt = (R hat(omega), m x omega)  +  (0, tau(t, R, m)).

The first part has an exact flow, the "drift" (`lierk.exact.free_flow`, or two
rotations for a symmetric body); the second, with ``R`` and ``t`` held fixed,
is the "kick" (`lierk.RigidBodyWithEffects.kick`: a straight line for torques
that do not read the momentum, an exponential for damping).  Time advances
with the drift and each kick reads the clock where it stands.  Strang's
kick-drift-kick is order 2; symmetric compositions of it reach orders 4 and 6
(`lierk.tableaux.SplittingScheme`).  When no torque reads the momentum, a kick
acts like a force in ``q'' = f(q)``: ``[K, [K, [K, D]]] = 0``, and the
Runge-Kutta-Nystrom schemes (`BlanesMoanRKN4`, `BlanesMoanRKN6`) use the
fewer order conditions this leaves for much smaller error constants.  Each piece is an exact flow on SO(3) x R^3,
so R stays a rotation to rounding.

For a conservative body (gravity, a constant space torque) every piece is a
symplectic map, so the energy error stays bounded over long runs instead of
drifting (Celledoni, Fasso, Safstrom, Zanna 2008; McLachlan 1993; Touma and
Wisdom 1994).  The drift is exact for any spin, so a fast top's spin costs
nothing; what limits the step is how fast the torque changes along the motion,
which for an asymmetric body is the spin rate again: there an RKMK method is
usually faster per accuracy (``benchmarks/results/torqued.md``).

Dense output and events (`lierk._interpolation.PartialStep`): the state at
``t_n + theta h`` is a fresh step of the method of size ``theta h`` from the
step's start, so between the steps it is as accurate as at them (exact to
rounding for a free body, where a polynomial interpolant was 500 to 10^7
times worse); each evaluation, and each event sample, costs a step.

In float32 every drift adds the rounding of an elliptic-function evaluation,
about 1e-7 per drift on the T-handle near its intermediate axis (1.2e-4 after
1000 Strang steps), against 2e-6 for RKMK4 over the same run; float64 has no
such floor worth noting.

References:
    E. Celledoni, F. Fasso, N. Safstrom, A. Zanna, SIAM J. Sci. Comput. 30
    (2008) 2084-2112.  H. Yoshida, Phys. Lett. A 150 (1990) 262-268.
    S. Blanes, P. C. Moan, J. Comput. Appl. Math. 142 (2002) 313-330.
"""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp

from .. import _interpolation as interpolation
from .. import so3
from .._problems.base import AbstractRigidBody
from ..tableaux import (
    BLANES_MOAN4,
    BLANES_MOAN6,
    BLANES_MOAN_RKN4,
    BLANES_MOAN_RKN6,
    STRANG,
    YOSHIDA4,
    YOSHIDA6,
    SplittingScheme,
)
from .base import AbstractSolver, Step

__all__ = [
    "AbstractSplitting",
    "Splitting",
    "Strang",
    "Yoshida4",
    "Yoshida6",
    "BlanesMoan4",
    "BlanesMoan6",
    "BlanesMoanRKN4",
    "BlanesMoanRKN6",
]


class AbstractSplitting(AbstractSolver):
    """Kick-drift splitting with the coefficients of ``self.scheme``.

    Works on problems that provide ``drift(R, y, h)`` (the exact torque-free
    flow) and ``kick(t, R, y, h)`` (the torques' flow): `lierk.RigidBodyWithEffects`,
    `lierk.FreeRigidBody` and `lierk.SpatialFreeRigidBody`.  Fixed step only:
    ``lierk.solve(problem, solver, t1, dt=...)``; ``estimate_error=True`` and
    ``target_error`` work as for any fixed-step solver.

    Two optional problem attributes steer it: ``closed_form_drift`` (True: the
    drift is small, and the stages are unrolled instead of looped) and
    ``kick_reads_momentum`` (the names of the torques that read ``m``; the
    Runge-Kutta-Nystrom schemes need it, and need it empty).
    """

    scheme: eqx.AbstractClassVar[SplittingScheme]

    @property
    def order(self) -> int:  # type: ignore[override]
        return self.scheme.order

    @property
    def stages(self) -> int:  # type: ignore[override]
        return self.scheme.stages

    def step(self, problem, t, h, R, y, fsal=None):
        if not isinstance(problem, AbstractRigidBody):
            raise ValueError(
                f"{self.name} splits off the exact torque-free flow, so it needs a rigid body with `drift` and "
                "`kick` (lierk.RigidBodyWithEffects, FreeRigidBody, SpatialFreeRigidBody), "
                f"got {type(problem).__name__}"
            )
        if self.scheme.nystrom:
            reads = problem.kick_reads_momentum
            if reads:
                raise ValueError(
                    f"{self.name} is a Runge-Kutta-Nystrom splitting: its order holds only for torques of time and "
                    f"attitude, and these effects read the momentum: {', '.join(reads)}; use BlanesMoan4 or "
                    "BlanesMoan6 instead"
                )
        a, b = self.scheme.a, self.scheme.b

        def stage(carry, ab):
            R, y, tk = carry
            y = problem.kick(tk, R, y, ab[0] * h)
            R, y = problem.drift(R, y, ab[1] * h)
            return (R, y, tk + ab[1] * h), None

        carry = (R, y, t)
        if problem.closed_form_drift:
            # A symmetric body's drift is two rotations: unrolled, XLA fuses
            # each kick into the drift before it and the inner loop's
            # bookkeeping goes.
            for ab in zip(a[:-1], b):
                carry, _ = stage(carry, ab)
        else:
            # A loop, not an unrolled sequence: the elliptic-function drift
            # is a large program, and ten copies of it took many seconds to
            # compile.
            carry, _ = jax.lax.scan(stage, carry, jnp.asarray([a[:-1], b], dtype=R.dtype).T)
        R, y, _ = carry
        y = problem.kick(t + h, R, y, a[-1] * h)
        # The drifts' products leave R off SO(3) by rounding only: the same
        # float32 correction as every other solver's step.
        return Step(so3.reorthonormalize(R), y, None, None)

    # Dense output: a shortened step from the step's start
    # (`lierk._interpolation.PartialStep`), not a polynomial through its ends,
    # whose O(h^6) error was 500 to 10^7 times the steps' on a free body.
    # Nothing is computed per step for it.

    def dense_node(self, problem, t, R, y):
        return None

    @property
    def dense_fevals(self) -> tuple[int, int]:
        # Nothing per step; locating an event runs shortened steps, a number
        # that depends on the root finder's iterations (not counted).
        return 0, 0

    def dense_step(self, problem, t, h, R, y, fsal=None, node=None):
        st = self.step(problem, t, h, R, y, fsal)
        empty = lambda a: jnp.zeros((0,) + jnp.shape(a), jnp.result_type(a))  # noqa: E731
        return st, (empty(R[0]), jax.tree_util.tree_map(empty, y)), None

    def dense_partial(self, problem):
        return interpolation.PartialStep(problem, self)


class Splitting(AbstractSplitting):
    """A splitting method with any `lierk.tableaux.SplittingScheme`.

    Example:
        >>> solver = lierk.Splitting(lierk.tableaux.BLANES_MOAN4)
    """

    scheme: SplittingScheme = eqx.field(static=True)


class Strang(AbstractSplitting):
    """Strang splitting: half kick, exact free flow, half kick.  Order 2,
    symmetric and symplectic; one drift per step."""

    scheme: ClassVar[SplittingScheme] = STRANG


class Yoshida4(AbstractSplitting):
    """Yoshida's triple jump of Strang steps: order 4, 3 drifts per step."""

    scheme: ClassVar[SplittingScheme] = YOSHIDA4


class Yoshida6(AbstractSplitting):
    """Yoshida's 7-step composition of Strang steps: order 6, 7 drifts per step."""

    scheme: ClassVar[SplittingScheme] = YOSHIDA6


class BlanesMoan4(AbstractSplitting):
    """Blanes and Moan's optimised order-4 splitting (S6): 6 drifts per step,
    with error constants far below the triple jump's."""

    scheme: ClassVar[SplittingScheme] = BLANES_MOAN4


class BlanesMoan6(AbstractSplitting):
    """Blanes and Moan's optimised order-6 splitting (S10): 10 drifts per step."""

    scheme: ClassVar[SplittingScheme] = BLANES_MOAN6


class BlanesMoanRKN4(AbstractSplitting):
    """Blanes and Moan's Runge-Kutta-Nystrom splitting SRKN_6^b: order 4,
    6 drifts per step, for torques of time and attitude only (gravity, body
    and space torques; not damping, which is refused).  About 10 times more
    accurate than `BlanesMoan4` at the same step on heavy tops."""

    scheme: ClassVar[SplittingScheme] = BLANES_MOAN_RKN4


class BlanesMoanRKN6(AbstractSplitting):
    """Blanes and Moan's Runge-Kutta-Nystrom splitting SRKN_11^b: order 6,
    11 drifts per step, for torques of time and attitude only (gravity, body
    and space torques; not damping, which is refused).  3 to 16 times more
    accurate than `BlanesMoan6` at the same step on heavy tops; with
    `BlanesMoanRKN4` the fastest lierk method on the symmetric tops of
    ``benchmarks/torqued.py`` (1e-4 to 1e-10)."""

    scheme: ClassVar[SplittingScheme] = BLANES_MOAN_RKN6
