"""A body's inputs in `lierk._validation`: the range its state must fit in
(refused now when concrete, at run time when traced), and the warning about
an inertia no rigid body has, given once per body."""

from __future__ import annotations

import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import lierk
from lierk import _validation as validation

W = np.array([1.0, 0.05, 0.3])
IMPOSSIBLE = np.array([0.5, 0.6, 1.5])  # 1.5 > 0.5 + 0.6


@pytest.mark.parametrize(
    "inertia, omega0, match",
    [
        # The solve of 1e300 kg m^2 at 1 rad/s returned success with the |L|
        # invariant inf (|L|^2 = 1e600), its drift nan.
        ([1e300, 1e300, 1e300], W, r"det\(I\), the product of the principal moments, = 1e\+900 overflows float64"),
        ([1e-300, 1e-300, 1e-300], W, r"det\(I\), the product of the principal moments, = 1e-900 underflows float64"),
        ([1e100, 1e100, 1e100], 1e55 * W, r"\|L\|\^2 = \|I omega\|\^2 = 1.1e\+310 overflows float64"),
        # lierk.exact divides by det(I): at 1e150 the flip interval came out inf.
        ([1e150, 2e150, 3e150], W, r"det\(I\), the product of the principal moments, = 6e\+450 overflows float64"),
        ([1.0, 2.0, 3.0], [1e200, 0.0, 0.0], r"\|omega\|\^2 = 1e\+400 overflows float64"),
        ([1e100, 2e100, 3e100], [1e60, 0.0, 0.0], r"\|L\|\^2 = \|I omega\|\^2 = 1e\+320 overflows float64"),
    ],
)
def test_a_state_that_does_not_fit_the_dtype_is_refused(inertia, omega0, match):
    with pytest.raises(ValueError, match=r"^inertia \[.*\] kg m\^2 with omega0 \[.*\] rad/s: " + match):
        lierk.FreeRigidBody(inertia, omega0)
    with pytest.raises(ValueError, match=match):
        lierk.exact.flip_interval(inertia, omega0)


def test_the_range_is_the_working_dtypes():
    I, w = np.array([1e10, 2e10, 2.5e10]), np.array([1e10, 0.5e10, 0.4e10])
    lierk.FreeRigidBody(I, w)
    with pytest.raises(
        ValueError,
        match=r"\|L\|\^2 = \|I omega\|\^2 = 3e\+40 overflows float32, whose normal numbers "
        r"lie between 1.2e-38 and 3.4e\+38",
    ):
        lierk.FreeRigidBody(I.astype(np.float32), w.astype(np.float32))
    assert validation.state_range_error(I, w, np.float64) is None


def test_extreme_bodies_that_fit_are_accepted_and_computed_right():
    """Scaling the inertia leaves the motion as it is: the exact flip interval
    of a 1:2:3 body at 1e+-100 kg m^2 is that of the unit one.  (At 1e150
    it came out inf, and 1e-150 was refused as "not positive definite"; both
    are out of range now, with that said.)"""
    w = np.array([0.05, 1.0, 0.05])
    unit = float(lierk.exact.flip_interval([1.0, 2.0, 3.0], w))
    for scale in (1e100, 1e-100):
        p = lierk.FreeRigidBody(scale * np.array([1.0, 2.0, 3.0]), w)
        np.testing.assert_allclose(float(lierk.exact.flip_interval(p.inertia, p.omega0)), unit, rtol=1e-12)
    # A body at rest squares nothing; its moments must still fit.  Squares
    # below the smallest normal number are a body at rest to any precision
    # that matters (hypothesis drew |omega| = 3.5e-218 rad/s).
    lierk.FreeRigidBody([1e100, 1e100, 1e100], [0.0, 0.0, 0.0])
    lierk.FreeRigidBody([1.0, 1.0, 1.0], [0.0, 0.0, 3.4594814563000027e-218])
    lierk.FreeRigidBody([1e-90, 1e-90, 1e-90], 1e-70 * W)


def test_a_traced_state_out_of_range_fails_at_run_time():
    """Checked inside the program: the solve ends with
    `RESULTS.invalid_problem` and NaN states (``throw=False``), or raises
    naming the condition (``throw=True``); one bad member of a batch is
    caught and the others are solved."""

    @jax.jit
    def final(I, w):
        sol = lierk.solve(lierk.FreeRigidBody(I, w), lierk.RKMK4(), 0.1, dt=0.05, throw=False)
        return sol.R[-1], sol.result

    R, code = final(jnp.array([1.0, 2.0, 3.0]), jnp.asarray(W))
    assert int(code) == 0 and np.isfinite(np.asarray(R)).all()
    R, code = final(jnp.array([1e300, 1e300, 1e300]), jnp.asarray(W))
    assert int(code) == lierk.RESULTS.invalid_problem and np.isnan(np.asarray(R)).all()
    raising = jax.jit(lambda I, w: lierk.solve(lierk.FreeRigidBody(I, w), lierk.RKMK4(), 0.1, dt=0.05).R)
    with pytest.raises(Exception, match="a traced inertia and omega0 give a body state outside float64's range"):
        jax.block_until_ready(raising(jnp.array([1e300, 1e300, 1e300]), jnp.asarray(W)))
    # One bad member of a batch is caught, the other solved.
    R, code = jax.jit(jax.vmap(final))(jnp.array([[1.0, 2.0, 3.0], [1e-300, 1e-300, 1e-300]]), jnp.stack([W, W]))
    np.testing.assert_array_equal(np.asarray(code), [0, lierk.RESULTS.invalid_problem])
    assert np.isfinite(np.asarray(R[0])).all() and np.isnan(np.asarray(R[1])).all()
    with pytest.raises(Exception, match="outside float64's range"):
        jax.block_until_ready(
            jax.vmap(raising)(jnp.array([[1.0, 2.0, 3.0], [1e-300, 1e-300, 1e-300]]), jnp.stack([W, W]))
        )


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_the_traced_range_check_decides_as_the_host_check(dtype):
    # A traced solve checks the state's range from the quantities themselves
    # (one XLA kernel); the host works in logarithms to name the sizes.  Both
    # must decide alike, at the edges of the dtype's range above all.
    rng = np.random.default_rng(7)
    top = np.log10(float(np.finfo(dtype).max))
    tiny = np.log10(float(np.finfo(dtype).tiny))
    inertias, omegas = [], []
    for k in range(600):
        if k % 3 == 0:  # |L|^2 and 2T tr(I) near overflow
            I = 10.0 ** rng.uniform(-5, 5, 3)
            w = rng.normal(size=3)
            w *= 10.0 ** (top / 2 - np.log10(I.max()) / 2 + rng.uniform(-0.4, 0.4)) / np.linalg.norm(w)
        elif k % 3 == 1:  # moments near underflow
            I, w = 10.0 ** (tiny / 3 + rng.uniform(-0.4, 0.4, 3)), rng.normal(size=3)
        else:  # moments near overflow, and a body at rest
            I, w = 10.0 ** (top / 3 + rng.uniform(-0.4, 0.4, 3)), rng.normal(size=3) * (k % 2) * 1e-3
        inertias.append(np.diag(I).astype(dtype))
        omegas.append(w.astype(dtype))
    with np.errstate(all="ignore"):
        host = np.array([validation.state_range_error(I, w, dtype) is None for I, w in zip(inertias, omegas)])
    traced = np.asarray(
        jax.jit(jax.vmap(validation._in_range))(jnp.asarray(np.stack(inertias)), jnp.asarray(np.stack(omegas)))
    )
    assert 100 < host.sum() < 500, host.sum()
    np.testing.assert_array_equal(traced, host)


def test_an_impossible_inertia_warns_once_per_body():
    with warnings.catch_warnings(record=True) as shown:
        warnings.simplefilter("always")
        p = lierk.FreeRigidBody(IMPOSSIBLE, W)
        # The library hands the body's own inertia back to the validation:
        # the exact solution, the flip event, another body built from it.
        lierk.exact.flip_interval(p.inertia, p.omega0)
        lierk.exact.free_rigid_body(p.inertia, p.omega0, 0.5)
        lierk.conditions.flip(p)
        lierk.FreeRigidBody(p.inertia, 2 * W)
        lierk.RigidBodyWithEffects(p.inertia, W, effects=lierk.Damping(0.1))
    assert [str(w.message).split(" breaks")[0] for w in shown] == ["inertia [0.5, 0.6, 1.5]"]
    # Each body built from the moments themselves is warned about.
    with pytest.warns(UserWarning, match="triangle inequality"):
        lierk.FreeRigidBody(IMPOSSIBLE, W)
    with pytest.warns(UserWarning, match="triangle inequality"):
        lierk.exact.flip_interval(list(IMPOSSIBLE), W)


def test_a_traced_impossible_inertia_is_solved_as_given_and_a_singular_one_fails():
    """A traced inertia cannot be warned about (its value is unknown while
    tracing).  It is not garbage either: the equations hold for any
    positive-definite inertia, and the jitted solve is the concrete one; a
    matrix that is not positive definite still fails at run time."""

    def final(I):
        return lierk.solve(lierk.FreeRigidBody(I, W), lierk.RKMK4(), 0.5, dt=0.05).R[-1]

    with warnings.catch_warnings(record=True) as shown:
        warnings.simplefilter("always")
        traced = jax.jit(final)(jnp.asarray(IMPOSSIBLE))
    assert not shown
    with pytest.warns(UserWarning, match="triangle inequality"):
        concrete = final(IMPOSSIBLE)
    np.testing.assert_allclose(np.asarray(traced), np.asarray(concrete), rtol=0, atol=1e-14)
    with pytest.raises(Exception, match="inertia must be positive definite"):
        jax.block_until_ready(jax.jit(final)(jnp.array([1.0, -2.0, 3.0])))


def test_values_put_on_the_device_together_keep_their_dtype_and_bits():
    """`_validation.as_jax_each` (one transfer for several values) gives what
    `as_jax` of each gives, in the dtype JAX makes it under the x64 setting
    of the call, sign of zero kept."""
    for x64 in (True, False):
        with jax.enable_x64(x64):
            values = (0.1, -0.0, np.array([1.0, 2.0]), 3, jnp.asarray(0.5))
            for dtype in (None, np.float32):
                for a, b in zip(
                    validation.as_jax_each(*values, dtype=dtype), (validation.as_jax(v, dtype) for v in values)
                ):
                    assert isinstance(a, jax.Array) and a.dtype == b.dtype and a.shape == b.shape
                    assert np.asarray(a).tobytes() == np.asarray(b).tobytes()
            c = lierk.Controller(1e-7, 1e-9)
            assert (float(c.rtol), float(c.atol)) == (
                np.float64(1e-7).astype(c.rtol.dtype),
                np.float64(1e-9).astype(c.rtol.dtype),
            )
            assert c.rtol.dtype == (np.float64 if x64 else np.float32)
