"""`ForwardSensitivity`, the default adjoint: every autodiff mode reads one
forward pass of tangents, and gets the derivative of the solve that was run.

Each claim is checked against an independent number: forward mode through
the plain loop (`ForwardMode`, which adds nothing to the solve), central
finite differences, or the exact flow's derivative."""

import functools
import types
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import OMEGA_GENERIC, TEE, fd_from_values, fd_jacobian, fd_points

import lierk

W0 = jnp.asarray(OMEGA_GENERIC)
TARGET = jnp.asarray(np.asarray(lierk.so3.exp(jnp.asarray([0.2, -0.1, 0.4]))))

# (solver, solve options): fixed steps through the scan, a splitting with the
# elliptic drift, an adaptive pair through the while loop.
CASES = {
    "RKMK4": (lierk.RKMK4(), dict(dt=0.05)),
    "Strang": (lierk.Strang(), dict(dt=0.1)),
    "DP54": (lierk.DP54(), dict(rtol=1e-9, atol=1e-9)),
}


def final(w, solver, adjoint=None, **kw):
    return lierk.solve(lierk.FreeRigidBody(TEE, w), solver, 2.0, adjoint=adjoint, **kw).R[-1]


def loss(w, *args, **kw):
    return jnp.sum((final(w, *args, **kw) - TARGET) ** 2)


@pytest.mark.parametrize("name", list(CASES))
def test_every_mode_reads_the_derivative_of_the_solve(name):
    solver, kw = CASES[name]
    # The reference: forward mode through the loop itself, one tangent pass,
    # of the solve a differentiated adaptive solve runs (its controller
    # resolves the body's perturbation modes).
    ref_kw = kw if "dt" in kw else {"controller": lierk.Controller(kw["rtol"], kw["atol"], resolve_modes=True)}
    reference = lambda w: final(w, solver, lierk.ForwardMode(), **ref_kw)  # noqa: E731
    # Every mode in one program: compiled apart they cost a third more (the
    # splitting's elliptic-drift derivatives dominate the module's time).
    J_ref, J_fwd, J_rev, g, R_ref, R_fd = jax.jit(
        lambda w: (
            jax.jacfwd(reference)(w),
            jax.jacfwd(lambda w: final(w, solver, **kw))(w),
            jax.jacrev(lambda w: final(w, solver, **kw))(w),
            jax.grad(lambda w: loss(w, solver, **kw))(w),
            reference(w),
            jax.vmap(reference)(jnp.asarray(fd_points(W0))),
        )
    )(W0)
    scale = float(jnp.linalg.norm(J_ref))
    g_ref = jnp.einsum("ij,ijk->k", 2 * (R_ref - TARGET), J_ref)
    assert float(jnp.linalg.norm(J_fwd - J_ref)) <= 1e-12 * scale
    assert float(jnp.linalg.norm(J_rev - J_ref)) <= 1e-12 * scale
    assert float(jnp.linalg.norm(g - g_ref)) <= 1e-12 * float(jnp.linalg.norm(g_ref))
    # ... and that is the Jacobian of the solve, not of some other computation.
    J_fd = fd_from_values(R_fd)
    assert float(jnp.linalg.norm(J_fwd - J_fd)) <= 1e-6 * scale


def test_gradient_under_vmap_matches_a_loop():
    solver, kw = CASES["RKMK4"]
    ws = jnp.asarray(OMEGA_GENERIC) * jnp.asarray([[1.0], [1.3], [0.7]])
    grad = jax.jit(jax.grad(lambda w: loss(w, solver, **kw)))
    batched = jax.jit(jax.vmap(jax.grad(lambda w: loss(w, solver, **kw))))(ws)
    for i in range(ws.shape[0]):
        np.testing.assert_allclose(batched[i], grad(ws[i]), rtol=1e-13, atol=1e-15)


def test_adaptive_gradient_does_not_depend_on_max_steps():
    """No checkpoint replays a step: the same gradient with room for 300 or
    5000 attempts, at a tolerance where the checkpointed adjoint's replay
    once drifted (issue 22's case)."""
    body = lambda w: lierk.FreeRigidBody(lierk.inertia.tee_handle(), w)  # noqa: E731
    w = jnp.asarray([0.9, 0.07, 0.2])

    def g(max_steps):
        f = lambda w: jnp.sum(  # noqa: E731
            (lierk.solve(body(w), lierk.DP54(), 2.5, rtol=1e-11, atol=1e-11, max_steps=max_steps).R[-1] - TARGET) ** 2
        )
        return jax.jit(jax.grad(f))(w)

    a, b = g(300), g(5000)
    np.testing.assert_allclose(a, b, rtol=1e-13, atol=0)


def grad_temp_bytes(n_steps):
    def g(w):
        return jax.grad(lambda w: loss(w, lierk.RKMK4(), dt=2.0 / n_steps))(w)

    return jax.jit(g).lower(W0).compile().memory_analysis().temp_size_in_bytes


def test_reverse_mode_memory_does_not_grow_with_steps():
    """The tangents ride in the scan's carry: no state is stored per step or
    per block, so 10^6 steps need what 10^4 need (reverse mode through the
    scan keeps sqrt(10^6) = 1000 block-start states, 96 kB).  (Both runs
    are long enough to skip blocks past their end, `lierk._loops`: a
    shorter one's program has no conditional, and 1.4 kB less.)"""
    small, large = grad_temp_bytes(10**4), grad_temp_bytes(10**6)
    assert large <= small + 1024
    assert large < 16 * 1024


def test_inputs_without_a_derivative_are_not_counted():
    """Differentiating in omega0 perturbs the body's momentum only (3
    scalars): the attitude, inertia and its inverse carry no tangent."""
    solver, kw = CASES["DP54"]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        jax.grad(lambda w: loss(w, solver, lierk.ForwardSensitivity(max_inputs=3), **kw))(W0)
    with pytest.warns(UserWarning, match="3 input scalars, more than ForwardSensitivity's max_inputs=2"):
        jax.grad(lambda w: loss(w, solver, lierk.ForwardSensitivity(max_inputs=2), **kw))(W0)


@pytest.mark.parametrize("name", ["RKMK4", "DP54"])
def test_beyond_max_inputs_the_fallback_gives_the_same_derivative(name):
    solver, kw = CASES[name]
    few = lierk.ForwardSensitivity(max_inputs=2)
    g_ref = jax.grad(lambda w: loss(w, solver, **kw))(W0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        g = jax.grad(lambda w: loss(w, solver, few, **kw))(W0)
        J = jax.jacfwd(lambda w: final(w, solver, few, **kw))(W0)
    np.testing.assert_allclose(g, g_ref, rtol=1e-11)
    J_ref = jax.jacfwd(lambda w: final(w, solver, **kw))(W0)
    np.testing.assert_allclose(J, J_ref, rtol=1e-11, atol=1e-14)


def test_gradient_with_respect_to_the_inertia_against_finite_differences():
    """21 perturbed scalars (inertia, its inverse, the momentum): fixed steps
    go through the scan's own reverse mode, adaptive ones carry them all."""

    def f(moments, solver, **kw):
        body = lierk.FreeRigidBody(jnp.diag(moments), W0)
        return jnp.sum((lierk.solve(body, solver, 2.0, **kw).R[-1] - TARGET) ** 2)

    moments = jnp.asarray(np.diag(TEE))
    for solver, kw in (CASES["RKMK4"], CASES["DP54"]):
        g = jax.grad(lambda m: f(m, solver, **kw))(moments)
        fd = fd_jacobian(jax.jit(lambda m: f(m, solver, adjoint=lierk.ForwardMode(), **kw)), moments, h=1e-8)
        np.testing.assert_allclose(g, fd, rtol=1e-6)


def test_float32_gradient():
    solver, kw = CASES["RKMK4"]
    w32 = W0.astype(jnp.float32)
    g = jax.grad(
        lambda w: jnp.sum(
            (
                lierk.solve(lierk.FreeRigidBody(TEE.astype(np.float32), w), solver, 2.0, **kw).R[-1]
                - TARGET.astype(jnp.float32)
            )
            ** 2
        )
    )(w32)
    assert g.dtype == jnp.float32
    np.testing.assert_allclose(g, jax.grad(lambda w: loss(w, solver, **kw))(W0), rtol=2e-4)


@pytest.mark.parametrize(
    "kw, match",
    [
        (dict(max_inputs=0), "positive int"),
        (dict(fallback=lierk.RecursiveCheckpointAdjoint()), "must support forward mode"),
    ],
)
def test_bad_settings_are_refused(kw, match):
    with pytest.raises(ValueError, match=match):
        lierk.ForwardSensitivity(**kw)


def test_values_a_user_function_closes_over_are_differentiated():
    """A torque profile or an event condition written as a closure over the
    value being differentiated (the review's case: UnexpectedTracerError)."""
    I = np.diag([2.0, 3.0, 4.0])

    def torque_loss(a, solver, **kw):
        eff = lierk.TimedTorque(lambda t: a * jnp.array([0.0, 0.0, 1.0]) * jnp.cos(t))
        return lierk.solve(lierk.RigidBodyWithEffects(I, W0, effects=(eff,)), solver, 2.0, **kw).R[-1, 0, 1]

    for solver, kw in (CASES["RKMK4"], CASES["DP54"]):
        g = jax.grad(lambda a: torque_loss(a, solver, **kw))(0.3)
        g_jit = jax.jit(jax.grad(lambda a: torque_loss(a, solver, **kw)))(0.3)
        # Jitted: a closure over a concrete value is a constant of the
        # program, so each difference point would otherwise compile anew.
        fd = fd_jacobian(
            jax.jit(lambda a: torque_loss(a[0], solver, adjoint=lierk.ForwardMode(), **kw)), jnp.array([0.3]), h=1e-4
        )
        np.testing.assert_allclose([g, g_jit], [fd[0], fd[0]], rtol=1e-7)

    def event_time(c):
        ev = lierk.Event(lambda t, R, y: R[2, 2] - c, terminate=True)
        body = lierk.FreeRigidBody(I, W0, lierk.so3.exp(jnp.array([0.2, 0.1, 0.0])))
        return lierk.solve(body, lierk.DOP853(), 20.0, rtol=1e-12, atol=1e-12, event=ev).ts[-1]

    fd = fd_jacobian(jax.jit(lambda c: event_time(c[0])), jnp.array([0.9]), h=1e-4)
    np.testing.assert_allclose(jax.grad(event_time)(0.9), fd[0], rtol=1e-7)


def test_a_function_closing_over_plain_numbers_traces_the_loop_once():
    """Closure conversion (what the test above needs) traces each of the
    primal, fallback and derivative loops once more; a function that closes
    over no traced value (a spacecraft scene's field, built from numbers)
    skips it.  Counted by the torque's traces, under `jax.jit` as a user
    calls it: the count is the same as for a torque with no closure at all."""
    I = np.diag([2.0, 3.0, 4.0])
    calls = [0]  # a count, not the traced times: a list of tracers would be a captured tracer

    def traces(make_torque, *args):
        calls[0] = 0

        def final_R(w, *args):
            eff = lierk.TimedTorque(make_torque(*args))
            return lierk.solve(lierk.RigidBodyWithEffects(I, w, effects=(eff,)), lierk.DP54(), 1.0, rtol=1e-6).R[-1]

        jax.jit(final_R).lower(W0, *args)
        return calls[0]

    def plain(t):
        calls[0] += 1
        return jnp.array([0.0, 0.0, 0.3]) * jnp.cos(t)

    def closing_over(a):
        def torque(t):
            calls[0] += 1
            return a * jnp.array([0.0, 0.0, 1.0]) * jnp.cos(t)

        return torque

    n_plain = traces(lambda: plain)
    assert n_plain > 0
    assert traces(lambda: closing_over(0.3)) == n_plain
    assert traces(lambda: closing_over(np.float64(0.3))) == n_plain
    # Closing over the traced argument: converted, so traced more often.
    assert traces(closing_over, jnp.asarray(0.3)) > n_plain


class _Height(eqx.Module):
    c: float

    def __call__(self, t, R, y):
        return R[2, 2] - self.c


def test_an_event_condition_written_as_a_function_traces_the_loop_once():
    """`lierk.solve` closure-converts an event's condition; what conversion
    leaves (shapes and dtypes, in static fields) holds no traced value, so
    the loops are not converted again: a condition written as a plain
    function traces them as often as the same condition written as a
    module.  Counted by the torque's traces under `jax.jit`."""
    I = np.diag([2.0, 3.0, 4.0])
    calls = [0]

    def torque(t):
        calls[0] += 1
        return jnp.array([0.0, 0.0, 0.3]) * jnp.cos(t)

    def traces(event):
        calls[0] = 0

        def final_R(w):
            body = lierk.RigidBodyWithEffects(I, w, effects=(lierk.TimedTorque(torque),))
            return lierk.solve(body, lierk.DP54(), 1.0, rtol=1e-6, event=event).R[-1]

        jax.jit(final_R).lower(W0)
        return calls[0]

    traces(lierk.Event(_Height(0.5)))  # the first solve traces a helper once more
    module = traces(lierk.Event(_Height(0.9)))
    assert module > 0
    assert traces(lierk.Event(lambda t, R, y: R[2, 2] - 0.9)) == module


def test_captured_tracers_are_found_wherever_a_function_keeps_them():
    from lierk._adjoint import _may_capture_tracer

    class Holder:  # a user's plain object, not a pytree
        def __init__(self, value):
            self.value = value

    found = {}

    def check(x):
        cases = {
            "closure": (lambda: lambda t: x * t)(),
            "default": lambda t, a=x: a * t,
            "partial": functools.partial(lambda a, t: a * t, x),
            "keyword": functools.partial(lambda t, a: a * t, a=x),
            "nested": (lambda: lambda t: [{"k": (x,)}][0]["k"][0] * t)(),
            "object": (lambda h: lambda t: h.value * t)(Holder(x)),
            "module": (lambda eff: lambda t: eff.c * t)(lierk.Damping(x)),
            "method": Holder(x).__init__,
            "callable object": _Gain(x),
            "method reading a global": (lambda g: lambda t: g.from_global(t))(_Gain(None)),
            "class attribute": (lambda c: lambda t: c.gain * t)(type("Params", (), {"gain": x})),
            "module attribute": (lambda m: lambda t: m.gain * t)(_module_holding(x)),
            "object array": (lambda a: lambda t: a[0] * t)(_objects(x)),
            "jitted closure": jax.jit((lambda: lambda t: x * t)()),
        }
        _STORE["gain"] = x
        for name, fn in cases.items():
            found.setdefault(name, []).append(_may_capture_tracer((lierk.FreeRigidBody(TEE, W0), {"f": fn})))
        return x

    check(0.5)
    jax.jit(check)(0.5)
    assert found == {name: [False, True] for name in found}
    # What it cannot look inside counts as holding one: an object without
    # attributes, one that refuses to be read, a function that reads its
    # globals by name.
    assert _may_capture_tracer((lambda o: lambda t: t * o)(_Opaque()))
    assert _may_capture_tracer((lambda o: lambda t: t * o)(_Refusing()))
    assert _may_capture_tracer(lambda t: globals()["_STORE"]["gain"] * t)
    assert not _may_capture_tracer(lambda t: jnp.cos(t) * np.pi)
    # A long chain is walked without recursion (it raised RecursionError).
    chain = None
    for _ in range(3000):
        chain = Holder(chain)
    assert not _may_capture_tracer((lambda c: lambda t: c.value * t)(chain))


_STORE = {}  # a user script's global state


class _Gain:
    def __init__(self, gain):
        self.gain = gain

    def __call__(self, t):
        return self.gain * t

    def from_global(self, t):
        return _STORE["gain"] * t


def _objects(x):
    a = np.empty(2, dtype=object)
    a[0] = x
    return a


def _module_holding(x):
    m = types.ModuleType("params")
    m.gain = x
    return m


class _Opaque:
    __slots__ = ()


class _Refusing:
    def __getattribute__(self, name):
        raise RuntimeError("no")


def test_adaptive_derivatives_in_the_times_are_those_of_the_solve():
    """The last step is clipped to t1 (or a save time), so R(t1) moves with
    t1; the derivative was 0 while the step size was out of the gradient."""

    def final(t0, t1, adjoint=None):
        return lierk.solve(
            lierk.FreeRigidBody(TEE, W0), lierk.DP54(), t1, t0=t0, rtol=1e-10, atol=1e-10, adjoint=adjoint
        ).R[-1]

    # Both times in one program per mode.
    Js = jax.jacfwd(final, argnums=(0, 1))(0.1, 2.0)
    J_revs = jax.jacrev(lambda *a: final(*a, lierk.RecursiveCheckpointAdjoint()), argnums=(0, 1))(0.1, 2.0)
    for argnum, J, J_rev in zip((0, 1), Js, J_revs):
        fd = fd_jacobian(
            lambda x: final(*(jnp.array([x[0], 2.0]) if argnum == 0 else jnp.array([0.1, x[0]])), lierk.ForwardMode()),
            jnp.array([0.1 if argnum == 0 else 2.0]),
            h=1e-3,
        )[..., 0]
        np.testing.assert_allclose(J, fd, atol=1e-7)
        np.testing.assert_allclose(J_rev, fd, atol=1e-7)
    # The steps are decisions: the first step's size has no derivative.
    g = jax.grad(lambda d: lierk.solve(lierk.FreeRigidBody(TEE, W0), lierk.DP54(), 2.0, rtol=1e-8, dt0=d).R[-1, 0, 1])(
        0.01
    )
    assert float(g) == 0.0


def test_padding_rows_do_not_poison_a_gradient():
    """Adaptive SaveAt(steps=True) pads with NaN; a loss that skips them
    (nansum) gets the gradient of the rows it reads."""

    def loss(w, adjoint=None):
        sol = lierk.solve(
            lierk.FreeRigidBody(TEE, w),
            lierk.DP54(),
            2.0,
            rtol=1e-8,
            saveat=lierk.SaveAt(steps=True),
            max_steps=64,
            adjoint=adjoint,
        )
        return jnp.nansum(sol.R[:, 0, 1] ** 2)

    g = jax.grad(loss)(W0)
    g_ref = jax.grad(lambda w: loss(w, lierk.RecursiveCheckpointAdjoint()))(W0)
    assert np.all(np.isfinite(g))
    np.testing.assert_allclose(g, g_ref, rtol=1e-10)


def test_a_fixed_step_solve_cut_short_ends_where_it_stopped():
    sol = lierk.solve(lierk.FreeRigidBody(TEE, W0), lierk.RKMK4(), 2.0, dt=0.1, max_steps=5, throw=False)
    assert int(sol.result) == int(lierk.RESULTS.max_steps_reached)
    np.testing.assert_allclose(float(sol.ts[-1]), 0.5, rtol=1e-14)
