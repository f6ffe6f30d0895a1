"""What a finished solve says about itself: angular velocity and momentum,
the invariants and how far they moved, and how far ``R`` is from SO(3).

`diagnostics` computes them in one compiled program (no eager ``jax.numpy``
op per quantity) and hands back NumPy arrays, for reports, files and figures.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import equinox as eqx
import numpy as np

__all__ = ["Diagnostics", "diagnostics"]


class Diagnostics(NamedTuple):
    """`diagnostics` of a solve with ``n`` saved points.

    Attributes:
        omega: ``(n, 3)`` body angular velocity (rad/s).
        L: ``(n, 3)`` spatial angular momentum (kg m^2/s): ``R I omega``, with
            reaction wheels' momentum added (`total_momentum`).
        invariants: per name (``problem.invariants``) an ``(n,)`` array.
        drift: per invariant, ``max_t |Q(t) - Q(0)| / |Q(0)|`` (``|Q(0)|``
            taken as 1 when it is 0); conserved or not, see ``problem.conserved()``;
            ``nan`` when ``Q`` is not finite at some saved point.
        orthogonality: ``max_t ||R^T R - I||_F``.
        quaternion: ``(n, 4)`` unit quaternions ``(w, x, y, z)`` of ``R``, ``w >= 0``.
        euler_angles: ``(n, 3)`` `lierk.so3.to_euler` of ``R`` (rad, in
            ``(-pi, pi]``, not unwrapped) in the convention asked for, or
            None if none was.
        flip_interval: a torque-free body's `lierk.exact.flip_interval` (s;
            ``inf``: it never flips), from the problem's ``omega0``; None for
            a body with effects.
    """

    omega: np.ndarray
    L: np.ndarray
    invariants: dict[str, np.ndarray]
    drift: dict[str, float]
    orthogonality: float
    quaternion: np.ndarray
    euler_angles: np.ndarray | None = None
    flip_interval: float | None = None


@eqx.filter_jit
def _compute(problem, R, y, euler_convention):
    from lierk import exact, so3

    omega = problem.angular_velocity(R, y)
    # In this program rather than one of its own: a separate program's trace
    # and cache lookup are a noticeable part of a warm `lierk simulate`.
    flip = exact._flip_interval(problem.inertia, problem.omega0) if problem.torque_free else None
    euler = None if euler_convention is None else so3.to_euler(R, euler_convention)
    # The whole body's (internal rotors included), which they do not change.
    L = so3.matvec(R, problem.total_momentum(R, y))
    return (omega, L, problem.invariants(R, y), so3.orthogonality_error(R), so3.to_quaternion(R), euler, flip)


def diagnostics(problem, sol, *, euler_convention: str | None = None) -> Diagnostics:
    """The `Diagnostics` of ``sol``, an unbatched solve of the rigid body
    ``problem``, over its valid saved points; with ``euler_convention``
    (``"zyx"`` or ``"zxz"``, see `lierk.so3.to_euler`) the Euler angles too."""
    import jax

    _, R, y = sol.trajectory()
    omega, L, inv, orth, q, euler, flip = jax.device_get(_compute(problem, R, y, euler_convention))
    inv = {k: np.asarray(v) for k, v in inv.items()}
    drift = {k: _drift(v) for k, v in inv.items()}
    euler = None if euler is None else np.asarray(euler)
    flip = None if flip is None else float(flip)
    return Diagnostics(np.asarray(omega), np.asarray(L), inv, drift, float(np.max(orth)), np.asarray(q), euler, flip)


def _drift(q: np.ndarray) -> float:
    """``max_t |q(t) - q(0)| / |q(0)|``, or ``nan`` (said, not warned about
    by NumPy) when ``q`` is not finite somewhere."""
    if not np.isfinite(q).all():
        return math.nan
    with np.errstate(over="ignore"):  # a change beyond the largest float is inf
        return float(np.max(np.abs(q - q[0])) / (abs(q[0]) if q[0] != 0 else 1.0))
