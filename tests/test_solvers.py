"""Convergence orders and exact cases of every solver."""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx
import jax
import numpy as np
import pytest
from helpers import ADAPTIVE_SOLVERS, LIE_SOLVERS, OMEGA_GENERIC, TEE, final_attitudes, order_fit, reference_R
from scipy.spatial.transform import Rotation

import lierk
from lierk import so3

T1 = 4.0


@pytest.fixture(scope="module")
def tee_reference():
    return reference_R(TEE, OMEGA_GENERIC, T1)


def _final_R_for_steps(solver, inertia, omega0, t1, Ns):
    """R(t1) of the free body for each step count in Ns."""
    return final_attitudes(lierk.FreeRigidBody(inertia, omega0), solver, t1, t1 / np.asarray(Ns, dtype=float))


class _RK4FirstCommutator(lierk.AbstractRKMK):
    tableau: ClassVar = lierk.tableaux.RK4
    dexpinv_terms: ClassVar = 1

    @property
    def order(self) -> int:  # type: ignore[override]
        return 3


class _LabelledDOP853(lierk.AbstractRKMK):
    """A user's solver with an ``__init__`` of its own (no ``compact``)."""

    tableau: ClassVar = lierk.tableaux.DOP853
    label: str = eqx.field(static=True)

    def __init__(self, label):
        self.label = label


def test_a_solver_with_its_own_init_takes_the_stage_loop_and_keeps_its_fields():
    """The one-body and derivative forms copy the solver with ``compact``
    set, without calling its ``__init__``.  Before: a subclass whose
    ``__init__`` takes other arguments failed every call from Python
    (``dataclasses.replace`` passed ``compact=``), and every sensitivity."""
    from lierk._programs import in_form

    mine = _LabelledDOP853("mine")
    looped = in_form(mine, "one body", 100)
    assert (looped.label, looped.compact, mine.compact) == ("mine", True, None)
    # A long solve, or one whose count is known only at run time, and a
    # batch take the unrolled stages: they run several times faster.
    for form, steps in (("one body", 4097), ("one body", None), ("batch", 100)):
        assert in_form(mine, form, steps).compact is False
    # A form the user fixed is kept.
    assert in_form(_LabelledDOP853("x").in_form(False), "one body", 100).compact is False
    body = lierk.FreeRigidBody(TEE, OMEGA_GENERIC)
    R = lierk.solve(body, mine, 1.0, rtol=1e-9, atol=1e-9).R[-1]
    R_dop = lierk.solve(body, lierk.DOP853(), 1.0, rtol=1e-9, atol=1e-9).R[-1]
    np.testing.assert_allclose(R, R_dop, rtol=0, atol=1e-14)
    J = lierk.sensitivity(body, mine, 1.0, rtol=1e-9, atol=1e-9, estimate_error=False).jacobian
    assert J.shape == (3, 3) and np.all(np.isfinite(J))


# (solver, stated order, step counts over T1 = 4 s).  The step counts keep every
# error in the asymptotic range and above 1e-11, 100x the reference's own error
# (scipy DOP853 at rtol 1e-13 agrees with lierk's order-8 RKMK to ~1e-13).
ORDER_CASES = [
    (lierk.ExplicitEuler(), 1, [40, 80, 160, 320]),
    (lierk.LieEuler(), 1, [40, 80, 160, 320]),
    (lierk.NaiveLieRK4(), 2, [20, 40, 80, 160]),
    (lierk.RKMK4(), 4, [20, 40, 80, 160]),
    (lierk.CF4(), 4, [20, 40, 80, 160]),
    (lierk.RKMK(lierk.tableaux.RK4), 4, [20, 40, 80, 160]),
    # RK4 stages with dexpinv cut after the first commutator: order 3 (numerics notes).
    (_RK4FirstCommutator(), 3, [20, 40, 80, 160]),
    (lierk.RKMK(lierk.tableaux.FEHLBERG45), 5, [20, 28, 40, 56, 80]),
    (lierk.RKMK(lierk.tableaux.DOPRI54), 5, [20, 28, 40, 56, 80]),
]


@pytest.mark.parametrize(
    "solver, order, Ns",
    ORDER_CASES,
    ids=[f"{s.name}-{getattr(s, 'tableau', None) and s.tableau.name}" for s, _, _ in ORDER_CASES],
)
def test_empirical_order_on_non_commuting_problem(solver, order, Ns, tee_reference):
    assert solver.order == order
    Rs = _final_R_for_steps(solver, TEE, OMEGA_GENERIC, T1, Ns)
    errs = np.linalg.norm(Rs - tee_reference, axis=(-2, -1))
    assert errs.min() > 1e-11, errs
    fitted = order_fit(T1 / np.asarray(Ns, dtype=float), errs)
    print(f"{solver.name}: fitted order {fitted:.3f}, errors {errs}")
    assert abs(fitted - order) < 0.15, (fitted, errs)


def test_naive_lie_rk4_exact_on_sphere_but_order_2_on_tee():
    """The report's "RK4" is exact when all stages commute (I = c E) and second
    order otherwise: halving h divides the T-handle error by ~4, not 16."""
    sphere = 1e-3 * np.eye(3)
    Ns = [4, 8, 16]
    Rs = _final_R_for_steps(lierk.NaiveLieRK4(), sphere, OMEGA_GENERIC, T1, Ns)
    exact = np.asarray(so3.exp(T1 * OMEGA_GENERIC))
    assert np.abs(Rs - exact).max() < 1e-13
    Rs = _final_R_for_steps(lierk.NaiveLieRK4(), TEE, OMEGA_GENERIC, T1, Ns)
    errs = np.linalg.norm(Rs - reference_R(TEE, OMEGA_GENERIC, T1), axis=(-2, -1))
    ratios = errs[:-1] / errs[1:]
    assert np.all((ratios > 3.0) & (ratios < 5.0)), ratios


@pytest.mark.parametrize("solver", LIE_SOLVERS + [lierk.RKMK(lierk.tableaux.DOPRI54)], ids=lambda s: s.name)
def test_sphere_exact_for_lie_solvers(solver):
    """For I = c E, omega is constant in the body frame and R(t) = R0 exp(t hat(omega0));
    any Lie-group method reproduces it at any step, including a final partial step."""
    R0 = Rotation.from_rotvec([0.2, -0.5, 0.9]).as_matrix()
    omega0 = np.array([0.7, -1.3, 2.1])
    t1 = 3.7
    sol = lierk.solve(lierk.FreeRigidBody(2.5 * np.eye(3), omega0, R0=R0), solver, t1, dt=0.5)
    np.testing.assert_allclose(sol.R[-1], R0 @ np.asarray(so3.exp(t1 * omega0)), atol=2e-14)


def test_explicit_euler_not_exact_on_sphere():
    """The baseline leaves SO(3), so even the uniform rotation is only first order."""
    omega0 = np.array([0.7, -1.3, 2.1])
    sol = lierk.solve(lierk.FreeRigidBody(np.eye(3), omega0), lierk.ExplicitEuler(), 1.0, dt=0.1)
    assert np.abs(np.asarray(sol.R[-1]) - np.asarray(so3.exp(omega0))).max() > 1e-2


@pytest.mark.parametrize("solver", ADAPTIVE_SOLVERS, ids=lambda s: s.name)
def test_adaptive_error_follows_tolerance_and_sphere_is_exact(solver, tee_reference):
    """On the T-handle: tighter rtol, smaller error, within a modest factor of rtol (the
    controller measures the local error in the algebra).  On a sphere: exact at any rtol."""
    rtols = np.array([1e-5, 1e-7, 1e-9])
    run = jax.jit(
        jax.vmap(
            lambda inertia, omega0, rtol: lierk.solve(lierk.FreeRigidBody(inertia, omega0), solver, T1, rtol=rtol).R[
                -1
            ],
            in_axes=(None, None, 0),
        )
    )
    errs = np.linalg.norm(np.asarray(run(TEE, OMEGA_GENERIC, rtols)) - tee_reference, axis=(-2, -1))
    print(f"{solver.name}: errors {errs} at rtol {rtols}")
    assert np.all(np.diff(errs) < 0), errs
    assert np.all(errs < 100 * rtols), errs
    omega0 = np.array([0.7, -1.3, 2.1])
    Rs = np.asarray(run(np.diag([0.3, 0.3, 0.3]), omega0, rtols))
    np.testing.assert_allclose(Rs, np.broadcast_to(so3.exp(T1 * omega0), Rs.shape), atol=2e-14)


def test_rkmk_is_named_after_its_tableau():
    """Tables, plots and `lierk accuracy` tell the tableaux apart by name."""
    assert lierk.RKMK(lierk.tableaux.DOP853).name == "RKMK(DOP853)"
    assert lierk.RKMK(lierk.tableaux.DOPRI54).name == "RKMK(DOPRI54)"
    own = lierk.tableaux.ButcherTableau("Heun", c=(0.0, 1.0), a=((), (1.0,)), b=(0.5, 0.5), order=2)
    assert lierk.RKMK(own).name == "RKMK(Heun)"
    assert lierk.DOP853().name == "DOP853"
