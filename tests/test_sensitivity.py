"""`lierk.sensitivity`: Jacobians of the final state against the exact flow's
Jacobian and finite differences, forward against reverse mode, the error
estimate's calibration, hard states, and bad input."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import TEE, fd_jacobian, order_fit

import lierk
import lierk.exact

BOX = np.array([1.0, 2.0, 3.0])  # a 1:2:3 box's principal moments (up to scale)


def exact_jacobian(inertia, omega0, t1, R0=None):
    """``dR(t1)/d omega0`` ``(3, 3, 3)`` of the closed form."""
    return np.asarray(jax.jacfwd(lambda w: lierk.exact.free_rigid_body(inertia, w, t1, R0)[0])(jnp.asarray(omega0)))


def near_axis(moments, n, seed=0):
    """``(n, 3)`` angular velocities within ~11 degrees of the intermediate axis, |omega| in [1, 3]."""
    axis = int(np.argsort(moments)[1])
    rng = np.random.default_rng(seed)
    d = rng.uniform(-0.2, 0.2, (n, 3))
    d[:, axis] = 1.0
    return rng.uniform(1.0, 3.0, n)[:, None] * d / np.linalg.norm(d, axis=1, keepdims=True)


def test_an_inertia_entry_is_read_through_the_symmetric_tensor():
    """``wrt="inertia"`` reads the tensor through its symmetric part: the
    derivatives along ``I[0, 1]`` and ``I[1, 0]`` are equal, half the
    derivative along the symmetric change of both (central differences),
    and a splitting and an RKMK agree on them.  (Perturbed alone, an entry
    took the tensor off the symmetric matrices, where each solver read it
    otherwise: Strang 3.6, RKMK4 -0.29.)"""
    I = np.array([[2.0, 0.1, 0.0], [0.1, 3.0, 0.2], [0.0, 0.2, 4.0]])
    w0 = np.array([1.0, 0.3, 0.5])

    def body(inertia):
        return lierk.RigidBodyWithEffects(inertia, w0, effects=(lierk.Damping(0.1),))

    J = {}
    for solver, dt in ((lierk.Strang(), 0.05), (lierk.RKMK4(), 0.01)):
        J[solver.name] = np.asarray(
            lierk.sensitivity(body(I), solver, 2.0, dt=dt, wrt="inertia", estimate_error=False).jacobian_R
        )
        np.testing.assert_allclose(J[solver.name][..., 0, 1], J[solver.name][..., 1, 0], rtol=1e-12, atol=1e-14)
    scale = np.abs(J["RKMK4"]).max()
    assert np.abs(J["Strang"] - J["RKMK4"]).max() < 1e-4 * scale
    e, E = 1e-6, np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 0.0]])

    def R_of(inertia):
        return np.asarray(lierk.solve(body(inertia), lierk.RKMK4(), 2.0, dt=0.01).R[-1])

    fd = (R_of(I + e * E) - R_of(I - e * E)) / (2 * e)
    np.testing.assert_allclose(J["RKMK4"][..., 0, 1], 0.5 * fd, atol=1e-7 * scale)


@pytest.mark.parametrize(
    "inertia, omega0",
    [(TEE, [1.0, 0.05, 0.3]), (BOX, [0.3, 1.0, 0.2])],
    ids=["tee", "box"],
)
@pytest.mark.parametrize(
    "solver, options, tol",
    [
        (lierk.RKMK4(), dict(dt=0.01), 1e-6),
        (lierk.DP54(), dict(rtol=1e-10, atol=1e-10), 1e-6),
        (lierk.Strang(), dict(dt=0.01), 1e-5),
    ],
    ids=["RKMK4", "DP54", "Strang"],
)
def test_jacobian_matches_the_exact_flow(inertia, omega0, solver, options, tol):
    s = lierk.sensitivity(lierk.FreeRigidBody(inertia, omega0), solver, 5.0, **options)
    J = exact_jacobian(inertia, omega0, 5.0)
    err = np.linalg.norm(np.asarray(s.jacobian_R) - J) / np.linalg.norm(J)
    assert err < tol
    # The algebra form is R^T dR, and R(t1) is the solve's own.
    np.testing.assert_allclose(
        np.asarray(s.R), lierk.solve(lierk.FreeRigidBody(inertia, omega0), solver, 5.0, **options).R[-1]
    )
    np.testing.assert_allclose(
        np.asarray(s.jacobian),
        np.einsum("ji,jkl->ikl", np.asarray(s.R), J)[[2, 0, 1], [1, 2, 0]],
        atol=10 * tol * np.abs(J).max(),
    )
    # Each form's error bar is its error, within the bounds the module promises.
    true = np.linalg.norm(np.asarray(s.jacobian_R) - J)
    assert true / 10 <= float(s.jacobian_R_error) <= 100 * true
    R, omega = lierk.exact.free_rigid_body(inertia, omega0, 5.0)
    J_alg = np.einsum("ji,jkl->ikl", np.asarray(R), J)[[2, 0, 1], [1, 2, 0]]
    true = np.linalg.norm(np.asarray(s.jacobian) - J_alg)
    assert true / 10 <= float(s.jacobian_error) <= 100 * true
    J_m = np.asarray(lierk.FreeRigidBody(inertia, omega0).inertia) @ np.asarray(
        jax.jacfwd(lambda w: lierk.exact.free_rigid_body(inertia, w, 5.0)[1])(jnp.asarray(omega0))
    )
    true = np.linalg.norm(np.asarray(s.jacobian_y) - J_m)
    assert true / 10 <= float(s.jacobian_y_error) <= 100 * true


def test_forward_and_reverse_modes_agree():
    body = lierk.FreeRigidBody(BOX, [0.3, 1.0, 0.2])
    for solver, options in [(lierk.RKMK4(), dict(dt=0.02)), (lierk.DP54(), dict(rtol=1e-9, atol=1e-9))]:
        f = lierk.sensitivity(body, solver, 3.0, estimate_error=False, **options)
        r = lierk.sensitivity(body, solver, 3.0, estimate_error=False, mode="reverse", **options)
        np.testing.assert_allclose(np.asarray(r.jacobian), np.asarray(f.jacobian), rtol=1e-11, atol=1e-11)
        np.testing.assert_allclose(np.asarray(r.jacobian_y), np.asarray(f.jacobian_y), rtol=1e-11, atol=1e-13)


def test_error_estimate_is_calibrated_on_a_near_axis_batch():
    """Within 10x of the true Jacobian error for at least 90% of members
    whose error is above 1e-12, and never below 1/100 of it."""
    omegas = near_axis(np.diag(TEE), 24)
    body = lierk.FreeRigidBody(TEE, omegas[0])
    J_exact = jax.vmap(lambda w: jax.jacfwd(lambda v: lierk.exact.free_rigid_body(TEE, v, 10.0)[0])(w))(
        jnp.asarray(omegas)
    )
    for solver, options in [(lierk.RKMK4(), dict(dt=0.02)), (lierk.DP54(), dict(rtol=1e-8, atol=1e-8))]:
        s = jax.vmap(lambda w: lierk.sensitivity(body.with_omega0(w), solver, 10.0, **options))(jnp.asarray(omegas))
        true = np.sqrt(np.sum((np.asarray(s.jacobian_R) - np.asarray(J_exact)) ** 2, axis=(1, 2, 3)))
        est = np.asarray(s.jacobian_R_error)
        keep = true > 1e-12
        assert keep.sum() >= 20
        ratio = est[keep] / true[keep]
        assert np.mean((ratio > 0.1) & (ratio < 10)) >= 0.9, ratio
        assert ratio.min() >= 0.01, ratio


def test_vmap_matches_a_python_loop():
    omegas = near_axis(BOX, 3, seed=1)
    body = lierk.FreeRigidBody(BOX, omegas[0])

    def f(w):
        return lierk.sensitivity(body.with_omega0(w), lierk.RKMK4(), 2.0, dt=0.05, estimate_error=False)

    batched = jax.vmap(f)(jnp.asarray(omegas))
    for k, w in enumerate(omegas):
        one = f(jnp.asarray(w))
        np.testing.assert_allclose(np.asarray(batched.jacobian[k]), np.asarray(one.jacobian), rtol=1e-12, atol=1e-14)


# BOX (1, 2, 3) is the flat-plate limit, I_max = I_a + I_b: finite differences
# of the inertia step across it, which the validation warns about.
@pytest.mark.filterwarnings("ignore:inertia .* breaks the triangle inequality")
def test_other_inputs_against_finite_differences():
    """R0 against the exact flow; the inertia and an effect's parameter against
    central differences of the solve itself."""
    w0 = np.array([0.3, 1.0, 0.2])
    s = lierk.sensitivity(lierk.FreeRigidBody(BOX, w0), lierk.RKMK4(), 2.0, dt=0.01, wrt="R0")
    J = jax.jacfwd(lambda p: lierk.exact.free_rigid_body(BOX, w0, 2.0, lierk.so3.exp(p))[0])(jnp.zeros(3))
    assert np.linalg.norm(np.asarray(s.jacobian_R) - np.asarray(J)) < 1e-7 * np.linalg.norm(J)

    def R_of(problem):
        return np.asarray(lierk.solve(problem, lierk.RKMK4(), 2.0, dt=0.01).R[-1])

    s = lierk.sensitivity(
        lierk.FreeRigidBody(BOX, w0), lierk.RKMK4(), 2.0, dt=0.01, wrt="inertia", estimate_error=False
    )
    dI = np.array([[0.1, 0.02, 0.0], [0.02, -0.05, 0.03], [0.0, 0.03, 0.07]])
    e = 1e-6
    fd = (
        R_of(lierk.FreeRigidBody(np.diag(BOX) + e * dI, w0)) - R_of(lierk.FreeRigidBody(np.diag(BOX) - e * dI, w0))
    ) / (2 * e)
    np.testing.assert_allclose(np.einsum("ijkl,kl->ij", np.asarray(s.jacobian_R), dI), fd, atol=1e-8)

    def top(mass):
        return lierk.RigidBodyWithEffects(
            BOX,
            [0.0, 0.5, 3.0],
            lierk.so3.exp(jnp.array([0.3, 0.0, 0.0])),
            effects=(lierk.Gravity([0.0, 0.1, 0.5], mass, 9.81),),
        )

    s = lierk.sensitivity(top(2.0), lierk.RKMK4(), 1.0, dt=0.005, wrt=lambda p: p.effects[0].mass, estimate_error=False)
    sol = lambda m: np.asarray(lierk.solve(top(m), lierk.RKMK4(), 1.0, dt=0.005).R[-1])  # noqa: E731
    fd = (sol(2.0 + e) - sol(2.0 - e)) / (2 * e)
    np.testing.assert_allclose(np.asarray(s.jacobian_R), fd, atol=1e-7)


@pytest.mark.parametrize(
    "solver, options",
    [(lierk.RKMK4(), dict(dt=0.05)), (lierk.DP54(), dict(rtol=1e-9, atol=1e-9)), (lierk.Strang(), dict(dt=0.01))],
    ids=["RKMK4", "DP54", "Strang"],
)
def test_hard_states(solver, options):
    """At rest, a small perturbation turns the body steadily: J = T I exactly.
    A sphere turns steadily at any spin: its Lyapunov exponent is 0.  Both
    stay finite on the separatrix."""
    T = 2.0
    rest = lierk.sensitivity(lierk.FreeRigidBody(BOX, [0.0, 0.0, 0.0]), solver, T, **options)
    np.testing.assert_allclose(np.asarray(rest.jacobian), T * np.eye(3), atol=1e-9)
    sphere = lierk.sensitivity(lierk.FreeRigidBody([2.0, 2.0, 2.0], [0.3, -1.0, 0.5]), solver, T, **options)
    # The state transition [Omega J; d omega/d omega0] is [Omega T I; I].
    Omega = np.linalg.norm([0.3, -1.0, 0.5])
    np.testing.assert_allclose(float(sphere.ftle), np.log(np.hypot(1.0, Omega * T)) / T, rtol=1e-8)
    # The deprecated name is still the attitude's growth beyond T: 0 here.
    with pytest.warns(DeprecationWarning, match="Sensitivity.ftle"):
        assert abs(float(sphere.lyapunov_exponent)) < 1e-8
    # On the separatrix of the 1:2:3 box: |m|^2 = 2 E I2.
    m = np.array([1.0, 0.0, np.sqrt((2.0 - 1.0) / (3.0 - 2.0) * 3.0 / 1.0)])
    sep = lierk.sensitivity(lierk.FreeRigidBody(BOX, m / BOX), solver, T, **options)
    assert np.all(np.isfinite(np.asarray(sep.jacobian)))
    # The reference: central differences of the closed form, whose branch on
    # the separatrix itself does not see perturbations off it.
    R_exact = lambda w: np.asarray(lierk.exact.free_rigid_body(BOX, w, T)[0])  # noqa: E731
    e = 1e-6
    J = np.stack([(R_exact(m / BOX + e * d) - R_exact(m / BOX - e * d)) / (2 * e) for d in np.eye(3)], -1)
    assert np.linalg.norm(np.asarray(sep.jacobian_R) - J) < 1e-4 * np.linalg.norm(J)


def _steady_spin_transition(moments, omega, T):
    """The exact Jacobians ``(d xi, d m)`` ``(6, 3)`` of a free body's final
    state with respect to omega0, about the steady spin ``omega`` about a
    principal axis: the spin is an equilibrium of Euler's equations turning
    at a constant rate, so the linearisation is exact and its flow is
    ``expm(A T)``, with ``xi' = xi x omega + I^-1 dm`` and ``dm' = dm x omega
    + m x I^-1 dm`` (``R = R_ref exp(hat(xi))``, ``m = I omega + dm``)."""
    from scipy.linalg import expm

    hat = lambda v: np.cross(np.eye(3), v)  # noqa: E731  hat(v) u = v x u
    A = np.zeros((6, 6))
    A[:3, :3] = -hat(omega)
    A[:3, 3:] = np.diag(1 / moments)
    A[3:, 3:] = -hat(omega) + hat(moments * omega) @ np.diag(1 / moments)
    return expm(A * T)[:, 3:] @ np.diag(moments)  # a change of omega0 moves m0 by I d omega0


@pytest.mark.parametrize(
    "moments, axis, rate, times",
    [(np.diag(TEE), 0, 1.0, (20.0, 40.0)), (BOX, 1, 1.5, (10.0, 20.0))],
    ids=["tee", "box"],
)
def test_ftle_about_the_intermediate_axis_tends_to_the_linear_growth_rate(moments, axis, rate, times):
    """An exact spin about the intermediate axis: each Jacobian, and each
    error bar, against the exact linearisation; the FTLE is that of the
    exact state transition, and tends to the growth rate ``Omega sqrt((I1 -
    I2)(I2 - I3)/(I1 I3))`` as ``lambda + log(C)/T`` (the same ``C`` at both
    times).  The T-handle's rate is 0.368 1/s; the deprecated
    ``lyapunov_exponent`` read 0.325 there at 40 s."""
    omega = np.zeros(3)
    omega[axis] = rate
    i, j = [k for k in range(3) if k != axis]
    lam = rate * np.sqrt((moments[i] - moments[axis]) * (moments[axis] - moments[j]) / (moments[i] * moments[j]))
    offsets = []
    for T in times:
        s = lierk.sensitivity(lierk.FreeRigidBody(moments, omega), lierk.DOP853(), T, rtol=1e-12, atol=1e-12)
        phi = _steady_spin_transition(moments, omega, T)
        J, J_m = phi[:3], phi[3:]
        R = lierk.so3.exp(T * omega)
        for got, want, bar in (
            (s.jacobian, J, s.jacobian_error),
            (s.jacobian_y, J_m, s.jacobian_y_error),
            (s.jacobian_R, np.einsum("ij,kjl->ilk", R, np.asarray(lierk.so3.hat(J.T))), s.jacobian_R_error),
        ):
            err = np.linalg.norm(np.asarray(got) - want)
            assert err < 1e-9 * np.linalg.norm(want) and err / 10 <= float(bar) <= 10 * err, (T, err, float(bar))
        state = np.vstack([rate * J, J_m / moments[:, None]])
        ftle = np.log(np.linalg.svd(state, compute_uv=False)[0]) / T
        np.testing.assert_allclose(float(s.ftle), ftle, rtol=1e-9)
        offsets.append(T * (ftle - lam))
    assert 0 < offsets[0] < 1 and abs(offsets[1] - offsets[0]) < 1e-3 * offsets[0], offsets
    assert abs(float(s.ftle) - lam) < 0.05 * lam


def test_ftle_is_the_same_for_every_formulation_and_method():
    """The body momentum's Jacobian is read through each problem's own state:
    the spatial form (``m = R^T L``) and the variational equations give the
    FTLE of the body form's derivative, near the intermediate axis of a box
    under no torque, and of a heavy top (against RKMK(DOP853) at fine steps)."""
    w0 = np.array([0.05, 1.0, 0.1])
    options = dict(rtol=1e-11, atol=1e-11, estimate_error=False)
    ref = lierk.sensitivity(lierk.FreeRigidBody(BOX, w0), lierk.DOP853(), 8.0, **options)
    spatial = lierk.sensitivity(lierk.SpatialFreeRigidBody(BOX, w0), lierk.DOP853(), 8.0, **options)
    var = lierk.sensitivity(lierk.FreeRigidBody(BOX, w0), lierk.DOP853(), 8.0, method="variational", **options)
    for other in (spatial, var):
        np.testing.assert_allclose(float(other.ftle), float(ref.ftle), rtol=1e-7)
    top = lierk.RigidBodyWithEffects(
        [0.6, 0.8, 0.3],
        [1.0, -0.5, 10.0],
        lierk.so3.exp(jnp.asarray([0.3, 0.0, 0.0])),
        effects=(lierk.Gravity([0.02, 0.01, 0.5], 1.0, 9.81),),
    )
    fine = lierk.sensitivity(top, lierk.RKMK(lierk.tableaux.DOP853), 2.0, dt=0.002, estimate_error=False)
    adaptive = lierk.sensitivity(top, lierk.DOP853(), 2.0, method="variational", **options)
    np.testing.assert_allclose(float(adaptive.ftle), float(fine.ftle), rtol=1e-7)
    # and from the fine solve's own Jacobians, by the definition
    Omega = np.linalg.norm(top.omega0)
    state = np.vstack([Omega * np.asarray(fine.jacobian), np.asarray(top.inertia_inv) @ np.asarray(fine.jacobian_y)])
    np.testing.assert_allclose(float(fine.ftle), np.log(np.linalg.svd(state, compute_uv=False)[0]) / 2.0, rtol=1e-12)


def test_float32():
    w0 = np.array([0.3, 1.0, 0.2], np.float32)
    s = lierk.sensitivity(lierk.FreeRigidBody(BOX.astype(np.float32), w0), lierk.RKMK4(), 2.0, dt=0.02)
    assert s.jacobian.dtype == jnp.float32
    J = exact_jacobian(BOX, w0.astype(float), 2.0)
    err = np.linalg.norm(np.asarray(s.jacobian_R, float) - J) / np.linalg.norm(J)
    assert err < 1e-4
    assert np.isfinite(float(s.jacobian_R_error))


def test_bad_input_is_refused_with_a_reason():
    body = lierk.FreeRigidBody(BOX, [0.3, 1.0, 0.2])
    with pytest.raises(ValueError, match="target_error"):
        lierk.sensitivity(body, lierk.RKMK4(), 1.0, target_error=1e-6)
    with pytest.raises(ValueError, match="wrt must be one of"):
        lierk.sensitivity(body, lierk.RKMK4(), 1.0, dt=0.1, wrt="omega")
    with pytest.raises(ValueError, match="not an input"):
        lierk.sensitivity(body, lierk.RKMK4(), 1.0, dt=0.1, wrt=lambda p: p.omega0)
    # The inertia is read through fields derived from it: replaced alone, the
    # Jacobian was off by its own size.
    for field in ("inertia", "inertia_inv"):
        with pytest.raises(ValueError, match=f"selects the body's {field}, .* use wrt='inertia'"):
            lierk.sensitivity(body, lierk.RKMK4(), 1.0, dt=0.1, wrt=lambda p: getattr(p, field))
    with pytest.raises(ValueError, match="mode must be"):
        lierk.sensitivity(body, lierk.RKMK4(), 1.0, dt=0.1, mode="sideways")
    with pytest.raises(ValueError, match="saveat"):
        lierk.sensitivity(body, lierk.RKMK4(), 1.0, dt=0.1, saveat=lierk.SaveAt(steps=True))
    by_inertia = lierk.sensitivity(body, lierk.RKMK4(), 1.0, dt=0.1, wrt="inertia", estimate_error=False)
    assert by_inertia.ftle is None  # defined for omega0 only
    with pytest.raises(ValueError, match="lyapunov_exponent needs"), pytest.warns(DeprecationWarning):
        by_inertia.lyapunov_exponent


# Steady spins: about the symmetry axis of a symmetric body, about the major
# and minor axes of a box, and 1e-9 off the major one.
STEADY_SPINS = (
    ([1.0, 1.0, 1.9], [0.0, 0.0, 2.0]),
    ([1.0, 2.0, 3.0], [0.0, 0.0, 2.0]),
    ([1.0, 2.0, 3.0], [2.0, 0.0, 0.0]),
    ([1.0, 2.0, 3.0], [1e-9, 0.0, 2.0]),
)


@pytest.mark.parametrize("solver", [lierk.DP54(), lierk.DOP853()], ids=lambda s: s.name)
def test_derivatives_about_a_steady_spin_resolve_the_nutation(solver):
    """About a steady spin the state's error estimate is 0, so the steps grew
    to the turn bound, where the nutation of a perturbation (the tangent) is
    not resolved: DP54's Jacobian of a symmetric body (1, 1, 3) was 1e9 off,
    DOP853's 1.1, the box's 0.14 and 1e-3, all reported successful.  A differentiated
    adaptive solve (`jax.jacfwd` through `solve`, and `lierk.sensitivity`)
    resolves the mode, `AbstractRigidBody.mode_frequency`."""
    T, tol = 10.0, 1e-9
    inertia = jnp.asarray([np.diag(i) for i, _ in STEADY_SPINS])
    omega = jnp.asarray([w for _, w in STEADY_SPINS])

    def jac(I, w):
        return jax.jacfwd(
            lambda v: lierk.solve(lierk.FreeRigidBody(I, v), solver, T, rtol=tol, atol=tol, max_steps=20000).R[-1]
        )(w)

    J = np.asarray(jax.jit(jax.vmap(jac))(inertia, omega))
    s = jax.jit(
        jax.vmap(
            lambda I, w: lierk.sensitivity(
                lierk.FreeRigidBody(I, w), solver, T, rtol=tol, atol=tol, max_steps=20000, throw=False
            )
        )
    )(inertia, omega)
    assert np.all(np.asarray(s.result) == 0)
    for k, (I, w) in enumerate(STEADY_SPINS):
        J_exact = exact_jacobian(np.diag(I), w, T)
        scale = np.linalg.norm(J_exact)
        assert np.linalg.norm(J[k] - J_exact) < 1e-8 * scale, (I, w)
        err = np.linalg.norm(np.asarray(s.jacobian_R[k]) - J_exact)
        assert err < 1e-8 * scale, (I, w)
        # ... and the Jacobian's error estimate is not fooled either (the
        # finer solve used to take the same few steps).
        assert float(s.jacobian_R_error[k]) >= err / 100, (I, w, float(s.jacobian_R_error[k]), err)


def _impulse_response(I, k, c, T):
    """``theta(T)`` of ``I theta'' = -k theta - c theta'`` from ``theta(0) = 0``,
    ``theta'(0) = 1``: a damped (or, for k < 0, falling) oscillator."""
    from scipy.linalg import expm

    return expm(np.array([[0.0, 1.0], [-k / I, -c / I]]) * T)[0, 1]


def test_derivatives_at_rest_under_a_torque_resolve_its_modes():
    """A heavy top at rest at an equilibrium does not move, so its error
    estimate is 0 and the steps grew to the turn bound, while a perturbation
    swings as a pendulum (or falls, upright).  Before (DOP853, rtol 1e-9,
    T = 5 s): hanging, the Jacobian was 9.8 off on a scale of 7.1; upright,
    152 off on 1183, and `lierk.sensitivity` estimated its error as 0, all
    reported successful.  The effects' modes now bound the steps of a
    differentiated solve (`RigidBodyWithEffects.mode_frequency`).

    Exact: about the equilibrium the perturbation obeys, per principal axis,
    ``I_i theta'' = -k_i theta - c theta'`` with ``k = M g chi_z (1, 1, 0)``
    (the centre of mass on the z axis, ``chi_z < 0`` hanging), so the
    Jacobian in the algebra is ``diag(theta_i(T))`` for a unit kick."""
    T, tol, M, g = 5.0, 1e-9, 1.0, 9.81
    moments = np.array([2.0, 3.0, 1.5])
    cases = np.array([[-0.5, 0.0], [0.5, 0.0], [-0.5, 0.4]])  # (chi_z (m), damping c (N m s))

    def sensitivity(case):
        chi = jnp.stack([jnp.zeros(()), jnp.zeros(()), case[0]])
        top = lierk.RigidBodyWithEffects(
            moments, jnp.zeros(3), effects=(lierk.Gravity(chi, M, g), lierk.Damping(case[1]))
        )
        return lierk.sensitivity(top, lierk.DOP853(), T, rtol=tol, atol=tol, max_steps=20000)

    s = jax.jit(jax.vmap(sensitivity))(jnp.asarray(cases))
    assert np.all(np.asarray(s.result) == 0)
    for k, (chi_z, c) in enumerate(cases):
        stiffness = -M * g * chi_z * np.array([1.0, 1.0, 0.0])
        J_exact = np.diag([_impulse_response(moments[i], stiffness[i], c, T) for i in range(3)])
        err = np.linalg.norm(np.asarray(s.jacobian[k]) - J_exact)
        assert err < 1e-7 * np.linalg.norm(J_exact), (chi_z, c, err)
        assert float(s.jacobian_R_error[k]) >= err / 100, (chi_z, c, float(s.jacobian_R_error[k]), err)


def test_derivatives_at_rest_in_a_turning_field_resolve_its_turn():
    """A body at rest under B-dot in a polar orbit's dipole field (orbit rate
    1 rad/s) stays at rest, but the field, and so the linearised torque,
    turns with the orbit.  Before: one DOP853 step of
    the whole interval, the Jacobian 14.5% off (B-dot) with an error estimate
    of 0 (found by an adversarial pass).  The rate at which time turns the
    effects' linearisation now bounds a differentiated solve's steps."""
    T, tol = 10.0, 1e-9
    field = lierk.dipole_field(1.0, radius=lierk._problems.spacecraft.R_EARTH, tilt=np.pi / 2, B0=1.0)
    # (A nearly symmetric satellite at rest under the gravity gradient was
    # 2.7% off the same way; the same rate resolves it.)
    bodies = {
        "bdot": lierk.RigidBodyWithEffects(
            [1.0, 1.5, 2.0], np.zeros(3), effects=(lierk.MagneticTorque(field, bdot_gain=0.01),)
        ),
    }
    for name, body in bodies.items():
        s = lierk.sensitivity(body, lierk.DOP853(), T, rtol=tol, atol=tol, max_steps=20000)
        ref = lierk.sensitivity(body, lierk.RKMK4(), T, dt=0.005, estimate_error=False)
        err = np.linalg.norm(np.asarray(s.jacobian_R) - np.asarray(ref.jacobian_R))
        assert int(s.result) == 0 and err < 1e-6 * np.linalg.norm(np.asarray(ref.jacobian_R)), (name, err)
        assert float(s.jacobian_R_error) >= err / 100, (name, float(s.jacobian_R_error), err)


# Jitted: called eagerly, each operation of the bounds is a program of its own.
_mode_frequency = eqx.filter_jit(lambda body: body.mode_frequency(0.0, body.R0, body.y0))
_decay_rate = eqx.filter_jit(lambda body: body.decay_rate(0.0, body.R0, body.y0))


def test_mode_frequency_counts_the_effects_modes():
    """A pendulum's frequency ``sqrt(M g l / I)``, a wheel's ``|h| / I``, a
    damper's decay rate ``c / I``: each bound is at least the true value and
    at most 1.35x (the swing) or sqrt(3)x (Frobenius norms) it."""
    I = np.array([2.0, 3.0, 1.5])
    hanging = lierk.RigidBodyWithEffects(I, [0.0, 0.0, 0.0], effects=(lierk.Gravity([0.0, 0.0, -0.5], 1.0, 9.81),))
    fastest = np.sqrt(9.81 * 0.5 / I[0])  # the swing about x, the smallest moment across the arm
    rho = float(_mode_frequency(hanging))
    assert fastest <= rho <= 1.35 * fastest, (rho, fastest)
    # A damper's decay is a rate the steps keep stable, not a phase: c = 100
    # made a differentiated DP54 solve take 57x the steps of the plain one.
    damped = lierk.RigidBodyWithEffects(I, [0.0, 0.0, 0.0], effects=(lierk.Damping(0.6),))
    assert float(_mode_frequency(damped)) == 0.0
    rate = float(_decay_rate(damped))
    assert 0.6 / I[2] <= rate <= np.sqrt(3.0) * 0.6 / I[2], rate
    # A wheel's coupling turns perturbations: |h| / I about its axis.
    wheel = lierk.RigidBodyWithEffects([2.0, 2.0, 1.0], [0.0, 0.0, 0.0], effects=(lierk.Rotor([0.0, 0.0, 3.0]),))
    assert 3.0 / 2.0 <= float(_mode_frequency(wheel)) <= np.sqrt(3.0) * 3.0 / 2.0
    # Effects that do not act add nothing: a free body's nutation is unchanged.
    spin = lierk.RigidBodyWithEffects(I, [0.0, 0.0, 2.0], effects=(lierk.Damping(0.0),))
    free = lierk.FreeRigidBody(I, [0.0, 0.0, 2.0])
    np.testing.assert_allclose(float(_mode_frequency(spin)), float(_mode_frequency(free)), rtol=1e-12)


def test_the_free_bodys_mode_frequency_is_sqrt_c2_and_the_nutation_at_a_steady_spin():
    """The torque-free part, written out by entries, against NumPy's
    ``sqrt(|c2|)`` of ``J = hat(m) I^-1 - hat(omega)`` for bodies with full
    (rotated) and diagonal inertia; at a steady spin about each principal
    axis, against the eigenvalues of ``J`` and the nutation ``omega
    sqrt((I_k - I_i)(I_k - I_j)/(I_i I_j))`` (growth about the intermediate
    one); a sphere's 0 exactly."""
    rng = np.random.default_rng(7)
    cases = []
    for _ in range(4):
        Q = np.linalg.qr(rng.normal(size=(3, 3)))[0]
        cases.append((Q @ np.diag(rng.uniform(1.0, 2.0, 3)) @ Q.T, rng.normal(size=3)))
    moments = np.array([1.0, 2.0, 2.5])
    cases += [(np.diag(moments), 2.0 * np.eye(3)[k]) for k in range(3)]
    for inertia, omega in cases:
        rho = float(_mode_frequency(lierk.FreeRigidBody(inertia, omega)))
        m, w = inertia @ omega, omega
        J = np.asarray(lierk.so3.hat(m)) @ np.linalg.inv(inertia) - np.asarray(lierk.so3.hat(w))
        c2 = sum(J[i, i] * J[j, j] - J[i, j] * J[j, i] for i, j in ((0, 1), (0, 2), (1, 2)))
        np.testing.assert_allclose(rho, np.sqrt(abs(c2)), rtol=1e-12)
        if np.linalg.norm(np.cross(m, w)) < 1e-12 * np.linalg.norm(m) * np.linalg.norm(w):  # a steady spin
            np.testing.assert_allclose(rho, np.max(np.abs(np.linalg.eigvals(J))), rtol=1e-12)
    for k in range(3):
        i, j = [x for x in range(3) if x != k]
        nutation = 2.0 * np.sqrt(abs((moments[k] - moments[i]) * (moments[k] - moments[j])) / (moments[i] * moments[j]))
        np.testing.assert_allclose(
            float(_mode_frequency(lierk.FreeRigidBody(moments, 2.0 * np.eye(3)[k]))), nutation, rtol=1e-13
        )
    assert float(_mode_frequency(lierk.FreeRigidBody([2.0, 2.0, 2.0], [0.3, -1.0, 7.0]))) == 0.0


@pytest.mark.parametrize("which", ["top", "spacecraft"])
def test_effects_linearisation_is_the_torques_derivative(which):
    """The mode bounds' linearisation (`RigidBodyWithEffects._effects_linearisation`,
    which turns the point to first order) against central differences of the
    field at attitudes ``R exp(hat(eps e_i))`` and momenta ``m + eps e_i``: a
    gravity vector, and a spacecraft whose effects read the whole attitude
    (a magnetic dipole in a turning field, gravity gradient, a rotor)."""
    I = np.array([2.0, 3.0, 1.5])
    if which == "top":
        effects = (lierk.Gravity([0.1, -0.2, 0.5], 1.0, 9.81),)
    else:
        field = lierk.dipole_field(0.0011, tilt=1.2)
        effects = (
            lierk.GravityGradient(I, mean_motion=0.0011),
            lierk.MagneticTorque(field, dipole=[0.3, -0.1, 0.2]),
            lierk.Rotor([0.0, 0.5, 0.1]),
        )
    R = np.asarray(lierk.so3.exp(np.array([0.4, -1.1, 0.7])))
    body = lierk.RigidBodyWithEffects(I, [0.3, -0.2, 0.9], R, effects=effects)
    t, m = 7.0, np.asarray(body.y0)
    IK_u, K_m, _ = eqx.filter_jit(lambda b: b._effects_linearisation(t, b.R0, b.y0))(body)
    field = jax.jit(lambda R, m: body.field(t, R, m)[1] - lierk.so3.cross(m, body.inertia_inv @ m))
    eps = 1e-6
    du = np.stack(
        [
            (
                np.asarray(field(R @ np.asarray(lierk.so3.exp(eps * e)), m))
                - np.asarray(field(R @ np.asarray(lierk.so3.exp(-eps * e)), m))
            )
            / (2 * eps)
            for e in np.eye(3)
        ],
        -1,
    )
    dm = np.stack(
        [(np.asarray(field(R, m + eps * e)) - np.asarray(field(R, m - eps * e))) / (2 * eps) for e in np.eye(3)], -1
    )
    # A central difference of a field that is a difference of O(|m| |omega|)
    # terms carries their rounding divided by eps (about 1e-10 here): where a
    # derivative is 0 (the top's K_m), that and not |dm| sets the tolerance.
    rounding = (
        100
        * np.finfo(float).eps
        * (np.abs(m).max() * np.abs(body.inertia_inv @ m).max() + np.abs(field(R, m)).max())
        / eps
    )
    np.testing.assert_allclose(
        np.asarray(IK_u), np.linalg.inv(np.diag(I)) @ du, rtol=1e-6, atol=max(1e-5 * np.abs(du).max(), rounding)
    )
    np.testing.assert_allclose(np.asarray(K_m), dm, rtol=1e-6, atol=max(1e-5 * np.abs(dm).max(), rounding))
    assert np.abs(du).max() > 0


def test_mode_frequency_is_the_nutation_frequency():
    """``omega_k sqrt(|(I_k - I_i)(I_k - I_j)|/(I_i I_j))`` for a spin about
    principal axis k (real growth about the intermediate one), 0 for a sphere
    and at rest."""
    I = np.array([1.0, 2.0, 3.0])
    for k in range(3):
        i, j = [a for a in range(3) if a != k]
        w = np.zeros(3)
        w[k] = 1.7
        body = lierk.FreeRigidBody(I, w)
        expected = 1.7 * np.sqrt(abs((I[k] - I[i]) * (I[k] - I[j])) / (I[i] * I[j]))
        np.testing.assert_allclose(float(_mode_frequency(body)), expected, rtol=1e-12)
    sphere = lierk.FreeRigidBody([2.0, 2.0, 2.0], [0.3, -1.0, 2.0])
    assert float(_mode_frequency(sphere)) == 0.0
    rest = lierk.FreeRigidBody(I, [0.0, 0.0, 0.0])
    assert float(_mode_frequency(rest)) == 0.0
    with pytest.raises(ValueError, match="resolve_modes must be True or False"):
        lierk.Controller(1e-6, resolve_modes="yes")


# --- method="variational": the variational equations integrated with the body ---


def test_variational_jacobian_has_the_solvers_order():
    """The exact flow's Jacobian to the solver's order: RKMK4 on a near-axis
    T-handle, fitted slope within 0.15 of 4, and the Richardson estimate
    within [1/2, 2] of the true error.  (Not the derivative of the solve:
    at the same step the two differ by their own errors.)"""
    w0, T = [1.0, 0.05, 0.3], 5.0
    J = exact_jacobian(TEE, w0, T)
    run = jax.jit(
        lambda dt: lierk.sensitivity(
            lierk.FreeRigidBody(TEE, w0), lierk.RKMK4(), T, dt=dt, max_steps=500, method="variational"
        )
    )
    dts = [0.04, 0.02, 0.01]
    errs, ests = [], []
    for dt in dts:
        s = run(dt)
        assert int(s.result) == 0
        errs.append(np.linalg.norm(np.asarray(s.jacobian_R) - J))
        ests.append(float(s.jacobian_R_error))
    assert abs(order_fit(dts, errs) - 4.0) < 0.15, errs
    for err, est in zip(errs, ests):
        assert err / 2 <= est <= 2 * err, (err, est)
    derivative = lierk.sensitivity(lierk.FreeRigidBody(TEE, w0), lierk.RKMK4(), T, dt=0.01, estimate_error=False)
    assert np.linalg.norm(np.asarray(derivative.jacobian_R) - np.asarray(s.jacobian_R)) > 1e-3 * errs[-1]


@pytest.mark.parametrize("wrt", ["omega0", "R0"])
def test_variational_agrees_with_the_derivative_on_a_heavy_top(wrt):
    """Both converge to the exact flow's Jacobian: on an asymmetric heavy top
    spinning at 40 rad/s they agree to their errors (~1e-12 at 200 RKMK(DOP853)
    steps), the momentum's Jacobian too; adaptive DOP853 with the variational
    equations under error control lands within its tolerance and says so."""
    R0 = lierk.so3.exp(jnp.asarray([0.3, 0.0, 0.0]))
    top = lierk.RigidBodyWithEffects(
        [0.6, 0.8, 0.3], [1.0, -0.5, 40.0], R0, effects=(lierk.Gravity([0.02, 0.01, 0.5], 1.0, 9.81),)
    )
    dop = lierk.RKMK(lierk.tableaux.DOP853)
    ref = lierk.sensitivity(top, dop, 0.5, wrt=wrt, dt=0.0025, estimate_error=False)
    var = lierk.sensitivity(top, dop, 0.5, wrt=wrt, dt=0.0025, method="variational", estimate_error=False)
    scale, scale_y = np.linalg.norm(np.asarray(ref.jacobian_R)), np.linalg.norm(np.asarray(ref.jacobian_y))
    assert np.linalg.norm(np.asarray(var.jacobian_R) - np.asarray(ref.jacobian_R)) < 1e-10 * scale
    assert np.linalg.norm(np.asarray(var.jacobian_y) - np.asarray(ref.jacobian_y)) < 1e-10 * scale_y
    np.testing.assert_allclose(np.asarray(var.R), np.asarray(ref.R), atol=1e-12)
    s = lierk.sensitivity(top, lierk.DOP853(), 0.5, wrt=wrt, rtol=1e-10, atol=1e-10, method="variational")
    err = np.linalg.norm(np.asarray(s.jacobian_R) - np.asarray(ref.jacobian_R))
    assert err < 1e-8 * scale, err / scale
    assert err / 10 <= float(s.jacobian_R_error) <= 10 * err + 1e-12 * scale, (err, float(s.jacobian_R_error))
    for got, want, bar in (
        (s.jacobian, ref.jacobian, s.jacobian_error),
        (s.jacobian_y, ref.jacobian_y, s.jacobian_y_error),
    ):
        err = np.linalg.norm(np.asarray(got) - np.asarray(want))
        assert err / 10 <= float(bar) <= 10 * err + 1e-12 * np.linalg.norm(np.asarray(want)), (err, float(bar))


def test_variational_error_control_resolves_steady_spins_and_rest():
    """The cases where the state does not move, so its own error estimate is
    0 (`test_derivatives_about_a_steady_spin_resolve_the_nutation`, ..._at_rest_under_a_torque_...):
    with method="variational" the derivatives are under the error control
    themselves, and their nutation or swing sets the steps without a mode
    bound.  Against the exact Jacobians, within 1e-8 at rtol 1e-9."""
    T, tol = 10.0, 1e-9
    inertia = jnp.asarray([np.diag(i) for i, _ in STEADY_SPINS])
    omega = jnp.asarray([w for _, w in STEADY_SPINS])
    s = jax.jit(
        jax.vmap(
            lambda I, w: lierk.sensitivity(
                lierk.FreeRigidBody(I, w), lierk.DOP853(), T, rtol=tol, atol=tol, max_steps=20000, method="variational"
            )
        )
    )(inertia, omega)
    for k, (I, w) in enumerate(STEADY_SPINS):
        J_exact = exact_jacobian(np.diag(I), w, T)
        err = np.linalg.norm(np.asarray(s.jacobian_R[k]) - J_exact)
        assert err < 1e-8 * np.linalg.norm(J_exact), (I, w, err)
        assert float(s.jacobian_R_error[k]) >= err / 100, (I, w, float(s.jacobian_R_error[k]), err)
    # At rest a small perturbation turns the body steadily: J = T I exactly.
    rest = lierk.sensitivity(
        lierk.FreeRigidBody(BOX, [0.0, 0.0, 0.0]), lierk.RKMK4(), 2.0, dt=0.05, method="variational"
    )
    np.testing.assert_allclose(np.asarray(rest.jacobian), 2.0 * np.eye(3), atol=1e-12)
    # A heavy top at rest, hanging, upright and damped: damped oscillators per axis.
    M, g, moments = 1.0, 9.81, np.array([2.0, 3.0, 1.5])
    for chi_z, c in [(-0.5, 0.0), (0.5, 0.0), (-0.5, 0.4)]:
        top = lierk.RigidBodyWithEffects(
            moments, np.zeros(3), effects=(lierk.Gravity([0.0, 0.0, chi_z], M, g), lierk.Damping(c))
        )
        st = lierk.sensitivity(top, lierk.DOP853(), 5.0, rtol=tol, atol=tol, max_steps=20000, method="variational")
        stiffness = -M * g * chi_z * np.array([1.0, 1.0, 0.0])
        J_exact = np.diag([_impulse_response(moments[i], stiffness[i], c, 5.0) for i in range(3)])
        err = np.linalg.norm(np.asarray(st.jacobian) - J_exact)
        assert err < 1e-7 * np.linalg.norm(J_exact), (chi_z, c, err)


def test_variational_in_float32():
    w0 = np.array([0.3, 1.0, 0.2], np.float32)
    s = lierk.sensitivity(
        lierk.FreeRigidBody(BOX.astype(np.float32), w0), lierk.RKMK4(), 2.0, dt=0.02, method="variational"
    )
    assert s.jacobian.dtype == jnp.float32 and s.jacobian_y.dtype == jnp.float32
    J = exact_jacobian(BOX, w0.astype(float), 2.0)
    assert np.linalg.norm(np.asarray(s.jacobian_R, float) - J) < 1e-4 * np.linalg.norm(J)
    assert np.isfinite(float(s.jacobian_R_error))


def test_variational_refuses_what_it_does_not_cover():
    body = lierk.FreeRigidBody(BOX, [0.3, 1.0, 0.2])
    with pytest.raises(ValueError, match="method must be 'derivative', 'variational' or 'auto', got 'adjoint'"):
        lierk.sensitivity(body, lierk.RKMK4(), 1.0, dt=0.1, method="adjoint")
    with pytest.raises(ValueError, match="covers wrt='omega0' and wrt='R0', got 'inertia'"):
        lierk.sensitivity(body, lierk.RKMK4(), 1.0, dt=0.1, wrt="inertia", method="variational")
    with pytest.raises(ValueError, match="not the splitting Strang"):
        lierk.sensitivity(body, lierk.Strang(), 1.0, dt=0.1, method="variational")
    with pytest.raises(ValueError, match="leave mode='forward'"):
        lierk.sensitivity(body, lierk.RKMK4(), 1.0, dt=0.1, mode="reverse", method="variational")
    with pytest.raises(ValueError, match="got SpatialFreeRigidBody"):
        lierk.sensitivity(
            lierk.SpatialFreeRigidBody(BOX, [0.3, 1.0, 0.2]), lierk.RKMK4(), 1.0, dt=0.1, method="variational"
        )


def test_auto_takes_the_variational_equations_where_they_apply():
    body = lierk.FreeRigidBody(BOX, [0.3, 1.0, 0.2])
    assert lierk.sensitivity_method(body, lierk.RKMK4()) == "variational"
    for solver, wrt, mode in (
        (lierk.Strang(), "omega0", "forward"),
        (lierk.RKMK4(), "inertia", "forward"),
        (lierk.RKMK4(), "omega0", "reverse"),
    ):
        assert lierk.sensitivity_method(body, solver, wrt, mode) == "derivative"
    assert lierk.sensitivity_method(body, lierk.Strang(), method="derivative") == "derivative"
    auto = lierk.sensitivity(body, lierk.RKMK4(), 1.0, dt=0.1, method="auto", estimate_error=False)
    var = lierk.sensitivity(body, lierk.RKMK4(), 1.0, dt=0.1, method="variational", estimate_error=False)
    der = lierk.sensitivity(body, lierk.RKMK4(), 1.0, dt=0.1, estimate_error=False)
    np.testing.assert_array_equal(np.asarray(auto.jacobian), np.asarray(var.jacobian))
    # The two methods differ by the step's truncation error, so they can be told apart.
    assert np.max(np.abs(np.asarray(var.jacobian) - np.asarray(der.jacobian))) > 1e-9
    split = lierk.sensitivity(body, lierk.Strang(), 1.0, dt=0.1, method="auto", estimate_error=False)
    np.testing.assert_array_equal(
        np.asarray(split.jacobian),
        np.asarray(lierk.sensitivity(body, lierk.Strang(), 1.0, dt=0.1, estimate_error=False).jacobian),
    )


@pytest.mark.parametrize(
    "method, mode", [("derivative", "forward"), ("derivative", "reverse"), ("variational", "forward")]
)
def test_a_derivative_of_the_jacobian_is_that_of_the_function(method, mode):
    """jacfwd of a sensitivity's Jacobian (a loss on the sensitivity, say)
    against finite differences of the same function.  The derivative method
    formed the body-frame tangent as the derivative of log(stop_gradient(R)^T R):
    the right Jacobian, but its own derivative lost the dR^T dR term, 37% off
    for jacobian_R and 83% for jacobian, with no sign (an adversarial pass)."""
    body = lierk.FreeRigidBody(BOX, [0.3, 1.0, 0.2])

    def f(w):
        s = lierk.sensitivity(
            body.with_omega0(w), lierk.RKMK4(), 1.0, dt=0.05, method=method, mode=mode, estimate_error=False
        )
        return jnp.concatenate([s.jacobian_R.ravel(), s.jacobian.ravel()])

    w0 = np.asarray(body.omega0)
    H = np.asarray(jax.jit(jax.jacfwd(f))(jnp.asarray(w0)))
    fd = fd_jacobian(jax.jit(f), w0, h=1e-3)
    assert np.linalg.norm(H - fd) < 1e-7 * np.linalg.norm(fd), np.linalg.norm(H - fd) / np.linalg.norm(fd)


def test_variational_resolves_a_sleeping_top():
    """A top spinning fast about its axis under gravity does not move, so the
    mode bounds leave its derivative's nutation unresolved (the derivative of
    DOP853's solve: 8.6e-7 relative at rtol 1e-9).  The variational
    equations are under the error control themselves."""
    top = lierk.RigidBodyWithEffects(
        [1.0, 1.0, 1.0], [0.0, 0.0, 100.0], effects=(lierk.Gravity([0.0, 0.0, 1.0], 1.0, 9.81),)
    )
    ref = lierk.sensitivity(top, lierk.RKMK(lierk.tableaux.DOP853), 1.0, dt=1.0 / 4000, estimate_error=False)
    s = lierk.sensitivity(top, lierk.DOP853(), 1.0, rtol=1e-9, atol=1e-9, max_steps=20000, method="variational")
    scale = np.linalg.norm(np.asarray(ref.jacobian_R))
    err = np.linalg.norm(np.asarray(s.jacobian_R) - np.asarray(ref.jacobian_R))
    assert int(s.result) == 0 and err < 1e-7 * scale, err / scale
    assert err / 10 <= float(s.jacobian_R_error) <= 10 * err, (err, float(s.jacobian_R_error))


def test_the_mode_bounds_of_a_differentiated_solve_can_be_turned_off():
    """A differentiated adaptive solve takes extra steps about a steady spin
    (the mode bounds) unless its adjoint says ``resolve_modes=False``: then
    its value is the undifferentiated solve's, bit for bit, with the same
    steps, and its derivative is that solve's (against central
    differences)."""
    I = np.diag([1.0, 1.0, 2.0])
    w = np.array([1e-3, 0.0, 5.0])

    def run(v, adjoint=None):
        sol = lierk.solve(lierk.FreeRigidBody(I, v), lierk.DP54(), 2.0, rtol=1e-6, atol=1e-6, adjoint=adjoint)
        return sol.R[-1], sol.stats["num_steps"]

    R_plain, steps_plain = jax.jit(run)(w)
    off = lierk.ForwardSensitivity(resolve_modes=False)
    (R_off, steps_off), (dR_off, _) = jax.jit(
        lambda v: jax.jvp(lambda u: run(u, off), (v,), (np.array([0.0, 1.0, 0.0]),))
    )(w)
    (R_on, steps_on), _ = jax.jit(lambda v: jax.jvp(run, (v,), (np.array([0.0, 1.0, 0.0]),)))(w)
    np.testing.assert_array_equal(np.asarray(R_off), np.asarray(R_plain))
    assert int(steps_off) == int(steps_plain) < int(steps_on)
    h = 1e-6
    fd = (np.asarray(jax.jit(run)(w + [0.0, h, 0.0])[0]) - np.asarray(jax.jit(run)(w - [0.0, h, 0.0])[0])) / (2 * h)
    np.testing.assert_allclose(np.asarray(dR_off), fd, atol=1e-5)
    with pytest.raises(ValueError, match="resolve_modes"):
        lierk.ForwardSensitivity(resolve_modes=1)
