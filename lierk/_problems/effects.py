"""Opt-in effects on a rigid body: gravity about a pivot, constant torques, damping.

`lierk.RigidBodyWithEffects` carries the body momentum ``m`` (kg m^2/s, body
frame) as its state ``y`` and integrates Euler's equations with torque,

    dR/dt = R hat(omega),    omega = I^{-1} m,
    dm/dt = m x omega + sum_k tau_k(t, R, m, omega),

where each ``tau_k`` is the body-frame torque (N m) of one effect.  ``R`` maps
body -> space and space ``z`` points up.  The effects are a tuple of immutable
modules and the sum is a Python loop over it, so an effect that a problem
does not hold is never traced: a problem with only `Damping` compiles to the
free body plus one multiply-add (see the jaxpr test in ``tests/test_effects.py``).

Every effect's torque and its addition to ``dm/dt`` are traced inside
``jax.named_scope("lierk_effect_<Name>")``, so they can be found in a jaxpr
printed with ``name_stack=True`` and in profiles.

Each effect also provides

- ``potential(R)``: its potential energy (J), 0 for a non-conservative effect;
  the problem's ``"energy"`` invariant is kinetic energy plus these;
- ``invariants(R, m)``: extra quantities that the free body with this effect
  alone conserves (its docstring says which and when);
- ``conservative``: whether the effect conserves total energy.
"""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.scipy.linalg
import numpy as np
from jax import Array
from jax.typing import ArrayLike

from .. import _validation as validation
from .. import so3

__all__ = [
    "AbstractEffect",
    "Gravity",
    "BodyTorque",
    "SpaceTorque",
    "TimedTorque",
    "Damping",
]


class AbstractEffect(eqx.Module):
    """One contribution to the body-frame torque.

    Subclasses implement `torque`, and `potential`/`invariants` where they apply.
    """

    conservative: ClassVar[bool] = False
    # Whether the torque reads m or omega.  Splitting solvers need each
    # effect's exact flow with R and t fixed (`kick`): for a torque that does
    # not read the momentum that flow is a straight line.  True by default so
    # that an effect written elsewhere is not kicked wrongly.
    reads_momentum: ClassVar[bool] = True
    # Whether the torque depends on time at fixed (R, m): a differentiated
    # adaptive solve then also resolves how fast time turns the torque's
    # linearisation (`RigidBodyWithEffects.mode_frequency`).  True by default,
    # the safe side for an effect written elsewhere.
    depends_on_time: ClassVar[bool] = True

    def torque(self, t: Array, R: Array, m: Array, omega: Array) -> Array:
        """Body-frame torque ``(3,)`` (N m) at time ``t`` (s), attitude ``R``
        ``(3, 3)`` (body -> space), body momentum ``m`` ``(3,)`` (kg m^2/s)
        and body angular velocity ``omega = I^{-1} m`` ``(3,)`` (rad/s).

        The default reads the attitude through `space_vectors` and calls
        `torque_from`; an effect that needs ``R`` otherwise overrides this
        and returns None from `space_vectors`.
        """
        S = self.space_vectors()
        if S is None:
            raise NotImplementedError(f"{type(self).__name__} implements neither torque nor space_vectors/torque_from")
        # In R's dtype: a function torque's vectors come in the default float
        # type, which with x64 on would lift a float32 kick to float64.
        return self.torque_from(t, so3.compose(jnp.asarray(S, R.dtype), R), m, omega)

    def space_vectors(self) -> Array | None:
        """The space-frame vectors ``s_j`` ``(k, 3)`` (a NumPy array when they
        are constants, so that tracing a stage adds no operation to build
        them) whose body-frame images
        ``R^T s_j`` are all the torque needs of the attitude (``(0, 3)`` for a
        torque that ignores it), or None if it reads ``R`` another way.

        With vectors, solver stages rotate only these ``k`` vectors to the
        stage point instead of forming a 3x3 attitude, and the torque is
        `torque_from`.
        """
        return None

    def torque_from(self, t: Array, v: Array, m: Array, omega: Array) -> Array:
        """Body-frame torque ``(3,)`` (N m) from ``v`` ``(k, 3)``, the body images
        ``R^T s_j`` of `space_vectors` (rows), and ``t``, ``m``, ``omega`` as in
        `torque`."""
        raise NotImplementedError

    def kick(self, t: Array, R: Array, m: Array, h: Array, inertia_inv: Array) -> Array:
        """The exact flow of ``dm/dt = torque`` over ``h`` (s) with ``t`` and the
        attitude ``R`` ``(3, 3)`` held fixed, from body momentum ``m`` ``(3,)``;
        ``inertia_inv`` ``(3, 3)`` gives ``omega = inertia_inv @ m``.  The
        splitting solvers' kick.  The default, ``m + h torque``, holds for a
        torque that does not read the momentum (``reads_momentum = False``);
        an effect whose torque does must override this."""
        if self.reads_momentum:
            raise ValueError(
                f"{type(self).__name__} reads the momentum but has no exact kick, so a splitting solver "
                "cannot use it; give it a `kick` method or pick an RKMK solver"
            )
        return m + h * self.torque(t, R, m, inertia_inv @ m)

    def affine_torque(self, t: Array, R: Array, inertia_inv: Array) -> tuple[Array, Array] | None:
        """The torque as ``A m + c`` with ``t`` and ``R`` held fixed: ``(A (3, 3),
        c (3,))``, or None if it is not affine in the momentum.  A kick of
        several effects whose torques all are is then exact (`affine_flow`
        of their sum) instead of a composition.  The default covers torques
        that do not read the momentum (``A = 0``)."""
        if self.reads_momentum:
            return None
        z = jnp.zeros(3, R.dtype)
        return jnp.zeros((3, 3), R.dtype), self.torque(t, R, z, z)

    def potential(self, R: Array) -> Array:
        """Potential energy (J) at attitude ``R`` ``(..., 3, 3)``; 0 unless conservative."""
        return jnp.zeros(R.shape[:-2], R.dtype)

    def invariants(self, R: Array, m: Array) -> dict[str, Array]:
        """Quantities conserved by the free body with this effect alone, besides
        the energy of a conservative effect.  ``R`` ``(..., 3, 3)``, ``m`` ``(..., 3)``."""
        return {}

    def energy_scale(self) -> Array:
        """The energy (J) this effect can give a body that starts at rest, as a
        scale for absolute momentum tolerances; 0 where it has none."""
        return jnp.zeros(())

    def conserved(self, inertia: Array) -> tuple[str, ...]:
        """Keys of `invariants` that the body with this effect alone conserves,
        for a body of ``inertia`` ``(3, 3)`` (kg m^2)."""
        # Only the keys: traced abstractly, nothing computed or compiled.
        keys = jax.eval_shape(self.invariants, jax.ShapeDtypeStruct((3, 3), float), jax.ShapeDtypeStruct((3,), float))
        return tuple(keys)

    def _cast(self, dtype) -> "AbstractEffect":
        """A copy with floating leaves in ``dtype`` (the problem's dtype)."""
        leaves, structure = jax.tree_util.tree_flatten(self)
        arrays = [i for i, x in enumerate(leaves) if eqx.is_array(x)]
        for i, x in zip(arrays, validation.as_jax_each(*(leaves[i] for i in arrays), dtype=dtype)):
            leaves[i] = x
        return jax.tree_util.tree_unflatten(structure, leaves)


def affine_flow(A: Array, c: Array, m: Array, h: Array) -> Array:
    """The exact flow of ``dm/dt = A m + c`` (``A`` ``(3, 3)``, ``c`` ``(3,)``
    constant) over ``h`` from ``m``: one exponential of the 4x4 block
    ``[[A, c], [0, 0]]`` gives ``exp(hA) m + (int_0^h exp(sA) ds) c``."""
    top = jnp.concatenate([A, c[:, None]], axis=1)
    M = jnp.concatenate([top, jnp.zeros((1, 4), m.dtype)], axis=0)
    return (jax.scipy.linalg.expm(h * M) @ jnp.concatenate([m, jnp.ones((1,), m.dtype)]))[:3]


def _scalar(x, name: str, positive: bool = False) -> Array:
    x = validation.check_scalar(x, name, bound="positive" if positive else "non-negative")
    return validation.as_jax(x)


def _vector(x, name: str) -> Array:
    x = validation.asarray(x, name=name)
    return validation.check_vector(x, name, x.dtype)


class Gravity(AbstractEffect):
    """Uniform gravity on a heavy top turning about a fixed pivot.

    The centre of mass sits at ``chi = pivot_to_com`` (body frame, m) from the
    pivot; gravity pulls with ``-M g e3`` in space (``e3`` = space z, up).  The
    body-frame torque about the pivot is

        tau = M g (Gamma x chi),    Gamma = R^T e3 (the vertical in the body frame).

    The problem's inertia must be the one about the pivot (the parallel-axis
    theorem: ``lierk.inertia.parallel_axis(I_cm, M, chi)``), and its momentum
    ``m`` is taken about the pivot: `lierk.heavy_top` builds the problem
    from the inertia about the centre of mass, as a scene's ``pivot`` does.

    Conserves:
        - energy ``omega . I omega / 2 + M g e3 . R chi`` (`potential` is the second term);
        - ``"L_vertical"``: the vertical component of spatial momentum ``e3 . R m``
          (the torque is horizontal);
        - ``"m_chi"``: the body momentum along ``chi``, ``m . chi/|chi|``, when the
          inertia is symmetric about ``chi`` (the Lagrange top; for ``chi`` on
          the body z axis this is ``m3``).  Otherwise it is only a diagnostic.

    Args:
        pivot_to_com: ``(3,)`` body-frame vector from the pivot to the centre of mass (m).
        mass: total mass ``M`` (kg), ``> 0``.
        g: gravitational acceleration (m/s^2), default 9.81, ``>= 0``.
    """

    pivot_to_com: Array
    mass: Array
    g: Array
    conservative: ClassVar[bool] = True

    reads_momentum: ClassVar[bool] = False
    depends_on_time: ClassVar[bool] = False

    def __init__(self, pivot_to_com: ArrayLike, mass: ArrayLike, g: ArrayLike = 9.81):
        self.pivot_to_com = _vector(pivot_to_com, "pivot_to_com")
        self.mass = _scalar(mass, "mass", positive=True)
        self.g = _scalar(g, "g")

    def space_vectors(self):
        return np.eye(3, dtype=self.pivot_to_com.dtype)[2:]  # the vertical e3

    def torque_from(self, t, v, m, omega):
        # v[0] = Gamma = R^T e3, the vertical in the body frame.
        return (self.mass * self.g) * so3.cross(v[0], self.pivot_to_com)

    def potential(self, R):
        return (self.mass * self.g) * jnp.einsum("...j,j->...", R[..., 2, :], self.pivot_to_com)

    def invariants(self, R, m):
        chi = self.pivot_to_com
        axis = chi / jnp.maximum(jnp.linalg.norm(chi), jnp.finfo(chi.dtype).tiny)
        return {
            "L_vertical": jnp.einsum("...j,...j->...", R[..., 2, :], m),
            "m_chi": jnp.einsum("...j,j->...", m, axis),
        }

    def energy_scale(self):
        # The potential's full range: the centre of mass from top to bottom.
        return 2 * self.mass * self.g * jnp.linalg.norm(self.pivot_to_com)

    def conserved(self, inertia):
        keys = ("L_vertical", "m_chi")
        return keys if _symmetric_about(inertia, self.pivot_to_com) else keys[:1]


class BodyTorque(AbstractEffect):
    """A torque ``tau`` (N m) constant in the body frame (a thruster fixed to the body).

    Conserves nothing in general (it does work ``tau . omega``).
    """

    tau: Array

    reads_momentum: ClassVar[bool] = False
    depends_on_time: ClassVar[bool] = False

    def __init__(self, tau: ArrayLike):
        self.tau = _vector(tau, "tau")

    def space_vectors(self):
        return np.zeros((0, 3), self.tau.dtype)

    def torque_from(self, t, v, m, omega):
        return self.tau


class SpaceTorque(AbstractEffect):
    """A torque ``tau`` (N m) constant in the space frame; in the body frame it is
    ``R^T tau``.  Spatial momentum grows linearly, ``L(t) = L(0) + tau t``, exactly.

    Conserves the components of spatial momentum orthogonal to ``tau``
    (``"L_perp"``, their norm ``|L - (L . tau_hat) tau_hat|``); energy is not conserved.
    """

    tau: Array

    reads_momentum: ClassVar[bool] = False
    depends_on_time: ClassVar[bool] = False

    def __init__(self, tau: ArrayLike):
        self.tau = _vector(tau, "tau")

    def space_vectors(self):
        return self.tau[None]

    def torque_from(self, t, v, m, omega):
        return v[0]  # R^T tau

    def invariants(self, R, m):
        L = jnp.einsum("...ij,...j->...i", R, m)
        n = jnp.linalg.norm(self.tau)
        tau_hat = self.tau / jnp.where(n > 0, n, 1.0)
        L_perp = L - jnp.einsum("...j,j->...", L, tau_hat)[..., None] * tau_hat
        return {"L_perp": jnp.linalg.norm(L_perp, axis=-1)}


class TimedTorque(AbstractEffect):
    """A torque that varies in time, fixed in the body or in space: a thruster
    profile or a control input.

    Give it either as samples, ``torque`` ``(n, 3)`` (N m) at ``times`` ``(n,)``
    (s, strictly increasing), interpolated linearly in between and held at the
    end values outside; or as a function ``torque(t) -> (3,)`` of time (s)
    that JAX can trace (it is jitted, vmapped and differentiated with the
    solve).  With ``frame="body"`` the torque turns with the body (a thruster
    on it); with ``frame="space"`` it is ``R^T tau(t)`` in the body frame.

    Samples are array leaves, so a sweep over them does not recompile; a
    function is part of the compiled program.  Piecewise-linear samples have
    kinks: adaptive solvers step through them by rejection, and fixed-step
    methods of order above 2 lose their order on a step that holds one, so
    put sample times on the step grid.

    Conserves nothing in general.

    Args:
        torque: ``(n, 3)`` samples (N m), or a callable ``t -> (3,)``.
        times: ``(n,)`` sample times (s), strictly increasing; only with samples.
        frame: ``"body"`` (default) or ``"space"``.

    Example:
        >>> burn = TimedTorque([[0, 0, 0], [0, 0, 0.5], [0, 0, 0]], times=[0.0, 1.0, 2.0])
        >>> spin_up = TimedTorque(lambda t: jnp.array([0.0, 0.0, 0.1 * jnp.sin(t)]), frame="space")
    """

    fn: object = eqx.field(static=True)
    times: Array | None
    values: Array | None
    frame: str = eqx.field(static=True)
    reads_momentum: ClassVar[bool] = False

    def __init__(self, torque, times: ArrayLike | None = None, frame: str = "body"):
        if frame not in ("body", "space"):
            raise ValueError(f"frame must be 'body' or 'space', got {frame!r}")
        self.frame = frame
        if callable(torque):
            if times is not None:
                raise ValueError("times apply to sampled torques; a torque function takes the time itself")
            out = jax.eval_shape(torque, jax.ShapeDtypeStruct((), jnp.result_type(float)))
            if getattr(out, "shape", None) != (3,):
                raise ValueError(
                    f"a torque function must return shape (3,) for a scalar time, got {getattr(out, 'shape', out)}"
                )
            self.fn, self.times, self.values = torque, None, None
            return
        if times is None:
            raise ValueError("sampled torques need their times (s): TimedTorque(torque, times=...)")
        values = validation.asarray(torque, name="torque")
        times = validation.asarray(times, name="times")
        if times.ndim != 1 or times.shape[0] < 1:
            raise ValueError(f"times must be a non-empty 1-d array (s), got shape {times.shape}")
        if values.shape != (times.shape[0], 3):
            raise ValueError(f"torque must have shape ({times.shape[0]}, 3), one row per time, got {values.shape}")
        dtype = jnp.result_type(values.dtype, times.dtype)
        values = validation.check(values, lambda v: (abs(v) < float("inf")).all(), "torque must be finite, got {value}")
        times = validation.check(times, lambda v: (abs(v) < float("inf")).all(), "times must be finite, got {value}")
        times = validation.check(
            times, lambda v: (v[1:] > v[:-1]).all(), "times must be strictly increasing, got {value}"
        )
        self.fn = None
        self.times, self.values = validation.as_jax(times, dtype), validation.as_jax(values, dtype)

    def at_time(self, t: Array) -> Array:
        """The torque ``(3,)`` (N m) at time ``t`` (s), in the effect's frame."""
        if self.fn is not None:
            return jnp.asarray(self.fn(t))
        return jnp.stack([jnp.interp(t, self.times, self.values[:, j]) for j in range(3)])

    def space_vectors(self):
        dtype = self.values.dtype if self.values is not None else jnp.result_type(float)
        # In space frame the whole R^T is needed: the images of e1, e2, e3.
        return np.eye(3, dtype=dtype) if self.frame == "space" else np.zeros((0, 3), dtype)

    def torque_from(self, t, v, m, omega):
        tau = self.at_time(t).astype(m.dtype)
        # v's rows are R^T e_i, so R^T tau = sum_i tau_i v_i.
        return tau @ v if self.frame == "space" else tau


class Damping(AbstractEffect):
    """Linear viscous damping ``tau = -c omega`` with ``c >= 0`` (N m s).

    Dissipative: the kinetic energy decays at ``dE/dt = -c |omega|^2`` (with
    other effects absent), and ``L`` keeps its direction in space only for a
    spherical body, where ``omega(t) = omega0 exp(-c t / I)``.  Conserves nothing.
    """

    c: Array
    depends_on_time: ClassVar[bool] = False

    def __init__(self, c: ArrayLike):
        self.c = _scalar(c, "c")

    def space_vectors(self):
        return np.zeros((0, 3), self.c.dtype)

    def torque_from(self, t, v, m, omega):
        return -self.c * omega

    def affine_torque(self, t, R, inertia_inv):
        return -self.c * inertia_inv, jnp.zeros(3, R.dtype)

    def kick(self, t, R, m, h, inertia_inv):
        # dm/dt = -c I^{-1} m: m(h) = exp(-c h I^{-1}) m, in I^{-1}'s eigenbasis.
        lam, V = jnp.linalg.eigh(inertia_inv)
        return V @ (jnp.exp(-self.c * h * lam) * (V.T @ m))


def _symmetric_about(inertia, chi, tol: float = 1e-9) -> bool:
    """Whether ``chi`` is an eigenvector of ``inertia`` and the other two
    principal moments are equal (relative tolerance ``tol``)."""
    if validation.is_traced(inertia, chi):
        return False
    I, c = np.asarray(inertia, float), np.asarray(chi, float)
    n = np.linalg.norm(c)
    if n == 0:
        return False
    c = c / n
    Ic = I @ c
    lam = c @ Ic
    scale = np.abs(I).max()
    if np.linalg.norm(Ic - lam * c) > tol * scale:
        return False
    P = np.eye(3) - np.outer(c, c)
    # On the plane orthogonal to chi, I must be a multiple of the identity.
    Ip = P @ I @ P
    mu = 0.5 * np.trace(Ip)
    return bool(np.linalg.norm(Ip - mu * P) <= tol * scale)
