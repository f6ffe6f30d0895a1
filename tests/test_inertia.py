"""Claims of lierk.inertia (shapes, composites, validation) and lierk._problems.kinematics
(angular momentum, kinetic energy, body angular velocity)."""

from __future__ import annotations

import math

import jax
import numpy as np
import pytest
from helpers import TEE
from scipy.spatial.transform import Rotation

import lierk
import lierk as body  # angular_momentum, kinetic_energy, body_angular_velocity
from lierk import inertia, so3


def test_tee_handle_reproduces_the_report_to_8_digits():
    I = np.asarray(inertia.tee_handle())
    assert I.shape == (3, 3)
    np.testing.assert_allclose(np.diag(I), [9.82271303e-05, 7.22671030e-05, 1.57865031e-04], rtol=5e-9, atol=0)
    assert np.abs(I - np.diag(np.diag(I))).max() < 1e-20


def test_tee_handle_matches_hand_computation():
    """Two cylinders by textbook formulas and Steiner's theorem, written out by hand,
    for non-default dimensions (so the defaults are not what makes it agree)."""
    rho, r_h, l_h, r_s, l_s = 7800.0, 0.012, 0.1, 0.007, 0.05
    m_h = rho * math.pi * r_h**2 * l_h
    m_s = rho * math.pi * r_s**2 * l_s
    x_s = r_h + l_s / 2  # shaft centre on the x axis; handle centre at the origin
    x_c = m_s * x_s / (m_h + m_s)
    d_h, d_s = x_c, x_s - x_c
    # Handle along y: m r^2/2 about y, m(3r^2 + l^2)/12 about x and z.  Shaft along x.
    Ixx = m_h * (3 * r_h**2 + l_h**2) / 12 + m_s * r_s**2 / 2
    Iyy = m_h * r_h**2 / 2 + m_h * d_h**2 + m_s * (3 * r_s**2 + l_s**2) / 12 + m_s * d_s**2
    Izz = m_h * (3 * r_h**2 + l_h**2) / 12 + m_h * d_h**2 + m_s * (3 * r_s**2 + l_s**2) / 12 + m_s * d_s**2
    I = inertia.tee_handle(handle_length=l_h, handle_radius=r_h, shaft_length=l_s, shaft_radius=r_s, density=rho)
    np.testing.assert_allclose(I, np.diag([Ixx, Iyy, Izz]), rtol=1e-13, atol=1e-20)
    c = inertia.composite(inertia.tee_handle_parts(l_h, r_h, l_s, r_s, rho))
    assert c.mass == pytest.approx(m_h + m_s, rel=1e-14)
    np.testing.assert_allclose(c.center_of_mass, [x_c, 0, 0], rtol=1e-14)


def test_sphere_cylinder_box_textbook():
    np.testing.assert_allclose(inertia.sphere(3.0, 0.5), 0.4 * 3.0 * 0.25 * np.eye(3), rtol=1e-15)
    m, r, l = 2.0, 0.3, 1.2
    axial, transverse = m * r**2 / 2, m * (3 * r**2 + l**2) / 12
    for axis, k in zip("xyz", range(3)):
        d = np.full(3, transverse)
        d[k] = axial
        np.testing.assert_allclose(inertia.solid_cylinder(m, r, l, axis), np.diag(d), rtol=1e-15)
    m, a, b, c = 5.0, 0.2, 0.4, 0.9
    np.testing.assert_allclose(
        inertia.box(m, a, b, c),
        np.diag([m * (b * b + c * c), m * (a * a + c * c), m * (a * a + b * b)]) / 12,
        rtol=1e-15,
    )


def test_composite_of_two_boxes_is_one_box():
    """Two equal boxes side by side along x are one box twice as long (parallel axis)."""
    m, lx, ly, lz = 1.5, 0.2, 0.3, 0.5
    half = inertia.box(m, lx, ly, lz)
    c = inertia.composite([inertia.Part(m, half, [0.0, 1.0, 2.0]), inertia.Part(m, half, [lx, 1.0, 2.0])])
    assert c.mass == pytest.approx(2 * m)
    np.testing.assert_allclose(c.center_of_mass, [lx / 2, 1.0, 2.0], rtol=1e-15)
    np.testing.assert_allclose(c.inertia, inertia.box(2 * m, 2 * lx, ly, lz), rtol=1e-14)


def test_composite_rotates_parts():
    """A z-cylinder rotated onto x is an x-cylinder; a generic rotation gives Q I Q^T."""
    m, r, l = 2.0, 0.1, 0.6
    Q = np.asarray(so3.exp(np.array([0.0, np.pi / 2, 0.0])))  # z -> x
    c = inertia.composite([inertia.Part(m, inertia.solid_cylinder(m, r, l, "z"), [0.0, 0.0, 0.0], Q)])
    np.testing.assert_allclose(c.inertia, inertia.solid_cylinder(m, r, l, "x"), atol=1e-16)
    Q = Rotation.random(random_state=3).as_matrix()
    B = np.asarray(inertia.box(1.0, 0.1, 0.2, 0.3))
    c = inertia.composite([inertia.Part(1.0, B, [0.3, -0.2, 0.1], Q)])
    np.testing.assert_allclose(c.inertia, Q @ B @ Q.T, atol=1e-16)


def test_parallel_axis_is_point_mass_term():
    d = np.array([0.3, -0.4, 1.2])
    I0 = np.asarray(inertia.box(2.0, 0.1, 0.2, 0.3))
    out = np.asarray(inertia.parallel_axis(I0, 2.0, d))
    np.testing.assert_allclose(out, I0 + 2.0 * (d @ d * np.eye(3) - np.outer(d, d)), rtol=1e-15)
    # About the axis through d itself the shift adds nothing.
    n = d / np.linalg.norm(d)
    assert n @ out @ n == pytest.approx(n @ I0 @ n, rel=1e-14)


def test_any_spd_tensor_accepted_and_solved_correctly():
    """A non-diagonal SPD tensor is the T-handle in a rotated body frame: with body
    coordinates b' = Q b one has I' = Q I Q^T, omega' = Q omega and R' = R Q^T."""
    Q = Rotation.from_rotvec([0.4, -0.7, 0.2]).as_matrix()
    I_rot = Q @ TEE @ Q.T
    I_rot = 0.5 * (I_rot + I_rot.T)
    np.testing.assert_allclose(inertia.tensor(I_rot), I_rot, rtol=0, atol=0)
    omega = np.array([1.0, 0.05, 0.3])
    sol = lierk.solve(lierk.FreeRigidBody(TEE, omega), lierk.RKMK4(), 1.0, dt=0.05)
    sol_rot = lierk.solve(lierk.FreeRigidBody(I_rot, Q @ omega, R0=Q.T), lierk.RKMK4(), 1.0, dt=0.05)
    np.testing.assert_allclose(sol_rot.R[-1], np.asarray(sol.R[-1]) @ Q.T, atol=1e-13)


def test_principal_moments_shortcut():
    np.testing.assert_array_equal(inertia.tensor([1.0, 2.0, 3.0]), np.diag([1.0, 2.0, 3.0]))
    # Integer input becomes float.
    assert np.issubdtype(inertia.tensor(np.array([1, 2, 3])).dtype, np.floating)


BAD_INERTIA = [
    (np.array([[1.0, 0.1, 0], [0, 1, 0], [0, 0, 1]]), "symmetric"),
    (np.diag([1.0, -1.0, 2.0]), "positive definite"),
    # Positive diagonal, yet indefinite: eigenvalues 3, -1, 1.
    (np.array([[1.0, 2.0, 0], [2.0, 1.0, 0], [0, 0, 1]]), "positive definite"),
    (np.diag([1.0, 0.0, 1.0]), "positive definite"),
    (np.diag([1.0, np.nan, 1.0]), "NaN"),
    (np.diag([1.0, np.inf, 1.0]), "inf"),
    (np.eye(2), "shape"),
    (np.ones((3, 3, 1)), "shape"),
    (np.ones(4), "shape"),
]


@pytest.mark.parametrize("bad, word", BAD_INERTIA)
def test_bad_inertia_raises_naming_the_problem(bad, word):
    with pytest.raises(ValueError, match=f"inertia.*{word}|{word}.*inertia"):
        inertia.tensor(bad)
    with pytest.raises(ValueError, match=word):
        lierk.FreeRigidBody(bad, [1.0, 0.0, 0.0])


def test_bad_inertia_under_jit_is_checked_in_the_program():
    # A traced inertia is checked inside the program: a bad one makes the
    # body's values NaN, and a solve of that body fails with
    # RESULTS.invalid_problem (raised by throw=True), never result 0.
    make = jax.jit(lambda I: lierk.FreeRigidBody(I, np.array([1.0, 0.0, 0.0])).inertia_inv)
    np.testing.assert_allclose(make(TEE), np.linalg.inv(TEE), rtol=1e-14)
    for bad in (np.diag([1.0, -1.0, 2.0]), np.diag([1.0, np.nan, 2.0])):
        assert np.isnan(np.asarray(make(bad))).all()

    def final(I, throw):
        body = lierk.FreeRigidBody(I, np.array([1.0, 0.2, 0.0]))
        return lierk.solve(body, lierk.RKMK4(), 0.1, dt=0.05, throw=throw)

    sol = jax.jit(lambda I: final(I, False))(np.diag([1.0, -1.0, 2.0]))
    assert int(sol.result) == lierk.RESULTS.invalid_problem
    assert np.isnan(np.asarray(sol.R)).all()
    with pytest.raises(Exception, match="inertia must be positive definite"):
        jax.jit(lambda I: final(I, True))(np.diag([1.0, -1.0, 2.0]))


@pytest.mark.parametrize(
    "call, word",
    [
        (lambda: inertia.sphere(-1.0, 1.0), "mass"),
        (lambda: inertia.sphere(1.0, float("nan")), "radius"),
        (lambda: inertia.solid_cylinder(1.0, 1.0, 1.0, "w"), "axis"),
        (lambda: inertia.box(1.0, 1.0, 0.0, 1.0), "ly"),
        (lambda: inertia.composite([]), "part"),
    ],
)
def test_bad_shape_parameters_raise(call, word):
    with pytest.raises(ValueError, match=word):
        call()


# --- body quantities --------------------------------------------------------------------


def test_body_quantities_consistent():
    rng = np.random.default_rng(4)
    Q = Rotation.random(random_state=5).as_matrix()
    I = Q @ TEE @ Q.T  # non-diagonal
    I = 0.5 * (I + I.T)
    omega = rng.standard_normal((5, 3))
    R = Rotation.random(5, random_state=6).as_matrix()
    m = np.asarray(body.angular_momentum(I, omega))
    np.testing.assert_allclose(m, omega @ I.T, rtol=1e-14)
    L = np.asarray(body.angular_momentum(I, omega, R))
    np.testing.assert_allclose(L, np.einsum("nij,nj->ni", R, m), rtol=1e-13)
    T = np.asarray(body.kinetic_energy(I, omega))
    np.testing.assert_allclose(T, 0.5 * np.einsum("ni,ni->n", omega, m), rtol=1e-14)
    assert np.all(T > 0)
    np.testing.assert_allclose(body.body_angular_velocity(I, R, L), omega, rtol=1e-12)
    # |L| is frame independent; 2T = omega . m.
    np.testing.assert_allclose(np.linalg.norm(L, axis=-1), np.linalg.norm(m, axis=-1), rtol=1e-14)


def test_free_rigid_body_stores_consistent_momentum():
    R0 = Rotation.from_rotvec([0.3, 0.2, -0.1]).as_matrix()
    omega0 = np.array([1.0, 0.05, 0.3])
    p = lierk.FreeRigidBody(TEE, omega0, R0=R0)
    np.testing.assert_allclose(p.L, body.angular_momentum(TEE, omega0, R0), rtol=1e-14)
    np.testing.assert_allclose(p.omega0, omega0, rtol=1e-13)
    np.testing.assert_allclose(p.inertia_inv @ p.inertia, np.eye(3), atol=1e-13)
    inv = p.invariants(np.stack([R0, np.eye(3)]), np.stack([p.y0, p.y0]))
    # At R0 the invariants are the initial energy and |L|.
    assert inv["energy"][0] == pytest.approx(float(body.kinetic_energy(TEE, omega0)), rel=1e-13)
    assert inv["|L|"][0] == pytest.approx(float(np.linalg.norm(TEE @ omega0)), rel=1e-13)
