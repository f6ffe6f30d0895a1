"""Input validation, one module for every layer: the problems, the effects,
`lierk.exact`, the controller and `solve` (none of which import each other
for it).

A value known while tracing (a NumPy array or Python number) is checked in
Python and raises `ValueError` at once, naming the value.  A traced value
cannot be inspected, so the same condition becomes a run-time check with
`eqx.error_if`, which raises when the compiled program runs.
"""

from __future__ import annotations

import contextlib
import contextvars
import warnings
from typing import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jax.typing import ArrayLike


def asarray(x, dtype=None, name: str = "value"):
    """``x`` as a NumPy array when its value is known now, so that `check` can
    raise while tracing; as a JAX array when it is traced.  (Inside `jax.jit`,
    even ``jnp.asarray(0.1)`` is a tracer, so NumPy is the only way to keep a
    constant inspectable.)  Integers become the default float type and half
    precision becomes float32; booleans, complex numbers and strings raise
    `ValueError` naming ``name`` (a complex value would lose its imaginary
    part without a word)."""
    if is_traced(x):
        x = jnp.asarray(x)
    else:
        try:
            x = np.asarray(x)
        except (TypeError, ValueError) as e:
            raise ValueError(f"{name} must be real numbers, got {x!r} ({e})") from None
    if x.dtype.kind not in "iuf":
        raise ValueError(f"{name} must be real numbers, got {_show(x) if not is_traced(x) else 'a traced value'} of dtype {x.dtype}")
    if dtype is None and (x.dtype.kind != "f" or x.dtype.itemsize < 4):
        dtype = jnp.result_type(float) if x.dtype.kind != "f" else np.float32
    if is_traced(x):
        return x if dtype is None else x.astype(dtype)
    return x if dtype is None else x.astype(jax.dtypes.canonicalize_dtype(dtype))


def as_jax(x, dtype=None):
    """``x`` as a JAX array (in ``dtype`` if given): a traced value cast as
    it is, a concrete one converted by NumPy and put on the device.  Unlike
    ``jnp.asarray``, which compiles a small program per shape and dtype, this
    compiles nothing on concrete values (host paths: validation, problems
    built from a scene)."""
    if is_traced(x):
        x = jnp.asarray(x)
        return x if dtype is None else x.astype(dtype)
    if isinstance(x, jax.Array) and (dtype is None or x.dtype == jax.dtypes.canonicalize_dtype(dtype)):
        return x
    x = np.asarray(x)
    return jax.device_put(x if dtype is None else x.astype(jax.dtypes.canonicalize_dtype(dtype)))


def all_finite(tree) -> jax.Array:
    """Whether every entry of every array leaf of ``tree`` is finite (a traced bool)."""
    return jnp.all(jnp.stack([jnp.all(jnp.isfinite(x)) for x in jax.tree_util.tree_leaves(tree)]))


def is_traced(*xs) -> bool:
    return any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree_util.tree_leaves(xs))


_CHECKED_ON_HOST = contextvars.ContextVar("lierk_checked_on_host", default=False)


@contextlib.contextmanager
def checked_on_host():
    """Trace a block whose traced inputs the caller has already checked on
    the host (say, the step times it computed itself): `check` then passes
    them through instead of adding a run-time check.

    A run-time check is a host callback, and JAX's persistent compilation
    cache does not keep programs with host callbacks: a program traced in
    this block can be loaded from the cache in a later process."""
    token = _CHECKED_ON_HOST.set(True)
    try:
        yield
    finally:
        _CHECKED_ON_HOST.reset(token)


def check(x, ok: Callable, message: str):
    """Return ``x``, raising ``ValueError(message)`` if ``ok(x)`` is false.

    ``ok`` must work on NumPy and on JAX arrays (use ``xnp``-agnostic operators or
    the array's own methods).  For traced ``x`` the check is deferred to run time
    (not made at all inside `checked_on_host`).
    """
    if is_traced(x) and _CHECKED_ON_HOST.get():
        return x
    if is_traced(x):
        import jax.numpy as jnp

        # The value is only known at run time; say which check failed.
        return eqx.error_if(x, ~jnp.all(ok(x)), message.replace("{value}", "a traced value that failed the check"))
    if not bool(np.all(ok(np.asarray(x)))):
        raise ValueError(message.format(value=_show(x)) if "{value}" in message else message)
    return x


def _show(x) -> str:
    return np.array2string(np.asarray(x), precision=6, separator=", ")


def check_shape(x, shape: tuple, name: str):
    if np.shape(x) != shape:
        raise ValueError(f"{name} must have shape {shape}, got shape {np.shape(x)}")


def check_scalar(x, name: str, dtype=None, *, bound: str = "finite"):
    """A real scalar: NumPy when known (checked now), JAX when traced (checked
    at run time), in ``dtype`` (default: float, as `asarray`).  ``bound``:
    ``"finite"``, ``"positive"`` (``> 0``, finite) or ``"non-negative"``."""
    if np.ndim(x) != 0:
        raise ValueError(f"{name} must be a scalar, got shape {np.shape(x)}")
    x = asarray(x, dtype, name)
    inf = float("inf")
    if bound == "finite":
        return check(x, lambda v: (v == v) & (abs(v) < inf), f"{name} must be finite, got {{value}}")
    ok = (lambda v: (v > 0) & (v < inf)) if bound == "positive" else (lambda v: (v >= 0) & (v < inf))
    return check(x, ok, f"{name} must be {bound} and finite, got {{value}}")


def check_attitude(R0: ArrayLike | None, dtype) -> Array:
    """Validate an initial attitude: ``(3, 3)``, finite, in SO(3) to 1e-6."""
    if R0 is None:
        return as_jax(np.eye(3), dtype)
    R0 = asarray(R0, dtype, "R0")
    check_shape(R0, (3, 3), "R0")
    tol = 1e-6
    xp = np if isinstance(R0, np.ndarray) else jnp
    R0 = check(R0, lambda R: (R == R).all() & (abs(R) < float("inf")).all(), "R0 has NaN or inf entries: {value}")
    R0 = check(
        R0,
        lambda R: (xp.linalg.norm(R.T @ R - xp.eye(3)) < tol) & (xp.linalg.det(R) > 0),
        f"R0 must be a rotation matrix (||R^T R - I|| < {tol:g} and det R = +1), got {{value}}",
    )
    return as_jax(R0)


def check_vector(x: ArrayLike, name: str, dtype) -> Array:
    x = asarray(x, dtype, name)
    check_shape(x, (3,), name)
    x = check(x, lambda v: (v == v).all() & (abs(v) < float("inf")).all(), f"{name} has NaN or inf entries: {{value}}")
    return as_jax(x)


def rigid_body_inputs(inertia: ArrayLike, omega0: ArrayLike, R0: ArrayLike | None):
    """Validate a rigid body's inertia and initial state, in one common float dtype.

    Returns ``(inertia (3, 3), omega0 (3,), R0 (3, 3))``.
    """
    inertia = check_inertia(inertia)
    dtype = jnp.result_type(inertia.dtype, asarray(omega0, name="omega0").dtype, float)
    inertia = as_jax(inertia, dtype)
    if not is_traced(inertia):
        moments = np.linalg.eigvalsh(np.asarray(inertia, np.float64))
        limit = 1e-10 if dtype == jnp.float64 else 1e-5
        if moments.min() < limit * moments.max():
            warnings.warn(
                f"inertia is nearly singular (I_min/I_max = {moments.min() / moments.max():.1e}): omega = I^-1 m "
                "turns tiny momentum errors into huge spins, so expect a stiff, inaccurate run; "
                "check the units, or drop the rotation about that axis",
                stacklevel=3,
            )
    omega0 = check_vector(omega0, "omega0", dtype)
    return inertia, omega0, check_attitude(R0, dtype)


def rigid_body_state(inertia: ArrayLike, omega0: ArrayLike, R0: ArrayLike | None):
    """`rigid_body_inputs` and the inverse inertia: ``(inertia (3, 3),
    inertia_inv (3, 3), omega0 (3,), R0 (3, 3))``."""
    inertia, omega0, R0 = rigid_body_inputs(inertia, omega0, R0)
    return inertia, jnp.linalg.inv(inertia), omega0, R0


def check_inertia(inertia: ArrayLike) -> Array:
    """Validate an inertia tensor and return it as a ``(3, 3)`` array.

    Args:
        inertia: ``(3, 3)`` symmetric positive-definite matrix, or ``(3,)``
            principal moments (kg m^2).

    Raises:
        ValueError: wrong shape, NaN/inf, not symmetric, or not positive
            definite (checked at run time with `eqx.error_if` when traced).
    """
    inertia = asarray(inertia, name="inertia")
    xp = np if isinstance(inertia, np.ndarray) else jnp
    if inertia.shape == (3,):
        inertia = xp.diag(inertia)
    if inertia.shape != (3, 3):
        raise ValueError(f"inertia must have shape (3, 3) or (3,), got shape {inertia.shape}")
    inertia = check(
        inertia, lambda I: (I == I).all() & (abs(I) < float("inf")).all(), "inertia has NaN or inf entries: {value}"
    )
    inertia = check(
        inertia,
        lambda I: abs(I - I.T).max() <= 1e-10 * abs(I).max(),
        "inertia must be symmetric, got {value}",
    )
    # The three leading principal minors are positive iff I is positive definite
    # (Sylvester); this avoids an eigendecomposition in the traced check.
    inertia = check(
        inertia,
        lambda I: (I[0, 0] > 0)
        & (I[0, 0] * I[1, 1] - I[0, 1] * I[1, 0] > 0)
        & (
            I[0, 0] * (I[1, 1] * I[2, 2] - I[1, 2] * I[2, 1])
            - I[0, 1] * (I[1, 0] * I[2, 2] - I[1, 2] * I[2, 0])
            + I[0, 2] * (I[1, 0] * I[2, 1] - I[1, 1] * I[2, 0])
            > 0
        ),
        "inertia must be positive definite, got {value}",
    )
    if isinstance(inertia, np.ndarray):
        moments = np.linalg.eigvalsh(inertia)
        if moments.max() > 0.5 * moments.sum() * (1 + 1e-9):
            # Canonical test problems (Hairer, Lubich and Wanner's I = (2, 1, 2/3))
            # break it too, so this warns rather than refuses.
            warnings.warn(
                f"inertia {_show(moments)} breaks the triangle inequality I_max <= I_a + I_b: "
                "no rigid body has these principal moments; the equations are solved as given",
                stacklevel=3,
            )
    return as_jax(inertia)
