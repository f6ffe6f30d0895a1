"""First-order methods: the report's two Euler methods (eqs. 24 and 25)."""

from __future__ import annotations

from typing import ClassVar

from .. import so3
from .base import AbstractSolver, Step, combine


class ExplicitEuler(AbstractSolver):
    """The report's eq. 24, ``W_{i+1} = W_i + h W_i hat(omega_i)``.

    Order 1.  It does not stay on SO(3): ``||R^T R - I||`` grows like ``h`` per
    unit time.  Kept as the baseline that shows why Lie-group methods exist.
    """

    order: ClassVar[int] = 1
    no_interpolant: ClassVar[str | None] = (
        "ExplicitEuler leaves SO(3), so its steps have no interpolant on the group: dense output and events "
        "need a Lie-group solver (LieEuler, RKMK4, DOP853, ...)"
    )

    def step(self, problem, t, h, R, y, fsal=None):
        omega, ydot = problem.at(problem.base(t, R, y), t, y)
        return Step(R + h * so3.compose(R, so3.hat(omega)), combine(y, h, (1.0,), (ydot,)), None, None)


class LieEuler(AbstractSolver):
    """The report's eq. 25, ``W_{i+1} = W_i exp(h hat(omega_i))``.  Order 1, stays on SO(3)."""

    order: ClassVar[int] = 1
    dense_serves_first_stage: ClassVar[bool] = True

    def step(self, problem, t, h, R, y, fsal=None):
        omega, ydot = fsal if fsal is not None else problem.at(problem.base(t, R, y), t, y)
        u = h * omega
        return Step(so3.right_exp(R, u), combine(y, h, (1.0,), (ydot,)), None, None)
