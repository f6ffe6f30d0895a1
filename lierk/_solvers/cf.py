"""Commutator-free Lie-group methods."""

from __future__ import annotations

from typing import ClassVar

from .. import so3
from .base import AbstractSolver, Step, combine


class CF4(AbstractSolver):
    """Commutator-free order 4 (Celledoni, Marthinsen, Owren, Future Gener.
    Comput. Syst. 19, 2003), in body form with right multiplication:

        k1 = h f(R0)            R2 = R0 e^{k1/2}
        k2 = h f(R2)            R3 = R0 e^{k2/2}
        k3 = h f(R3)            R4 = R2 e^{k3 - k1/2}
        k4 = h f(R4)
        R1 = R0 e^{(3k1+2k2+2k3-k4)/12} e^{(-k1+2k2+2k3+3k4)/12}

    No dexpinv and no commutators; two exponentials per step.  Extra state y is
    advanced with the classical RK4 weights.
    """

    order: ClassVar[int] = 4
    stages: ClassVar[int] = 4
    dense_serves_first_stage: ClassVar[bool] = True

    def step(self, problem, t, h, R, y, fsal=None):
        b0 = problem.base(t, R, y)
        w1, g1 = fsal if fsal is not None else problem.at(b0, t, y)
        b2 = problem.advance(b0, 0.5 * h * w1)
        w2, g2 = problem.at(b2, t + 0.5 * h, combine(y, h, (0.5,), (g1,)))
        b3 = problem.advance(b0, 0.5 * h * w2)
        w3, g3 = problem.at(b3, t + 0.5 * h, combine(y, h, (0.0, 0.5), (g1, g2)))
        b4 = problem.advance(b2, h * (w3 - 0.5 * w1))
        w4, g4 = problem.at(b4, t + h, combine(y, h, (0.0, 0.0, 1.0), (g1, g2, g3)))
        ua = (h / 12.0) * (3.0 * w1 + 2.0 * w2 + 2.0 * w3 - w4)
        ub = (h / 12.0) * (-w1 + 2.0 * w2 + 2.0 * w3 + 3.0 * w4)
        y1 = combine(y, h, (1 / 6, 1 / 3, 1 / 3, 1 / 6), (g1, g2, g3, g4))
        return Step(so3.right_exp(R, ua, ub), y1, None, None)
