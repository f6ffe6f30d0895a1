"""Butcher tableaux as validated constants.

Each tableau is checked once, when it is defined: ``c_i = sum_j a_ij``,
``sum_i b_i = 1``, the error weights sum to 0, the classical order conditions
up to order ``min(order, 4)`` hold, and an FSAL tableau's last row of ``a``
equals ``b``.  With the exact dexpinv of `lierk.so3`, every explicit tableau
here drives an RKMK method of the tableau's own order (Munthe-Kaas 1999).
"""

from __future__ import annotations

import dataclasses
import functools
from fractions import Fraction as F

import numpy as np

__all__ = [
    "ButcherTableau",
    "oscillation_error_constant",
    "EULER",
    "RK4",
    "FEHLBERG45",
    "DOPRI54",
    "DOP853",
    "SplittingScheme",
    "STRANG",
    "YOSHIDA4",
    "YOSHIDA6",
    "BLANES_MOAN4",
    "BLANES_MOAN6",
    "BLANES_MOAN_RKN4",
    "BLANES_MOAN_RKN6",
]


@dataclasses.dataclass(frozen=True)
class ButcherTableau:
    """An explicit Runge-Kutta tableau, hashable so it can be a static field.

    Attributes:
        name: for messages and plots.
        c: ``(s,)`` nodes.
        a: strictly lower-triangular rows; row ``i`` has ``i`` entries.
        b: ``(s,)`` weights of the propagated solution.
        order: order of the propagated solution.
        b_error: ``(s,)`` weights of the embedded error estimate
            ``e = h sum_i b_error_i k_i`` (``b - b_hat``), or None.
        error_order: the lower order ``q`` of the pair; step control uses the
            exponent ``-1/(q+1)``.
        b_error3: DOP853 only: the 3rd-order estimate that its error norm
            combines with the 5th-order one (Hairer, Norsett, Wanner I, II.10).
        fsal: the last stage is evaluated at the new point, so its field value
            is the next step's first stage.
        tolerance_calibration: adaptive steps hold the embedded estimate to
            ``tol * tolerance_calibration``, a measured constant that makes the
            global attitude error of the pair come out near ``tol`` (see
            `lierk._controller`).
        dense_c: nodes of the extra stages of a continuous extension (dense
            output), evaluated after the step; ``()`` for none.
        dense_a: their rows of ``a``; row ``i`` has ``stages + i`` entries
            (it may use every stage, the extra ones before it included).
        dense_b: ``(d, stages + len(dense_c))`` weights of the continuous
            extension in the nested basis of `lierk._interpolation`: with
            ``F_j = h sum_i dense_b[j][i] k_i``, the solution at ``t + theta h``
            is ``y + theta (F_0 + (1 - theta)(F_1 + theta (F_2 + ...)))``.
            Empty without a continuous extension.
        dense_order: the order ``q`` of the continuous extension (its error
            is ``O(h^(q+1))`` at every ``theta`` in ``[0, 1]``).
    """

    name: str
    c: tuple
    a: tuple
    b: tuple
    order: int
    b_error: tuple | None = None
    error_order: int | None = None
    b_error3: tuple | None = None
    fsal: bool = False
    tolerance_calibration: float = 1.0
    dense_c: tuple = ()
    dense_a: tuple = ()
    dense_b: tuple = ()
    dense_order: int | None = None

    def __post_init__(self):
        s = len(self.c)
        tol = 1e-12
        if len(self.a) != s or len(self.b) != s:
            raise ValueError(f"{self.name}: c, a and b must have {s} rows")
        for i, row in enumerate(self.a):
            if len(row) != i:
                raise ValueError(f"{self.name}: row {i} of a must have {i} entries, has {len(row)}")
            if abs(sum(row) - self.c[i]) > tol:
                raise ValueError(f"{self.name}: c[{i}] = {self.c[i]} but row {i} of a sums to {sum(row)}")
        if abs(sum(self.b) - 1) > tol:
            raise ValueError(f"{self.name}: b sums to {sum(self.b)}, not 1")
        for name, e in (("b_error", self.b_error), ("b_error3", self.b_error3)):
            if e is not None and (len(e) != s or abs(sum(e)) > tol):
                raise ValueError(f"{self.name}: {name} must have {s} entries summing to 0")
        if (self.b_error is None) != (self.error_order is None):
            raise ValueError(f"{self.name}: give b_error and error_order together")
        if self.fsal and (self.c[-1] != 1 or any(abs(x - y) > tol for x, y in zip(self.a[-1], self.b))):
            raise ValueError(f"{self.name}: an FSAL tableau's last row of a must equal b")
        A, b, c = self.a_matrix, np.asarray(self.b), np.asarray(self.c)
        conditions = [
            (1, b @ c, 1 / 2),
            (2, b @ c**2, 1 / 3),
            (2, b @ (A @ c), 1 / 6),
            (3, b @ c**3, 1 / 4),
            (3, b @ (c * (A @ c)), 1 / 8),
            (3, b @ (A @ c**2), 1 / 12),
            (3, b @ (A @ (A @ c)), 1 / 24),
        ]
        for k, value, want in conditions:
            if self.order > k and abs(value - want) > 1e-10:
                raise ValueError(f"{self.name}: an order-{k + 1} condition fails ({value} != {want})")
        self._check_dense(tol)

    def _check_dense(self, tol: float) -> None:
        """A continuous extension's extra rows are consistent and its weights
        interpolate: the solution of ``y' = 1`` is ``theta h`` (row sums 1, 0,
        0, ...), and at ``theta = 1`` (where only ``F_0`` is left) it is the
        step's (``dense_b[0] = b``)."""
        if not self.dense_b:
            if self.dense_c or self.dense_a or self.dense_order is not None:
                raise ValueError(f"{self.name}: dense_c, dense_a and dense_order need dense_b")
            return
        s, extra = self.stages, len(self.dense_c)
        if len(self.dense_a) != extra or self.dense_order is None:
            raise ValueError(f"{self.name}: give one row of dense_a per dense_c, and dense_order")
        for i, (c, row) in enumerate(zip(self.dense_c, self.dense_a)):
            if len(row) != s + i or abs(sum(row) - c) > tol:
                raise ValueError(f"{self.name}: dense row {i} must have {s + i} entries summing to dense_c[{i}] = {c}")
        B = np.asarray(self.dense_b)
        if B.ndim != 2 or B.shape[1] != s + extra:
            raise ValueError(f"{self.name}: dense_b must have rows of {s + extra} entries, got shape {B.shape}")
        sums = B.sum(axis=1)
        if abs(sums[0] - 1) > tol or np.abs(sums[1:]).max(initial=0.0) > 1e-10:
            raise ValueError(f"{self.name}: the continuous weights must sum to theta, got row sums {sums}")
        if np.abs(B[0] - np.concatenate([self.b, np.zeros(extra)])).max() > tol:
            raise ValueError(f"{self.name}: the continuous weights at theta = 1 (dense_b[0]) must equal b")

    @property
    def dense(self) -> bool:
        """Whether the tableau has a continuous extension (`dense_b`)."""
        return bool(self.dense_b)

    @property
    def stages(self) -> int:
        return len(self.c)

    @property
    def a_matrix(self) -> np.ndarray:
        A = np.zeros((self.stages, self.stages))
        for i, row in enumerate(self.a):
            A[i, :i] = row
        return A


def blend_estimates(err, err3, sqrt=np.sqrt):
    """DOP853's error: its 5th- and 3rd-order estimates ``err`` and ``err3``
    (norms, NumPy or JAX; ``sqrt`` of the same kind) blended so that the
    result behaves like O(h^8) (Hairer, Norsett, Wanner I, II.10):
    ``err^2 / sqrt(err^2 + 0.01 err3^2)``.  Where both are 0 this divides
    0 by 0; `lierk._solvers.rkmk.AbstractRKMK.error_norm` guards it."""
    return err * err / sqrt(err * err + 0.01 * err3 * err3)


@functools.lru_cache(maxsize=None)
def oscillation_error_constant(tableau: ButcherTableau) -> float:
    """``c`` such that a step of phase ``theta = rho h`` (rad) on the
    oscillation ``y' = i rho y``, ``|y| = 1``, gets the embedded error
    estimate ``c theta^(q+1)`` (``q = error_order``; DOP853's two estimates
    blended as its error norm blends them), read at ``theta = 0.05``.  It
    tells a controller the largest phase per step whose error it would
    accept at a tolerance: ``(tol / c)^(1/(q+1))``."""
    if tableau.b_error is None:
        raise ValueError(f"{tableau.name} has no error estimate")
    theta = 0.05
    z = 1j * theta
    k = np.linalg.solve(np.eye(tableau.stages) - z * tableau.a_matrix, np.ones(tableau.stages))

    def estimate(weights):
        return abs(z * np.dot(weights, k))

    e = estimate(tableau.b_error)
    if tableau.b_error3 is not None:
        e = blend_estimates(e, estimate(tableau.b_error3))
    return float(e / theta ** (tableau.error_order + 1))


def _f(*xs) -> tuple:
    return tuple(float(F(x)) for x in xs)


EULER = ButcherTableau("Euler", c=(0.0,), a=((),), b=(1.0,), order=1)

RK4 = ButcherTableau(
    "RK4",
    c=_f(0, "1/2", "1/2", 1),
    a=((), _f("1/2"), _f(0, "1/2"), _f(0, 0, 1)),
    b=_f("1/6", "1/3", "1/3", "1/6"),
    order=4,
)

# The report's Fehlberg 4(5) tableau (oppg4_fehlberg.py); advance with order 5.
_FEHLBERG_B4 = _f("25/216", 0, "1408/2565", "2197/4104", "-1/5", 0)
_FEHLBERG_B5 = _f("16/135", 0, "6656/12825", "28561/56430", "-9/50", "2/55")
FEHLBERG45 = ButcherTableau(
    "Fehlberg 4(5)",
    c=_f(0, "1/4", "3/8", "12/13", 1, "1/2"),
    a=(
        (),
        _f("1/4"),
        _f("3/32", "9/32"),
        _f("1932/2197", "-7200/2197", "7296/2197"),
        _f("439/216", -8, "3680/513", "-845/4104"),
        _f("-8/27", 2, "-3544/2565", "1859/4104", "-11/40"),
    ),
    b=_FEHLBERG_B5,
    order=5,
    b_error=tuple(x - y for x, y in zip(_FEHLBERG_B5, _FEHLBERG_B4)),
    error_order=4,
    # Near-axis batches of four bodies (T = 10 s) measured error/tol of 30 to 270.
    tolerance_calibration=1 / 30,
)

_DP_B5 = _f("35/384", 0, "500/1113", "125/192", "-2187/6784", "11/84", 0)
_DP_B4 = _f("5179/57600", 0, "7571/16695", "393/640", "-92097/339200", "187/2100", "1/40")
DOPRI54 = ButcherTableau(
    "Dormand-Prince 5(4)",
    c=_f(0, "1/5", "3/10", "4/5", "8/9", 1, 1),
    a=(
        (),
        _f("1/5"),
        _f("3/40", "9/40"),
        _f("44/45", "-56/15", "32/9"),
        _f("19372/6561", "-25360/2187", "64448/6561", "-212/729"),
        _f("9017/3168", "-355/33", "46732/5247", "49/176", "-5103/18656"),
        _DP_B5[:6],
    ),
    b=_DP_B5,
    order=5,
    b_error=tuple(x - y for x, y in zip(_DP_B5, _DP_B4)),
    error_order=4,
    fsal=True,
    # Near-axis batches of four bodies (T = 10 s) measured error/tol of 16 to 146.
    tolerance_calibration=1 / 15,
)

# Dormand-Prince 8(5,3) (DOP853) coefficients as published by Hairer and
# Wanner and distributed with SciPy (scipy/integrate/_ivp/dop853_coefficients.py,
# BSD licence).  The 13th stage is the FSAL evaluation at the new point, which
# the error estimates use.
_DOP853_C = (
    0.0,
    0.05260015195876773,
    0.0789002279381516,
    0.1183503419072274,
    0.2816496580927726,
    0.3333333333333333,
    0.25,
    0.3076923076923077,
    0.6512820512820513,
    0.6,
    0.8571428571428571,
    1.0,
    1.0,
)
_DOP853_A = (
    (),
    (0.05260015195876773,),
    (0.0197250569845379, 0.0591751709536137),
    (0.02958758547680685, 0.0, 0.08876275643042054),
    (0.2413651341592667, 0.0, -0.8845494793282861, 0.924834003261792),
    (0.037037037037037035, 0.0, 0.0, 0.17082860872947386, 0.12546768756682242),
    (0.037109375, 0.0, 0.0, 0.17025221101954405, 0.06021653898045596, -0.017578125),
    (
        0.03709200011850479,
        0.0,
        0.0,
        0.17038392571223998,
        0.10726203044637328,
        -0.015319437748624402,
        0.008273789163814023,
    ),
    (
        0.6241109587160757,
        0.0,
        0.0,
        -3.3608926294469414,
        -0.868219346841726,
        27.59209969944671,
        20.154067550477894,
        -43.48988418106996,
    ),
    (
        0.47766253643826434,
        0.0,
        0.0,
        -2.4881146199716677,
        -0.590290826836843,
        21.230051448181193,
        15.279233632882423,
        -33.28821096898486,
        -0.020331201708508627,
    ),
    (
        -0.9371424300859873,
        0.0,
        0.0,
        5.186372428844064,
        1.0914373489967295,
        -8.149787010746927,
        -18.52006565999696,
        22.739487099350505,
        2.4936055526796523,
        -3.0467644718982196,
    ),
    (
        2.273310147516538,
        0.0,
        0.0,
        -10.53449546673725,
        -2.0008720582248625,
        -17.9589318631188,
        27.94888452941996,
        -2.8589982771350235,
        -8.87285693353063,
        12.360567175794303,
        0.6433927460157636,
    ),
    (
        0.054293734116568765,
        0.0,
        0.0,
        0.0,
        0.0,
        4.450312892752409,
        1.8915178993145003,
        -5.801203960010585,
        0.3111643669578199,
        -0.1521609496625161,
        0.20136540080403034,
        0.04471061572777259,
    ),
)
_DOP853_B = (
    0.054293734116568765,
    0.0,
    0.0,
    0.0,
    0.0,
    4.450312892752409,
    1.8915178993145003,
    -5.801203960010585,
    0.3111643669578199,
    -0.1521609496625161,
    0.20136540080403034,
    0.04471061572777259,
    0.0,
)
_DOP853_E5 = (
    0.01312004499419488,
    0.0,
    0.0,
    0.0,
    0.0,
    -1.2251564463762044,
    -0.4957589496572502,
    1.6643771824549864,
    -0.35032884874997366,
    0.3341791187130175,
    0.08192320648511571,
    -0.022355307863886294,
    0.0,
)
_DOP853_E3 = (
    -0.18980075407240762,
    0.0,
    0.0,
    0.0,
    0.0,
    4.450312892752409,
    1.8915178993145003,
    -5.801203960010585,
    -0.4226823213237919,
    -0.1521609496625161,
    0.20136540080403034,
    0.02265179219836082,
    0.0,
)
# DOP853's continuous extension of order 7 (Hairer, Norsett, Wanner I, II.6,
# and Hairer's DOP853 code; coefficients as distributed with SciPy): three more
# stages after the step, at c = 0.1, 0.2 and 7/9, and a polynomial of degree 7
# in the nested form (SciPy's)
#     y(x) = y0 + x (F0 + (1 - x)(F1 + x (F2 + (1 - x)(F3 + x (F4 + (1 - x)(F5 + x F6))))))
# with F0 = h sum_i b_i k_i, F1 = h k_1 - F0, F2 = 2 F0 - h (k_1 + k_13) and
# F3..F6 = h D k (k_13 is the FSAL stage, the field at the new point).
_DOP853_DENSE_C = (0.1, 0.2, 0.7777777777777778)
_DOP853_DENSE_A = (
    (
        0.056167502283047954,
        0.0,
        0.0,
        0.0,
        0.0,
        0.0,
        0.25350021021662483,
        -0.2462390374708025,
        -0.12419142326381637,
        0.15329179827876568,
        0.00820105229563469,
        0.007567897660545699,
        -0.008298,
    ),
    (
        0.03183464816350214,
        0.0,
        0.0,
        0.0,
        0.0,
        0.028300909672366776,
        0.053541988307438566,
        -0.05492374857139099,
        0.0,
        0.0,
        -0.00010834732869724932,
        0.0003825710908356584,
        -0.00034046500868740456,
        0.1413124436746325,
    ),
    (
        -0.42889630158379194,
        0.0,
        0.0,
        0.0,
        0.0,
        -4.697621415361164,
        7.683421196062599,
        4.06898981839711,
        0.3567271874552811,
        0.0,
        0.0,
        0.0,
        -0.0013990241651590145,
        2.9475147891527724,
        -9.15095847217987,
    ),
)
_DOP853_DENSE_D = (
    (
        -8.428938276109013,
        0.0,
        0.0,
        0.0,
        0.0,
        0.5667149535193777,
        -3.0689499459498917,
        2.38466765651207,
        2.117034582445028,
        -0.871391583777973,
        2.2404374302607883,
        0.6315787787694688,
        -0.08899033645133331,
        18.148505520854727,
        -9.194632392478356,
        -4.436036387594894,
    ),
    (
        10.427508642579134,
        0.0,
        0.0,
        0.0,
        0.0,
        242.28349177525817,
        165.20045171727028,
        -374.5467547226902,
        -22.113666853125306,
        7.733432668472264,
        -30.674084731089398,
        -9.332130526430229,
        15.697238121770845,
        -31.139403219565178,
        -9.35292435884448,
        35.81684148639408,
    ),
    (
        19.985053242002433,
        0.0,
        0.0,
        0.0,
        0.0,
        -387.0373087493518,
        -189.17813819516758,
        527.8081592054236,
        -11.57390253995963,
        6.8812326946963,
        -1.0006050966910838,
        0.7777137798053443,
        -2.778205752353508,
        -60.19669523126412,
        84.32040550667716,
        11.99229113618279,
    ),
    (
        -25.69393346270375,
        0.0,
        0.0,
        0.0,
        0.0,
        -154.18974869023643,
        -231.5293791760455,
        357.6391179106141,
        93.40532418362432,
        -37.45832313645163,
        104.0996495089623,
        29.8402934266605,
        -43.53345659001114,
        96.32455395918828,
        -39.17726167561544,
        -149.72683625798564,
    ),
)


def _dop853_dense_b() -> tuple:
    """The rows ``F_0 .. F_6`` above as weights of the 16 stages."""
    b = np.concatenate([_DOP853_B, np.zeros(3)])
    k1, k13 = np.eye(16)[0], np.eye(16)[12]
    rows = [b, k1 - b, 2 * b - (k1 + k13)] + [np.asarray(r) for r in _DOP853_DENSE_D]
    return tuple(tuple(float(x) for x in row) for row in rows)


DOP853 = ButcherTableau(
    "DOP853",
    c=_DOP853_C,
    a=_DOP853_A,
    b=_DOP853_B,
    order=8,
    b_error=_DOP853_E5,
    error_order=7,
    b_error3=_DOP853_E3,
    fsal=True,
    # Near-axis batches of four bodies (T = 10 s) measured error/tol of 13 to 30.
    tolerance_calibration=1 / 3,
    dense_c=_DOP853_DENSE_C,
    dense_a=_DOP853_DENSE_A,
    dense_b=_dop853_dense_b(),
    dense_order=7,
)


@dataclasses.dataclass(frozen=True)
class SplittingScheme:
    """Coefficients of a symmetric splitting ``K(a_0 h) D(b_0 h) K(a_1 h) ... D(b_{s-1} h) K(a_s h)``.

    ``K`` is the kick (the torques' flow) and ``D`` the drift (the exact
    torque-free flow).  Checked once, when defined: ``sum(a) = sum(b) = 1``,
    ``len(a) = len(b) + 1``, and both are palindromes, so the method is
    symmetric (time-reversible) and its order is even.  The order itself is
    measured by the tests (a fitted slope on the heavy top), not assumed.

    Attributes:
        name: for messages and plots.
        a: ``(s + 1,)`` kick fractions of the step.
        b: ``(s,)`` drift fractions of the step.
        order: the composition's order.
        nystrom: True for a Runge-Kutta-Nystrom scheme, whose ``order`` holds
            only when the kicks do not read the momentum (torques of time and
            attitude: gravity, body and space torques).  Then the kick is
            nilpotent against the drift, ``[K, [K, [K, D]]] = 0`` (the kinetic
            energy is quadratic in the momentum), and such schemes are built
            on the fewer order conditions this leaves, for much smaller error
            constants at the same number of drifts (Blanes and Moan 2002).
    """

    name: str
    a: tuple
    b: tuple
    order: int
    nystrom: bool = False

    def __post_init__(self):
        tol = 1e-13
        if len(self.a) != len(self.b) + 1:
            raise ValueError(f"{self.name}: need one more kick than drifts, got {len(self.a)} and {len(self.b)}")
        for label, x in (("a", self.a), ("b", self.b)):
            if abs(sum(x) - 1) > tol:
                raise ValueError(f"{self.name}: {label} sums to {sum(x)}, not 1")
            if any(abs(p - q) > tol for p, q in zip(x, x[::-1])):
                raise ValueError(f"{self.name}: {label} is not a palindrome, so the method is not symmetric")

    @property
    def stages(self) -> int:
        """Drifts per step."""
        return len(self.b)

    @classmethod
    def compose(cls, name: str, gammas: tuple, order: int) -> "SplittingScheme":
        """Strang steps of fractions ``gammas`` in sequence, adjacent half-kicks merged."""
        a = [gammas[0] / 2] + [(p + q) / 2 for p, q in zip(gammas, gammas[1:])] + [gammas[-1] / 2]
        return cls(name, tuple(a), tuple(gammas), order)


STRANG = SplittingScheme("Strang", a=(0.5, 0.5), b=(1.0,), order=2)

# Yoshida (1990) / Suzuki triple jump of Strang steps.
_Y1 = 1.0 / (2.0 - 2.0 ** (1.0 / 3.0))
YOSHIDA4 = SplittingScheme.compose("Yoshida 4", (_Y1, 1.0 - 2.0 * _Y1, _Y1), order=4)

# Yoshida (1990), Phys. Lett. A 150, 262, order 6 "solution A": 7 Strang steps.
_W1, _W2, _W3 = -1.17767998417887, 0.235573213359357, 0.784513610477560
_W0 = 1.0 - 2.0 * (_W1 + _W2 + _W3)
YOSHIDA6 = SplittingScheme.compose("Yoshida 6", (_W3, _W2, _W1, _W0, _W1, _W2, _W3), order=6)


def _palindrome(head: tuple, middle: float | None) -> tuple:
    return head + (() if middle is None else (middle,)) + head[::-1]


# Blanes and Moan (2002), J. Comput. Appl. Math. 142, 313, Table 2: the
# 6-stage order-4 method S6 and the 10-stage order-6 method S10, optimised for
# small error constants.
_BM4_A = (0.0792036964311957, 0.353172906049774, -0.0420650803577195)
_BM4_B = (0.209515106613362, -0.143851773179818)
BLANES_MOAN4 = SplittingScheme(
    "Blanes-Moan 4",
    a=_palindrome(_BM4_A, 1.0 - 2.0 * sum(_BM4_A)),
    b=_palindrome(_BM4_B + (0.5 - sum(_BM4_B),), None),
    order=4,
)
_BM6_A = (0.0502627644003922, 0.413514300428344, 0.0450798897943977, -0.188054853819569, 0.541960678450780)
_BM6_B = (0.148816447901042, -0.132385865767784, 0.067307604692185, 0.432666402578175)
BLANES_MOAN6 = SplittingScheme(
    "Blanes-Moan 6",
    a=_palindrome(_BM6_A, 1.0 - 2.0 * sum(_BM6_A)),
    b=_palindrome(_BM6_B + (0.5 - sum(_BM6_B),), None),
    order=6,
)

# Blanes and Moan (2002), Table 3: the Runge-Kutta-Nystrom methods SRKN_6^b
# (order 4, 6 drifts) and SRKN_11^b (order 6, 11 drifts), which begin and end
# with a kick.  On the heavy tops of `benchmarks/torqued.py` they are 3 to 16
# times more accurate than S6 and S10 above at the same step.
_RKN4_KICK = (0.0829844064174052, 0.396309801498368, -0.0390563049223486)
_RKN4_DRIFT = (0.245298957184271, 0.604872665711080)
BLANES_MOAN_RKN4 = SplittingScheme(
    "Blanes-Moan RKN 4",
    a=_palindrome(_RKN4_KICK, 1.0 - 2.0 * sum(_RKN4_KICK)),
    b=_palindrome(_RKN4_DRIFT + (0.5 - sum(_RKN4_DRIFT),), None),
    order=4,
    nystrom=True,
)
_RKN6_KICK = (0.0414649985182624, 0.198128671918067, -0.0400061921041533, 0.0752539843015807, -0.0115113874206879)
_RKN6_DRIFT = (0.123229775946271, 0.290553797799558, -0.127049212625417, -0.246331761062075, 0.357208872795928)
BLANES_MOAN_RKN6 = SplittingScheme(
    "Blanes-Moan RKN 6",
    a=_palindrome(_RKN6_KICK + (0.5 - sum(_RKN6_KICK),), None),
    b=_palindrome(_RKN6_DRIFT, 1.0 - 2.0 * sum(_RKN6_DRIFT)),
    order=6,
    nystrom=True,
)
