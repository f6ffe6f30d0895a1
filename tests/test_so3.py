"""Claims of lierk.so3: batching, dtypes, exactness at 0 and past 2 pi,
stability of log near 0 and pi, derivatives (finite at half turns), dexp/dexpinv,
Euler angles at and near the gimbal lock (against SciPy), and input checks."""

from __future__ import annotations

import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import lierk
from lierk import so3 as _so3


class _Jitted:
    """lierk.so3 with every function wrapped in jax.jit: the maps under test are the
    same, but eager op-by-op dispatch (slow for these tiny arrays) is avoided."""

    def __getattr__(self, name):
        f = jax.jit(getattr(_so3, name))
        setattr(self, name, f)
        return f


so3 = _Jitted()

RNG = np.random.default_rng(0)
E = np.eye(3)


def _random_vectors(shape, scale=1.0, rng=RNG):
    return scale * rng.standard_normal(shape + (3,))


def _vectors_with_norms(norms, rng=RNG):
    d = rng.standard_normal((len(norms), 3))
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    return np.asarray(norms)[:, None] * d


def _central_jacobian(f, x, eps):
    """d f / d x by central differences, as an array of shape f(x).shape + x.shape."""
    x = np.asarray(x, dtype=float)
    cols = []
    for i in range(x.size):
        dx = np.zeros(x.size)
        dx[i] = eps
        dx = dx.reshape(x.shape)
        cols.append((np.asarray(f(x + dx)) - np.asarray(f(x - dx))) / (2 * eps))
    return np.stack(cols, axis=-1).reshape(cols[0].shape + x.shape)


# --- batching and dtypes --------------------------------------------------------------


@pytest.mark.parametrize("dtype, tol", [(np.float64, 1e-14), (np.float32, 2e-6)])
def test_every_function_broadcasts_over_leading_axes(dtype, tol):
    """Each map applied to a (2, 4, ...) batch equals the map applied element by element,
    and keeps the input's dtype."""
    u = _random_vectors((2, 4)).astype(dtype)
    v = _random_vectors((2, 4)).astype(dtype)
    R = np.asarray(so3.exp(u))
    batched = {
        "hat": (so3.hat(u), lambda i: so3.hat(u[i])),
        "vee": (so3.vee(so3.hat(u)), lambda i: so3.vee(so3.hat(u[i]))),
        "exp": (so3.exp(u), lambda i: so3.exp(u[i])),
        "log": (so3.log(R), lambda i: so3.log(R[i])),
        "dexp": (so3.dexp(u, v), lambda i: so3.dexp(u[i], v[i])),
        "dexpinv": (so3.dexpinv(u, v), lambda i: so3.dexpinv(u[i], v[i])),
        "rotate": (so3.rotate(u, v), lambda i: so3.rotate(u[i], v[i])),
        "cross": (so3.cross(u, v), lambda i: so3.cross(u[i], v[i])),
        "orthogonality_error": (so3.orthogonality_error(R), lambda i: so3.orthogonality_error(R[i])),
    }
    for name, (out, single) in batched.items():
        assert out.dtype == dtype, name
        assert out.shape[:2] == (2, 4), name
        for i in np.ndindex(2, 4):
            np.testing.assert_allclose(out[i], single(i), rtol=0, atol=tol, err_msg=name)


@pytest.mark.parametrize("dtype, tol", [(np.float64, 1e-14), (np.float32, 1e-5)])
def test_hat_vee_cross_agree(dtype, tol):
    a = _random_vectors((5,)).astype(dtype)
    b = _random_vectors((5,)).astype(dtype)
    np.testing.assert_allclose(so3.hat(a) @ b[..., None], np.cross(a, b)[..., None], atol=tol)
    np.testing.assert_allclose(so3.cross(a, b), np.cross(a, b), atol=tol)
    np.testing.assert_array_equal(so3.vee(so3.hat(a)), a)
    H = np.asarray(so3.hat(a))
    np.testing.assert_array_equal(H, -np.swapaxes(H, -1, -2))


def test_broadcasting_mixes_batch_shapes():
    """A single u against a batch of x (and vice versa) broadcasts like NumPy."""
    u = _random_vectors(())
    x = _random_vectors((6,))
    np.testing.assert_allclose(so3.rotate(u, x), (np.asarray(so3.exp(u)) @ x.T).T, atol=1e-14)
    np.testing.assert_allclose(so3.dexpinv(u, x), [so3.dexpinv(u, xi) for xi in x], atol=1e-14)


def test_wrong_shapes_raise():
    with pytest.raises(ValueError, match=r"\(\.\.\., 3\)"):
        so3.exp(np.zeros(4))
    with pytest.raises(ValueError, match=r"\(\.\.\., 3\)"):
        so3.hat(np.zeros((2, 2)))
    with pytest.raises(ValueError, match=r"\(\.\.\., 3, 3\)"):
        so3.log(np.zeros((3, 4)))
    with pytest.raises(ValueError, match=r"\(\.\.\., 3, 3\)"):
        so3.vee(np.zeros(3))


@pytest.mark.parametrize("name", ["to_quaternion", "to_mrp", "to_euler", "log"])
def test_matrix_conversions_refuse_other_shapes_even_traced(name):
    """A shape is static, so it is refused inside jit as well; to_mrp of a
    vector raised IndexError, to_quaternion and to_euler read whatever entries
    were there."""
    f = getattr(_so3, name)
    for shape in [(3,), (3, 4), (2, 4, 3)]:
        with pytest.raises(ValueError, match=rf"{name} expects .*\(\.\.\., 3, 3\), got shape {re.escape(str(shape))}"):
            f(np.zeros(shape))
        with pytest.raises(ValueError, match=re.escape(str(shape))):
            jax.jit(f)(np.zeros(shape))


@pytest.mark.parametrize("name", ["to_quaternion", "to_mrp", "to_euler", "log"])
def test_matrix_conversions_refuse_known_non_rotations(name):
    """A known (not traced) matrix that is not a rotation is refused with its
    index, ||R^T R - I||, det R and entries: 2 I (to_quaternion returned
    (1.32, 0, 0, 0) for it), a reflection (det -1), and a rotation scaled by
    1 + 1e-5 in float64 or off by 1e-3 in float32."""
    f = getattr(_so3, name)
    with pytest.raises(
        ValueError,
        match=rf"{name} expects rotation.* R has \|\|R\^T R - I\|\| = 5\.2 and det R = 8: \[\[2\., 0\., 0\.\]",
    ):
        f(2 * np.eye(3))
    good = Rotation.random(3, random_state=6).as_matrix()
    flipped = good.copy()
    flipped[1] = np.diag([1.0, 1.0, -1.0])
    with pytest.raises(ValueError, match=r"R\[1\] has .* det R = -1: \[\[ 1\., +0\., +0\.\]"):
        f(flipped)
    off = good.copy()
    off[2] *= 1 + 1e-5  # R^T R - I = (2e-5 + 1e-10) I
    with pytest.raises(ValueError, match=r"R\[2\] has \|\|R\^T R - I\|\| = 3.46e-05 and det R = 1.00003"):
        f(off)
    off32 = good.astype(np.float32)
    off32[0, 1, 1] += 1e-3
    with pytest.raises(ValueError, match=r"<= 0.00012 in float32, .*R\[0\] has \|\|R\^T R - I\|\| = 0.0018"):
        f(off32)


def test_rotation_check_passes_rounded_rotations_nan_and_traced_values():
    """Rotations rounded in float32 pass, even after 1000 unnormalised float32
    products (||R^T R - I|| ~ 1e-5); NaN states (a failed solve's padding) pass
    through as NaN; traced values are not checked (a check would be a host
    callback in every compiled caller)."""
    R32 = np.eye(3, dtype=np.float32)
    for Q in Rotation.random(1000, random_state=8).as_matrix().astype(np.float32):
        R32 = R32 @ Q
    assert 1e-6 < float(np.asarray(so3.orthogonality_error(R32))) < 1e-4
    q = np.asarray(_so3.to_quaternion(np.stack([R32, np.full((3, 3), np.nan, np.float32)])))
    np.testing.assert_allclose(
        q[0], Rotation.from_matrix(R32.astype(np.float64)).as_quat(canonical=True, scalar_first=True), atol=1e-5
    )
    assert np.all(np.isnan(q[1]))
    so3.to_quaternion(2 * np.eye(3))


def test_from_quaternion_refuses_a_zero_quaternion():
    """A zero quaternion has no direction to normalise (it gave a NaN matrix):
    refused with its index and value when known, and for a shape other than (..., 4)
    even inside jit."""
    with pytest.raises(ValueError, match=r"non-zero quaternion, got q = \[0\., 0\., 0\., 0\.\]"):
        _so3.from_quaternion(np.zeros(4))
    q = np.array([[1.0, 0, 0, 0], [0.0, 0, 0, 0]])
    with pytest.raises(ValueError, match=r"got q\[1\] = \[0\., 0\., 0\., 0\.\]"):
        _so3.from_quaternion(q)
    # Squared norm underflowing in float32 is as bad as zero.
    with pytest.raises(ValueError, match=r"q = \[1\.e-30, 0\.e\+00, 0\.e\+00, 0\.e\+00\]"):
        _so3.from_quaternion(np.array([1e-30, 0, 0, 0], np.float32))
    with pytest.raises(ValueError, match=r"\(\.\.\., 4\), got shape \(3,\)"):
        jax.jit(_so3.from_quaternion)(np.ones(3))
    np.testing.assert_allclose(_so3.from_quaternion(np.array([2.0, 0, 0, 0])), np.eye(3), atol=0)


# --- exp --------------------------------------------------------------------------------


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_exp_at_zero_is_exact_in_value_and_both_derivative_modes(dtype):
    z = np.zeros(3, dtype)
    R = so3.exp(z)
    np.testing.assert_array_equal(R, np.eye(3, dtype=dtype))
    generators = np.stack([np.asarray(so3.hat(e)) for e in E], axis=-1)  # (3, 3, 3): [:, :, i] = hat(e_i)
    for jac in (jax.jit(jax.jacfwd(so3.exp)), jax.jit(jax.jacrev(so3.exp))):
        J = np.asarray(jac(z))
        assert J.dtype == dtype
        np.testing.assert_array_equal(J, generators.astype(dtype))
    # A batch of zeros, through vmap of the gradient of a scalar, stays finite and exact.
    g = jax.jit(jax.vmap(jax.grad(lambda w: jnp.sum(so3.exp(w) * so3.hat(jnp.ones(3, dtype))))))(
        np.zeros((4, 3), dtype)
    )
    np.testing.assert_array_equal(g, np.full((4, 3), 2.0, dtype))


def test_exp_matches_scipy_over_many_turns():
    """Angles up to 20 rad (over three full turns) in one call, against SciPy's rotvec."""
    norms = np.concatenate(
        [[1e-9, 1e-4, 0.05, 0.3, 1.0, np.pi - 1e-9, np.pi, 4.0], np.linspace(2 * np.pi - 0.5, 20.0, 12)]
    )
    w = _vectors_with_norms(norms)
    np.testing.assert_allclose(so3.exp(w), Rotation.from_rotvec(w).as_matrix(), rtol=0, atol=1e-14)
    # Exactly 2 pi k about any axis is the identity.
    k = np.arange(1, 4)[:, None] * 2 * np.pi * np.array([0.6, 0.0, 0.8])
    np.testing.assert_allclose(so3.exp(k), np.broadcast_to(np.eye(3), (3, 3, 3)), atol=1e-14)


def test_exp_float32_matches_float64():
    w = _vectors_with_norms(np.array([1e-6, 0.2, 0.31, 1.0, 3.0, 9.0]))
    R32 = so3.exp(w.astype(np.float32))
    assert R32.dtype == np.float32
    np.testing.assert_allclose(R32, so3.exp(w), atol=3e-6)
    assert np.all(so3.orthogonality_error(R32) < 1e-6)


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_exp_of_huge_angles_is_a_rotation_within_their_rounding(dtype):
    """|w| of 1e300 in float64 or 1e20 in float32 gave NaN: |w|^2
    overflowed.  The angle is exact to within its rounding (|w| eps; NumPy's
    sin and cos reduce a float64 exactly), and once that passes a turn any
    angle is: then the result must be a rotation about w, finite."""
    eps, big = float(np.finfo(dtype).eps), float(np.finfo(dtype).max)
    angles = np.geomspace(1e3, big / 2, 60).astype(dtype)
    w = np.zeros((len(angles), 3), dtype)
    w[:, 2] = angles
    R = np.asarray(so3.exp(w), np.float64)
    assert np.all(np.isfinite(R))
    np.testing.assert_allclose(R[:, :, 2], np.broadcast_to([0.0, 0.0, 1.0], (len(angles), 3)), atol=4 * eps)
    assert np.max(np.asarray(so3.orthogonality_error(R))) < 4 * eps
    theta = angles.astype(np.float64)
    gap = np.angle(np.exp(1j * (np.arctan2(R[:, 1, 0], R[:, 0, 0]) - np.arctan2(np.sin(theta), np.cos(theta)))))
    assert np.all(np.abs(gap) <= 0.5 * theta * eps + 4 * eps), (theta[np.abs(gap) > 0.5 * theta * eps], gap)
    # Any direction, the largest vectors there are; finite derivatives too.
    w = np.array([[big, -big, big], [big / 3, 0.0, -big / 7], [1e30, 2e30, -1e30]], dtype)
    R = np.asarray(so3.exp(w), np.float64)
    assert np.all(np.isfinite(R)) and np.max(np.asarray(so3.orthogonality_error(R))) < 4 * eps
    scaled = w.astype(np.float64) / np.max(np.abs(w.astype(np.float64)), axis=-1, keepdims=True)
    axes = scaled / np.linalg.norm(scaled, axis=-1, keepdims=True)
    np.testing.assert_allclose(np.einsum("nij,nj->ni", R, axes), axes, atol=8 * eps)
    for jac in (jax.jit(jax.jacfwd(so3.exp)), jax.jit(jax.jacrev(so3.exp))):
        assert np.all(np.isfinite(np.asarray(jac(w[0]))))


def test_exp_is_a_one_parameter_group():
    """exp(s w) exp(t w) = exp((s + t) w) across the series/closed-form threshold."""
    w = _vectors_with_norms(np.array([1.0]))[0]
    for s, t in [(0.01, 0.02), (0.09, 0.02), (1.3, 2.9), (4.0, 5.0)]:
        np.testing.assert_allclose(so3.exp(s * w) @ so3.exp(t * w), so3.exp((s + t) * w), atol=1e-14)


def test_exp_continuous_across_series_threshold():
    """The two evaluations of the coefficients (series in theta^2 up to theta = pi/2,
    reduced argument beyond) agree where they meet: no jump larger than a few ulp."""
    axis = np.array([0.36, 0.48, 0.8])
    for dtype, tol in [(np.float64, 2e-15), (np.float32, 6e-7)]:
        th = np.pi / 2
        w = (th * np.array([1 - 1e-7, 1 + 1e-7]))[:, None] * axis
        a, b = np.asarray(so3.exp(w.astype(dtype)))
        # The true difference is ~1e-7 th |dR/dth| <= 1e-7 th.
        assert np.abs(a - b).max() < 2e-7 * th + tol


def _coefficients_reference(theta):
    """(A, B, D) in extended precision (NumPy long double), D by its series below 0.1 rad."""
    t = np.asarray(theta, np.longdouble)
    x = t / 2
    with np.errstate(divide="ignore", invalid="ignore"):
        A = np.where(t > 0, np.sin(t) / t, 1)
        B = np.where(t > 0, 2 * np.sin(x) ** 2 / t**2, 0.5)
        t2 = t * t
        D_series = 1 / np.longdouble(12) + t2 / 720 + t2**2 / 30240 + t2**3 / 1209600 + t2**4 / 47900160
        D = np.where(t > 0.1, (1 - x * np.cos(x) / np.sin(x)) / t2, D_series)
    return A, B, D


def test_exp_coefficients_exact_to_rounding_at_every_angle():
    """A, B, D against extended precision from 1e-9 rad to 3e9 rad (about 5e8 turns),
    including the quadrant edges of the argument reduction (theta/2 = k pi/4), in float64
    and float32.  Errors are measured as they enter exp and dexpinv: |dA|, |dB| theta^2
    and |dD| theta^2, each against 1.  D is left out next to its poles (theta = 2 pi k)."""
    if np.finfo(np.longdouble).bits <= 64:
        pytest.skip("no extended precision long double on this platform")
    rng = np.random.default_rng(3)
    edges = np.arange(1, 80) * np.pi / 2
    theta = np.concatenate(
        [
            np.geomspace(1e-9, 3e9, 3000),
            rng.uniform(0, 40, 3000),
            edges,
            edges * (1 + 1e-9),
            edges * (1 - 1e-9),
        ]
    )
    for dtype, limit, tol in [(np.float64, 3e9, 4e-16), (np.float32, 2.6e4, 4e-7)]:
        th = theta[theta <= limit].astype(dtype)
        A, B, D = (np.asarray(c, np.float64) for c in jax.jit(_so3.exp_coefficients)(th.astype(dtype) ** 2))
        # The reference at the angle the input actually holds (theta^2 rounded in dtype).
        t = np.sqrt(np.asarray(th.astype(dtype) ** 2, np.longdouble))
        rA, rB, rD = _coefficients_reference(t)
        t2 = t * t
        far_from_pole = np.abs(np.sin(t / 2)) > 0.05
        # Large angles: theta itself is only known to ulp(theta), and every
        # coefficient moves by up to that much (times 1/theta).
        slack = tol + np.spacing(np.asarray(t, dtype)).astype(np.float64)
        assert np.all(np.abs(A - rA) <= 4 * slack), np.max(np.abs(A - rA) / slack)
        assert np.all(np.abs(B - rB) * t2 <= 4 * slack * np.maximum(1, t)), np.max(np.abs(B - rB) * t2 / slack)
        dD = (np.abs(D - rD) * t2)[far_from_pole]
        assert np.all(dD <= 20 * (slack * np.maximum(1, t2))[far_from_pole]), np.max(dD / slack[far_from_pole])


def test_exp_coefficients_derivatives_at_zero_and_across_the_switch():
    """d/d(theta^2) of (A, B, D) is (-1/6, -1/24, 1/720) at 0, finite everywhere
    (no NaN leaking from the unused branch), and continuous where the evaluation
    switches at theta = pi/2."""
    grad = jax.jit(jax.vmap(jax.jacfwd(lambda t2: jnp.stack(_so3.exp_coefficients(t2)))))
    g0 = np.asarray(grad(jnp.zeros(1)))[0]
    np.testing.assert_allclose(g0, [-1 / 6, -1 / 24, 1 / 720], rtol=1e-15)
    grev = jax.jit(jax.vmap(jax.grad(lambda t2: sum(_so3.exp_coefficients(t2)))))
    t2 = np.concatenate([[0.0, 1e-30], np.linspace(0, 30, 301) ** 2])
    assert np.all(np.isfinite(grev(t2)))
    s = (np.pi / 2) ** 2 * np.array([1 - 1e-9, 1 + 1e-9])
    a, b = np.asarray(grad(s))
    np.testing.assert_allclose(a, b, rtol=1e-7)


def test_the_compact_forms_give_the_same_numbers():
    """One body's solve takes the compact forms (fewer XLA kernels; the
    public functions have one form, `lierk._programs` chooses): the
    coefficients as one stacked division, and the group update row by row,
    without forming exp(u).  The same to rounding, in value and in both
    derivative modes, from 0 through several turns."""
    theta = np.concatenate([[0.0, 1e-9], np.geomspace(1e-6, 60.0, 200)])
    c = jax.jit(lambda t2: (_so3.exp_coefficients(t2), _so3._coefficients(t2, True)))
    plain, compact = c(theta**2)
    for a, b in zip(plain, compact):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-15, atol=1e-17)
    u = _vectors_with_norms(np.array([0.0, 1e-9, 1e-3, 0.5, np.pi, 7.0, 40.0]))
    R = np.asarray(so3.exp(_random_vectors((7,))))

    def update(compact):
        return jax.jit(lambda R, u: _so3._right_exp(R, u, compact))

    np.testing.assert_allclose(update(True)(R, u), update(False)(R, u), rtol=0, atol=4e-15)
    for mode in (jax.jacfwd, jax.jacrev):
        d = [jax.jit(jax.vmap(mode(lambda R, u, c=c: _so3._right_exp(R, u, c), (0, 1))))(R, u) for c in (True, False)]
        for a, b in zip(*d):
            np.testing.assert_allclose(a, b, rtol=0, atol=4e-14)


def test_rotate_equals_exp_times_x():
    u = _vectors_with_norms(np.array([0.0, 1e-8, 1e-3, 0.5, np.pi, 7.0, 15.0]))
    x = _random_vectors((7,))
    expected = np.einsum("nij,nj->ni", np.asarray(so3.exp(u)), x)
    np.testing.assert_allclose(so3.rotate(u, x), expected, atol=1e-14)


@pytest.mark.parametrize("k", [0, 1, 2])
def test_axis_turn_is_the_coordinate_axis_exp_from_the_right(k):
    phi = np.array([0.0, -1e-8, 1e-3, -0.5, np.pi, 7.0, -15.0, 1e4])
    X = np.random.default_rng(k).normal(size=(len(phi), 2, 3))
    E = np.asarray(_so3.exp(np.eye(3)[k] * phi[:, None]))
    turn = jax.jit(_so3.axis_turn, static_argnums=1)
    np.testing.assert_allclose(turn(X, k, phi), X @ E, atol=1e-13)
    # On a vector: the inverse rotation, exp(-phi e_k) x.
    np.testing.assert_allclose(turn(X[:, 0], k, phi), np.einsum("nji,nj->ni", E, X[:, 0]), atol=1e-13)


@pytest.mark.parametrize("k", [3, -1, 1.0, True, np.array([0.0, 0.0, 1.0])])
def test_axis_turn_refuses_anything_but_a_coordinate_index(k):
    with pytest.raises(ValueError, match="axis_turn: k is .* 0, 1 or 2"):
        _so3.axis_turn(np.ones(3), k, 0.5)
    # symmetric_flow took the axis as a unit vector before: say so, do not index.
    from lierk import exact

    with pytest.raises(ValueError, match="symmetric_flow: k is .* 0, 1 or 2"):
        exact.symmetric_flow(5.0, 1.0, k, np.ones(3), 0.1)


# --- log --------------------------------------------------------------------------------


def test_log_inverts_exp_below_pi():
    norms = np.concatenate(
        [
            [0.0, 1e-300, 1e-12, 1e-8, 1e-5, 0.01, 0.099, 0.1, 0.101],
            RNG.uniform(0, np.pi, 30),
            [3.0, np.pi - 1e-4, np.pi - 1e-7],
        ]
    )
    w = _vectors_with_norms(norms)
    back = np.asarray(so3.log(so3.exp(w)))
    # Relative to |w| for small angles (no absolute 1e-16 floor that hides a 100% error).
    err = np.linalg.norm(back - w, axis=-1)
    assert np.all(err <= 4e-16 * np.maximum(norms, 1e-300) + 2e-15 * (norms > 1e-3)), err.max()


def test_log_near_zero_is_accurate_relative_to_angle():
    for theta in [1e-15, 1e-10, 1e-7, 1e-4]:
        w = theta * np.array([0.6, -0.48, 0.64])
        np.testing.assert_allclose(so3.log(so3.exp(w)), w, rtol=1e-14, atol=0)
    np.testing.assert_array_equal(so3.log(np.eye(3)), np.zeros(3))


def test_log_near_and_at_pi():
    axis = np.array([2.0, -1.0, 2.0]) / 3.0
    for gap in [1e-3, 1e-6, 1e-9, 1e-12]:
        w = (np.pi - gap) * axis
        np.testing.assert_allclose(so3.log(so3.exp(w)), w, atol=2e-14)
    # At exactly pi, +axis and -axis give the same rotation: either answer is right,
    # and exp(log(R)) must reproduce R.
    R = Rotation.from_rotvec(np.pi * axis).as_matrix()
    w = np.asarray(so3.log(R))
    assert abs(np.linalg.norm(w) - np.pi) < 1e-14
    assert min(np.abs(w - np.pi * axis).max(), np.abs(w + np.pi * axis).max()) < 1e-14
    np.testing.assert_allclose(so3.exp(w), R, atol=1e-14)


def test_log_matches_scipy_for_random_rotations():
    R = Rotation.random(50, random_state=1)
    np.testing.assert_allclose(so3.log(R.as_matrix()), R.as_rotvec(), atol=1e-14)


def test_log_float32():
    w = _vectors_with_norms(np.array([1e-6, 1e-3, 0.3, 2.0, np.pi - 1e-2]))
    w32 = w.astype(np.float32)
    out = so3.log(so3.exp(w32))
    assert out.dtype == np.float32
    np.testing.assert_allclose(out, w, atol=2e-6)


# --- derivatives vs finite differences --------------------------------------------------


def _log_along_group(x, R0):
    return _so3.log(R0 @ _so3.exp(x))


# Compiled once for the whole module; the base point is an argument, not a constant.
_JACOBIANS = {
    name: (f, jax.jit(jax.jacfwd(f)), jax.jit(jax.jacrev(f)))
    for name, f in [("exp", _so3.exp), ("log", _so3.log), ("log_along_group", _log_along_group)]
}


def _check_jacobians(name, x, fd_eps, atol, *args):
    f, jf, jr = _JACOBIANS[name]
    fj = jax.jit(f)
    fd = _central_jacobian(lambda y: fj(y, *args), x, fd_eps)
    for jac in (jf, jr):
        J = np.asarray(jac(jnp.asarray(x), *args))
        assert np.all(np.isfinite(J))
        np.testing.assert_allclose(J, fd, rtol=0, atol=atol)


def test_exp_jacobian_matches_finite_differences():
    for theta in [0.0, 1e-9, 0.1, 1.0, np.pi - 1e-3, np.pi - 1e-7, 5.0]:
        _check_jacobians("exp", theta * np.array([0.6, -0.48, 0.64]), 1e-6, 1e-9)


def test_log_jacobian_matches_finite_differences():
    """The derivative of log along the group, x -> log(R0 exp(x)) at x = 0, and with
    respect to the matrix entries of R (a smooth function of R near R0).  log jumps
    at |w| = pi, so the difference step stays below pi - theta."""
    cases = [
        (0.0, 1e-6, 1e-8),
        (1e-9, 1e-6, 1e-8),
        (0.1, 1e-6, 1e-8),
        (1.0, 1e-6, 1e-8),
        (np.pi - 1e-3, 1e-6, 1e-8),
        (np.pi - 1e-5, 1e-7, 1e-7),
    ]
    for theta, eps, atol in cases:
        R0 = np.asarray(so3.exp(theta * np.array([0.6, -0.48, 0.64])))
        _check_jacobians("log_along_group", np.zeros(3), eps, atol, R0)
        _check_jacobians("log", R0, eps, atol)


def test_log_jacobian_at_identity_is_vee():
    """d log / d R at R = I applied to a skew direction hat(a) gives a."""
    a = np.array([0.3, -1.2, 0.5])
    _, t = jax.jvp(so3.log, (jnp.eye(3),), (so3.hat(a),))
    np.testing.assert_allclose(t, a, atol=1e-15)
    _, vjp = jax.vjp(so3.log, jnp.eye(3))
    (g,) = vjp(jnp.asarray(a))
    # <g, hat(b)> = <a, b> for every b: the cotangent's antisymmetric part is hat(a)/2.
    for b in E:
        assert abs(np.sum(np.asarray(g) * np.asarray(so3.hat(b))) - a @ b) < 1e-15


def _log_branch_jacobian(x, u):
    """d/dx log(exp(x)) on the branch whose value u = log(exp(x)) was returned:
    I where u = x, and the derivative of x - 2 pi x/|x| where the angle passed pi."""
    x, u = np.asarray(x, np.float64), np.asarray(u, np.float64)
    t = np.linalg.norm(x)
    if np.linalg.norm(u - x) < 1e-3:
        return np.eye(3)
    n = x / t
    return np.eye(3) - 2 * np.pi / t * (np.eye(3) - np.outer(n, n))


_HALF_TURN_AXES = np.concatenate([np.eye(3), _vectors_with_norms(np.ones(4), np.random.default_rng(11))])


@pytest.mark.parametrize("dtype, tol", [(np.float64, 2e-15), (np.float32, 1e-6)])
def test_log_derivatives_at_and_near_a_half_turn(dtype, tol):
    """x -> log(exp(x)) at pi - gap times e_0, e_1, e_2 and four random unit
    axes, gap = 0, 1e-7, 1e-6 and -1e-7 (just past pi), in both modes: finite,
    and the derivative of the branch log returned (the identity below pi;
    in float32 pi itself rounds above pi, so there the angle has passed it).
    Before, the unused series branch of log (1/w, and x^3 overflowing in float32)
    turned reverse mode into NaN within 7e-7 of pi in float32: jax.grad of
    log(exp(x)).sum() at x = (pi, 0, 0) was (NaN, NaN, NaN)."""
    gaps = np.array([0.0, 1e-7, 1e-6, -1e-7])
    x = ((np.pi - gaps)[:, None, None] * _HALF_TURN_AXES).reshape(-1, 3).astype(dtype)
    u = np.asarray(so3.log(so3.exp(x)))
    # log(I exp(x)), through the programs the finite-difference test compiled
    # (a call each costs far less than compiling a vmapped pair).
    _, jf, jr = _JACOBIANS["log_along_group"]
    eye = np.eye(3, dtype=dtype)
    for xi, ui in zip(x, u):
        want = _log_branch_jacobian(xi, ui)
        for jac in (jf, jr):
            J = np.asarray(jac(xi, eye))
            assert J.dtype == dtype
            assert np.all(np.isfinite(J)), (xi, jac)
            np.testing.assert_allclose(J, want, rtol=0, atol=tol, err_msg=str(xi))


def _matrix_conversions(R):
    """log, to_quaternion and to_mrp of R, concatenated: (10,)."""
    return jnp.concatenate([_so3.log(R), _so3.to_quaternion(R), _so3.to_mrp(R)])


@pytest.mark.parametrize("dtype, tol", [(np.float64, 1e-15), (np.float32, 2e-7)])
def test_log_quaternion_and_mrp_derivatives_at_exact_half_turns(dtype, tol):
    """At R = diag(1, -1, -1) and its permutations (w = 0 exactly), the Jacobians
    of log, to_quaternion and to_mrp in R's entries are finite in both modes
    (log's were NaN in reverse mode, also in float64), and log along the group,
    x -> log(R exp(x)) at 0, has the one-sided derivative of the value it
    returns, u: the inverse right Jacobian I + hat(u)/2 + hat(u)^2/pi^2
    (D(pi) = 1/pi^2).  log(R) itself jumps there."""
    Rs = np.stack([np.diag(d) for d in ([1.0, -1, -1], [-1.0, 1, -1], [-1.0, -1, 1])]).astype(dtype)
    for jac in (jax.jacfwd, jax.jacrev):
        J = np.asarray(jax.jit(jax.vmap(jac(_matrix_conversions)))(Rs))
        assert J.dtype == dtype
        assert np.all(np.isfinite(J)), jac.__name__
    u = np.asarray(so3.log(Rs), np.float64)
    np.testing.assert_allclose(np.abs(u), np.pi * np.eye(3), atol=tol)
    _, jf, jr = _JACOBIANS["log_along_group"]
    for R, ui in zip(Rs, u):
        H = np.asarray(_so3.hat(ui))
        want = np.eye(3) + H / 2 + H @ H / np.pi**2
        for jac in (jf, jr):
            J = np.asarray(jac(np.zeros(3, dtype), R))
            assert J.dtype == dtype
            np.testing.assert_allclose(J, want, rtol=0, atol=4 * tol)


# --- dexp and dexpinv -------------------------------------------------------------------


def test_dexp_is_the_derivative_of_exp():
    """d/ds exp(u + s v) at s = 0 equals hat(dexp_u(v)) exp(u) (left trivialisation)."""
    for theta in [0.0, 1e-6, 0.05, 1.0, 3.0, 8.0]:
        u = theta * np.array([0.6, -0.48, 0.64])
        v = np.array([0.2, 0.7, -0.4])
        _, dR = jax.jvp(so3.exp, (jnp.asarray(u),), (jnp.asarray(v),))
        expected = np.asarray(so3.hat(so3.dexp(u, v))) @ np.asarray(so3.exp(u))
        np.testing.assert_allclose(dR, expected, atol=1e-14)
        # Body form: exp(u) hat(dexp_{-u}(v)).
        body = np.asarray(so3.exp(u)) @ np.asarray(so3.hat(so3.dexp(-u, v)))
        np.testing.assert_allclose(dR, body, atol=1e-14)


def test_dexpinv_inverts_dexp():
    norms = np.concatenate([[0.0, 1e-10, 1e-4, 0.05, 0.1, 0.2], RNG.uniform(0.2, 2 * np.pi - 0.3, 20)])
    u = _vectors_with_norms(norms)
    v = _random_vectors((len(norms),))
    np.testing.assert_allclose(so3.dexpinv(u, so3.dexp(u, v)), v, atol=1e-13)
    np.testing.assert_allclose(so3.dexp(u, so3.dexpinv(u, v)), v, atol=1e-13)


@pytest.mark.parametrize("dtype, tol", [(np.float64, 1e-15), (np.float32, 1e-7)])
def test_dexpinv_matches_series_for_small_u(dtype, tol):
    """dexpinv_u(v) = v - u x v / 2 + u x (u x v) / 12 + O(|u|^4 |v|)."""
    v = np.array([0.3, -0.9, 0.4])
    for theta in [0.0, 1e-8, 1e-4, 1e-3]:
        u = theta * np.array([0.6, -0.48, 0.64])
        series = v - 0.5 * np.cross(u, v) + np.cross(u, np.cross(u, v)) / 12.0
        out = so3.dexpinv(u.astype(dtype), v.astype(dtype))
        assert out.dtype == dtype
        np.testing.assert_allclose(out, series, rtol=0, atol=tol + theta**4)


def test_dexpinv_series_term_is_not_truncated():
    """At a moderate angle the closed form differs from the 3-term series by the next
    Bernoulli term -|u|^2/720 u x (u x v) (to O(|u|^6)): the formula is exact, not truncated."""
    u = 0.05 * np.array([0.6, -0.48, 0.64])
    v = np.array([0.3, -0.9, 0.4])
    uuv = np.cross(u, np.cross(u, v))
    series3 = v - 0.5 * np.cross(u, v) + uuv / 12.0
    diff = np.asarray(so3.dexpinv(u, v)) - series3
    np.testing.assert_allclose(diff, (u @ u) / 720.0 * uuv, rtol=1e-3, atol=1e-18)


def test_dexp_dexpinv_float32_finite_gradients_at_zero():
    z = np.zeros(3, np.float32)
    v = np.array([0.3, -0.9, 0.4], np.float32)
    for f in (so3.dexp, so3.dexpinv, so3.rotate):
        for jac in (jax.jacfwd, jax.jacrev):
            J = np.asarray(jax.jit(jac(f))(z, v))
            assert J.dtype == np.float32
            # d/du (v + c1 u x v + ...) at 0 = c1 * (-hat(v)) with c1 = 1/2 (dexp),
            # -1/2 (dexpinv), 1 (rotate).
            c1 = {so3.dexp: 0.5, so3.dexpinv: -0.5, so3.rotate: 1.0}[f]
            np.testing.assert_allclose(J, -c1 * np.asarray(so3.hat(v)), atol=1e-7)


# --- quaternions and Euler angles -------------------------------------------------------


def test_quaternion_and_euler_round_trips():
    R = Rotation.random(20, random_state=2)
    q = np.asarray(so3.to_quaternion(R.as_matrix()))
    q_scipy = R.as_quat()[:, [3, 0, 1, 2]]
    q_scipy *= np.sign(q_scipy[:, :1])
    np.testing.assert_allclose(q, q_scipy, atol=1e-14)
    np.testing.assert_allclose(so3.from_quaternion(q), R.as_matrix(), atol=1e-14)
    ang = np.asarray(so3.to_euler(R.as_matrix()))
    np.testing.assert_allclose(so3.from_euler(ang[:, 0], ang[:, 1], ang[:, 2]), R.as_matrix(), atol=1e-14)
    # Rz(phi) Ry(theta) Rx(psi) is SciPy's extrinsic "xyz" with angles (psi, theta, phi).
    np.testing.assert_allclose(ang, R.as_euler("xyz")[:, ::-1], atol=1e-12)


@pytest.mark.parametrize("terms", [0, 1, 2])
def test_truncated_dexpinv_is_the_series(terms):
    """``dexpinv(u, v, terms=k)`` keeps the series up to ad_u^k exactly, and
    differs from the closed form by O(|u|^(k+1)) (k = 2: by O(|u|^4))."""
    v = np.array([0.3, -0.9, 0.4])
    d = np.array([0.6, -0.48, 0.64])
    series = [v, -0.5 * np.cross(d, v), np.cross(d, np.cross(d, v)) / 12.0]
    gaps = []
    for theta in [0.2, 0.1]:
        u = theta * d
        want = sum(theta**j * series[j] for j in range(terms + 1))
        got = np.asarray(_so3.dexpinv(u, v, terms))
        np.testing.assert_allclose(got, want, atol=1e-15)
        gaps.append(np.linalg.norm(np.asarray(_so3.dexpinv(u, v)) - got))
    # The next non-zero term is ad^(k+1) for k < 2, ad^4 for k = 2.
    expected = {0: 1, 1: 2, 2: 4}[terms]
    assert abs(np.log2(gaps[0] / gaps[1]) - expected) < 0.2, gaps


def test_truncated_dexpinv_rejects_unknown_truncation():
    with pytest.raises(ValueError, match="terms"):
        _so3.dexpinv(np.zeros(3), np.ones(3), 3)


def test_classical_zxz_angles_round_trip_and_name_the_tilt():
    so3 = _so3
    rng = np.random.default_rng(7)
    phi, psi = rng.uniform(-3.1, 3.1, (2, 50))
    theta = rng.uniform(0.01, 3.13, 50)
    R = so3.from_euler(phi, theta, psi, "zxz")
    np.testing.assert_allclose(np.asarray(so3.to_euler(R, "zxz")), np.stack([phi, theta, psi], -1), atol=1e-12)
    # Nutation is the tilt of the body z axis from space z.
    np.testing.assert_allclose(np.arccos(np.asarray(R)[:, 2, 2]), theta, atol=1e-12)
    # At theta = 0 only phi + psi is determined; the round trip still gives R.
    R0 = so3.from_euler(0.4, 0.0, 0.3, "zxz")
    np.testing.assert_allclose(so3.from_euler(*so3.to_euler(R0, "zxz"), "zxz"), R0, atol=1e-15)
    with pytest.raises(ValueError, match="convention"):
        so3.to_euler(R0, "xyz")


# Lierk's "zyx" is R = Rz(phi) Ry(theta) Rx(psi), SciPy's intrinsic "ZYX"; "zxz" is SciPy's "ZXZ".
_SCIPY_SEQ = {"zyx": "ZYX", "zxz": "ZXZ"}
_TO_EULER = jax.jit(_so3.to_euler, static_argnums=1)
_FROM_EULER = jax.jit(_so3.from_euler, static_argnums=3)


def _euler_round_trip_error(R, convention):
    """max |from_euler(to_euler(R)) - R| per matrix, and the angles."""
    a = np.asarray(_TO_EULER(R, convention))
    back = np.asarray(_FROM_EULER(a[..., 0], a[..., 1], a[..., 2], convention))
    return np.abs(back - R).max(axis=(-2, -1)), a


def _angle_gap(a, b):
    return np.abs((a - b + np.pi) % (2 * np.pi) - np.pi)


@pytest.mark.parametrize("convention", ["zyx", "zxz"])
def test_euler_angles_match_scipy_for_random_rotations(convention):
    """SciPy's own as_euler tests, with lierk in its place: 1000 angles (outer
    uniform in (-pi, pi), middle over its whole range) back from SciPy's matrices
    to SciPy's tolerances (relative 1e-12 for zyx, 1.1e-13 for the symmetric zxz,
    which arccos of R_22 missed in 11 of the 1000); and 1000 random rotations
    agree with SciPy's as_euler and come back through from_euler to 1e-14."""
    seq = _SCIPY_SEQ[convention]
    rnd = np.random.RandomState(0)
    n = 1000
    angles = np.empty((n, 3))
    angles[:, 0] = rnd.uniform(-np.pi, np.pi, n)
    angles[:, 1] = rnd.uniform(-np.pi / 2, np.pi / 2, n) if convention == "zyx" else rnd.uniform(0, np.pi, n)
    angles[:, 2] = rnd.uniform(-np.pi, np.pi, n)
    got = np.asarray(_TO_EULER(Rotation.from_euler(seq, angles).as_matrix(), convention))
    np.testing.assert_allclose(got, angles, atol=0, rtol=1e-12 if convention == "zyx" else 1.1e-13)
    R = Rotation.random(n, random_state=4).as_matrix()
    err, got = _euler_round_trip_error(R, convention)
    assert err.max() < 1e-14, err.max()
    assert _angle_gap(got, Rotation.from_matrix(R).as_euler(seq)).max() < 1e-13


def _near_lock_angles(convention):
    """(phi, theta, psi) rows, and each row's distance from the lock: the middle
    angle at the lock exactly and 1e-10..1e-4 from it, for three outer pairs."""
    gaps = np.array([0.0, 1e-10, 1e-9, 1e-8, 1e-7, 1e-6, 1e-5, 1e-4])
    if convention == "zyx":
        middles = np.concatenate([np.pi / 2 - gaps, gaps - np.pi / 2])
    else:
        middles = np.concatenate([gaps, np.pi - gaps])
    outer = np.array([[0.4, 0.3], [-2.5, 3.0], [3.1, -1.2]])
    rows = [[p, m, s] for m in middles for p, s in outer]
    return np.array(rows), np.repeat(np.concatenate([gaps, gaps]), len(outer))


@pytest.mark.parametrize("convention", ["zyx", "zxz"])
def test_euler_angles_at_and_near_the_gimbal_lock(convention):
    """At the lock and 1e-10..1e-4 rad from it (zxz: from theta = 0 and from pi),
    against the angles a matrix was built from (by SciPy) and SciPy's as_euler:

    - the middle angle to rounding: absolutely, and for zxz near 0 relatively
      (arcsin/arccos of one entry missed it by sqrt(eps): 1e-9 rad at 1e-9 from
      the lock, 4.4e-11 at theta = 1e-6);
    - from_euler of the angles is the matrix to 1e-14 at every distance (2e-8 before);
    - the outer angles are those built from, to eps over the distance (how
      ill-determined the lock makes them); at the lock, psi is 0 and phi is SciPy's.
    """
    seq = _SCIPY_SEQ[convention]
    angles, gap = _near_lock_angles(convention)
    R = Rotation.from_euler(seq, angles).as_matrix()
    err, got = _euler_round_trip_error(R, convention)
    assert err.max() < 1e-14, (err.max(), angles[np.argmax(err)])
    theta = angles[:, 1]
    # Relative near theta = 0; absolute (one ulp of pi/2 or pi) elsewhere.
    tol = 1e-15 * np.minimum(np.abs(theta), 1.0) + 1e-15 * (np.abs(theta) > 1)
    assert np.all(np.abs(got[:, 1] - theta) <= tol), np.max(np.abs(got[:, 1] - theta) / tol)
    scipy = Rotation.from_matrix(R).as_euler(seq, suppress_warnings=True)
    assert np.all(np.abs(got[:, 1] - scipy[:, 1]) <= 2 * tol)
    at_lock = gap == 0
    np.testing.assert_array_equal(got[at_lock, 2], 0.0)
    assert _angle_gap(got[at_lock], scipy[at_lock]).max() < 1e-14
    # SciPy sets psi = 0 within 1e-7 of the lock; lierk only at it.
    off = ~at_lock
    outer_err = _angle_gap(got[off][:, [0, 2]], angles[off][:, [0, 2]]).max(axis=-1)
    assert np.all(outer_err <= 1e-15 / gap[off] + 1e-14), np.max(outer_err * gap[off])


@pytest.mark.parametrize("convention", ["zyx", "zxz"])
def test_euler_float32_round_trip_at_rounding_level(convention):
    """In float32, random rotations and the lock cases above come back through
    from_euler(to_euler(R)) to a few float32 roundings (arcsin lost 1e-4 near the lock)."""
    angles, _ = _near_lock_angles(convention)
    R = np.concatenate(
        [
            Rotation.from_euler(_SCIPY_SEQ[convention], angles).as_matrix(),
            Rotation.random(200, random_state=5).as_matrix(),
        ]
    ).astype(np.float32)
    err, got = _euler_round_trip_error(R, convention)
    assert got.dtype == np.float32
    assert err.max() < 8 * np.finfo(np.float32).eps, err.max()


def _body_rates(angles, convention):
    """B(a), (n, 3, 3): d/dt from_euler(a(t)) = R hat(B(a) a'), the body angular
    velocity of each angle's rate.  zyx: columns Rx(psi)^T Ry(theta)^T e_z,
    Rx(psi)^T e_y, e_x; zxz: Rz(psi)^T Rx(theta)^T e_z, Rz(psi)^T e_x, e_z."""
    _, theta, psi = angles.T
    middle, last = ("Y", "X") if convention == "zyx" else ("X", "Z")
    Rm, Rl = (Rotation.from_euler(ax, t[:, None]).as_matrix() for ax, t in [(middle, theta), (last, psi)])
    axis = {"X": E[0], "Y": E[1], "Z": E[2]}
    c0 = np.einsum("nji,nkj,k->ni", Rl, Rm, E[2])
    c1 = np.einsum("nji,j->ni", Rl, axis[middle])
    c2 = np.broadcast_to(axis[last], c0.shape)
    return np.stack([c0, c1, c2], axis=-1)


@pytest.mark.parametrize("convention", ["zyx", "zxz"])
def test_euler_derivatives_invert_those_of_from_euler(convention):
    """d/dx to_euler(R0 exp(x)) at 0, from both modes' Jacobians in R's entries,
    is the inverse of the body rates of the angles, B(a) (from SciPy's
    elementary rotations), to rounding relative to its size (it grows like
    1/distance) at every distance from the lock down to 1e-10; at the lock
    itself it is finite (psi held at 0; arcsin's derivative was infinite there)."""
    angles, gap = _near_lock_angles(convention)
    R0 = np.asarray(_FROM_EULER(angles[:, 0], angles[:, 1], angles[:, 2], convention))

    def euler(R):
        a = _so3.to_euler(R, convention)
        return a, a

    # Along the group: d/dx R0 exp(x) at 0 is R0 hat(e_k).
    tangents = R0[:, None] @ np.asarray(_so3.hat(E))[None]  # (n, k, 3, 3)
    off = gap > 0
    for jac in (jax.jacfwd, jax.jacrev):
        JR, a0 = (np.asarray(v) for v in jax.jit(jax.vmap(jac(euler, has_aux=True)))(R0))
        assert np.all(np.isfinite(JR)), jac.__name__
        J = np.einsum("nijl,nkjl->nik", JR, tangents)
        prod = np.einsum("nij,njk->nik", _body_rates(a0[off], convention), J[off])
        scale = np.abs(J[off]).max(axis=(-2, -1))
        assert np.all(np.abs(prod - np.eye(3)).max(axis=(-2, -1)) <= 1e-14 * scale), jac.__name__


# --- modified Rodrigues parameters (Basilisk's sigma_BN) --------------------------

# Generic rotations, the identity, tiny ones, half turns about an axis and a
# generic axis, and angles just below and above pi.
_HALF = np.pi * np.array([[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0], [0.6, 0.0, 0.8]])
MRP_VECTORS = np.concatenate(
    [
        Rotation.random(24, random_state=7).as_rotvec(),
        np.zeros((1, 3)),
        1e-7 * np.array([[1.0, -2.0, 0.5]]),
        _HALF,
        (1 - 1e-9) * _HALF[3:],
        np.array([[0.0, 0.0, np.pi + 1e-6]]),
    ]
)


def test_mrp_matches_scipy_and_stays_in_the_unit_ball():
    R = np.asarray(so3.exp(jnp.asarray(MRP_VECTORS)))
    s = np.array(so3.to_mrp(jnp.asarray(R)))
    assert np.all(np.linalg.norm(s, axis=-1) <= 1 + 1e-15)
    # Away from a half turn the set is unique; at one, sigma and its shadow
    # -sigma are both unit vectors: compare the rotations there.
    ref = Rotation.from_matrix(R).as_mrp()
    generic = np.abs(np.linalg.norm(ref, axis=-1) - 1) > 1e-6
    np.testing.assert_allclose(s[generic], ref[generic], atol=1e-15, rtol=1e-13)
    np.testing.assert_allclose(Rotation.from_mrp(np.array(s)).as_matrix(), R, atol=1e-14)


def test_from_mrp_matches_scipy_for_either_set():
    s = Rotation.from_rotvec(MRP_VECTORS).as_mrp()
    shadow = -s / np.maximum(np.sum(s * s, axis=-1, keepdims=True), 1e-300)
    for sig in (s, shadow[np.linalg.norm(s, axis=-1) > 1e-3]):
        np.testing.assert_allclose(
            np.asarray(so3.from_mrp(jnp.asarray(sig))), Rotation.from_mrp(sig).as_matrix(), atol=1e-14
        )
    assert float(jnp.max(so3.orthogonality_error(so3.from_mrp(jnp.asarray(shadow[:24]))))) < 1e-14


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_from_mrp_of_huge_shadow_sets_is_the_turn_near_the_identity(dtype):
    """sigma = [1e160, 0, 0] is the shadow of [-1e-160, 0, 0], a turn of
    4e-160 rad about -x; the formula's (1 + |sigma|^2)^2 overflowed and it
    gave NaN.  Now formed from the shadow wherever |sigma| > 1."""
    huge = float(np.sqrt(np.finfo(dtype).max))
    for sigma in ([huge * 1e3, 0.0, 0.0], [huge, -2 * huge, 3 * huge], [3.0, -4.0, 12.0]):
        sigma = np.asarray(sigma, dtype)
        m = float(np.max(np.abs(sigma)))
        unit = sigma.astype(np.float64) / m
        shadow = -unit / (m * np.sum(unit**2))  # -sigma/|sigma|^2, without overflow
        R = np.asarray(so3.from_mrp(sigma))
        assert R.dtype == dtype and np.all(np.isfinite(R))
        np.testing.assert_allclose(
            R, Rotation.from_mrp(shadow).as_matrix(), rtol=0, atol=4 * float(np.finfo(dtype).eps)
        )
        if float(np.linalg.norm(shadow)) < 1e-3:
            # I + 4 hat(shadow) to first order: the tiny turn is kept, not rounded away.
            np.testing.assert_allclose(R - np.eye(3), 4 * np.asarray(so3.hat(shadow)), rtol=1e-6)
        for jac in (jax.jit(jax.jacfwd(so3.from_mrp)), jax.jit(jax.jacrev(so3.from_mrp))):
            assert np.all(np.isfinite(np.asarray(jac(sigma))))


@pytest.mark.parametrize(
    "w",
    [np.zeros(3), 1e-9 * np.ones(3), _HALF[0], _HALF[3], (1 - 1e-4) * _HALF[3]],
    ids=["zero", "tiny", "pi-x", "pi-generic", "below-pi"],
)
def test_mrp_derivatives_are_finite_and_right(w):
    w = jnp.asarray(w)
    f = lambda v: so3.to_mrp(so3.exp(v))  # noqa: E731
    for jac in (jax.jacfwd, jax.jacrev):
        J = np.asarray(jac(f)(w))
        assert np.all(np.isfinite(J))
        Jb = np.asarray(jac(so3.from_mrp)(f(w)))
        assert np.all(np.isfinite(Jb))
    if np.linalg.norm(w) < 1:
        # sigma = tan(phi/4) n: d sigma/dw = I/4 at the identity, and
        # from_mrp's Jacobian there is four times the generators.
        np.testing.assert_allclose(jax.jacfwd(f)(w), np.eye(3) / 4, atol=1e-9)
        np.testing.assert_allclose(
            jax.jacfwd(so3.from_mrp)(jnp.zeros(3)), 4 * np.asarray(so3.hat(jnp.eye(3))).transpose(1, 2, 0), atol=0
        )
    else:
        # Off the switching surface, against central differences.
        h = 1e-6
        fd = np.stack([(np.asarray(f(w + h * e)) - np.asarray(f(w - h * e))) / (2 * h) for e in np.eye(3)], -1)
        if float(jnp.linalg.norm(w)) < np.pi:
            np.testing.assert_allclose(jax.jacfwd(f)(w), fd, atol=1e-6)


def test_solution_quaternions_and_mrps_against_scipy():
    body = lierk.FreeRigidBody(np.diag([1.0, 2.0, 3.0]), [0.3, 1.0, 2.5])
    sol = lierk.solve(body, lierk.RKMK4(), 3.0, dt=0.01, saveat=lierk.SaveAt(t0=True, steps=10))
    rot = Rotation.from_matrix(np.asarray(sol.R))
    np.testing.assert_allclose(sol.quaternion(scalar_first=False), rot.as_quat(canonical=True), atol=1e-14)
    q = np.asarray(sol.quaternion())
    np.testing.assert_allclose(q, rot.as_quat(canonical=True, scalar_first=True), atol=1e-14)
    # The body turns through a half turn in this run: the MRPs switch to the
    # shadow set there and stay in the unit ball.
    s = np.array(sol.mrp())
    assert np.max(np.linalg.norm(s, axis=-1)) <= 1 + 1e-15
    assert np.max(np.linalg.norm(np.diff(s, axis=0), axis=-1)) > 1.0
    np.testing.assert_allclose(Rotation.from_mrp(np.array(s)).as_matrix(), sol.R, atol=1e-13)
