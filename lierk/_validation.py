"""Input validation, one module for every layer: the problems, the effects,
`lierk.exact`, the controller and `solve` (none of which import each other
for it).

A value known while tracing (a NumPy array or Python number) is checked in
Python and raises `ValueError` at once, naming the value.  A traced value
cannot be inspected, so the same condition is computed inside the program
and a value that fails it comes back as NaN (`check`): a solve finds the NaN
among its inputs and ends with a code of `RESULTS.invalid` and NaN states
(`first_invalid`), which ``throw=True`` raises as an error and
``throw=False`` returns.  So a program holds no host callback for its input
checks, JAX's persistent compilation cache can keep it, and no bad input
comes back as success.
"""

from __future__ import annotations

import contextlib
import contextvars
import functools
import math
import warnings
import weakref
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
        x = _traced(x)
    else:
        try:
            x = np.asarray(x)
        except (TypeError, ValueError) as e:
            raise ValueError(f"{name} must be real numbers, got {x!r} ({e})") from None
    if x.dtype.kind not in "iuf":
        raise ValueError(
            f"{name} must be real numbers, got {show(x) if not is_traced(x) else 'a traced value'} of dtype {x.dtype}"
        )
    if dtype is None and (x.dtype.kind != "f" or x.dtype.itemsize < 4):
        dtype = jnp.result_type(float) if x.dtype.kind != "f" else np.float32
    if is_traced(x):
        return _traced(x, dtype)
    return x if dtype is None else x.astype(jax.dtypes.canonicalize_dtype(dtype))


def as_jax(x, dtype=None):
    """``x`` as a JAX array (in ``dtype`` if given): a traced value cast as
    it is, a concrete one converted by NumPy and put on the device.  Unlike
    ``jnp.asarray``, which compiles a small program per shape and dtype, this
    compiles nothing on concrete values (host paths: validation, problems
    built from a scene)."""
    if is_traced(x):
        return _traced(x, dtype)
    if isinstance(x, jax.Array) and (dtype is None or x.dtype == jax.dtypes.canonicalize_dtype(dtype)):
        return x
    return jax.device_put(_host(x, dtype))


def as_jax_each(*xs, dtype=None) -> tuple:
    """`as_jax` of each of ``xs`` (in ``dtype`` if given), the concrete
    values put on the device together: one transfer instead of one per value,
    each a part of a call from Python.  (Keeping the transfers of
    recurring scalars for later calls was tried: a shared array broke JAX's
    dispatch of a ``jit(vmap)`` of a solve on its second call, "Execution
    supplied 1 arguments but compiled program expected 14", jax 0.10.)"""
    out, put = list(xs), []
    for i, x in enumerate(xs):
        if is_traced(x) or isinstance(x, jax.Array):
            out[i] = as_jax(x, dtype)
        else:
            out[i] = _host(x, dtype)
            put.append(i)
    for i, x in zip(put, jax.device_put([out[i] for i in put])):
        out[i] = x
    return tuple(out)


def _host(x, dtype=None) -> np.ndarray:
    x = np.asarray(x)
    return x if dtype is None else x.astype(jax.dtypes.canonicalize_dtype(dtype))


def _traced(x, dtype=None):
    """A traced ``x`` as a JAX value (of ``dtype`` if given), with no
    operation where it is one already: under an eager `jax.jacfwd` or
    `jax.grad` every operation on it, a cast to its own dtype included,
    compiles a program."""
    if not isinstance(x, jax.core.Tracer):
        x = jnp.asarray(x)
    if dtype is None or (x.dtype == jnp.dtype(dtype) and not x.aval.weak_type):
        return x
    return x.astype(dtype)


def all_finite(tree, *, compact: bool = False) -> jax.Array:
    """Whether every entry of every array leaf of ``tree`` is finite (a traced
    bool).  ``compact`` (one body's form, `lierk._programs`): one reduction
    over all the entries, which XLA compiles as one kernel instead of one per
    leaf; a batch runs slower that way."""
    leaves = jax.tree_util.tree_leaves(tree)
    if not leaves:
        return jnp.asarray(True)
    if compact:
        dtype = jnp.result_type(*leaves)
        return jnp.all(jnp.isfinite(jnp.concatenate([jnp.ravel(x).astype(dtype) for x in leaves])))
    return jnp.all(jnp.stack([jnp.all(jnp.isfinite(x)) for x in leaves]))


def is_traced(*xs) -> bool:
    return any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree_util.tree_leaves(xs))


@contextlib.contextmanager
def checked_on_host():
    """Deprecated, and does nothing: traced inputs are checked inside the
    program, with no host callback (a bad one ends the solve with
    `RESULTS.invalid`), so every program can live in JAX's persistent
    compilation cache and there is nothing to turn off.  Kept for one
    release; remove the ``with`` block."""
    warnings.warn(
        "lierk.checked_on_host() is deprecated and does nothing: traced inputs are checked inside the program "
        "(a bad one ends the solve with a code of lierk.RESULTS.invalid), with no host callback; remove the with block",
        DeprecationWarning,
        stacklevel=3,
    )
    yield


def checking_on_host() -> bool:
    """Deprecated: always False (see `checked_on_host`)."""
    return False


def first_invalid(tree) -> Array:
    """Whether some floating entry of ``tree``'s array leaves is NaN (a
    traced bool): an input that is NaN, or that failed its `check` inside
    the program.  Infinite values pass (a tolerance's ``dtmax`` may be
    ``inf``); those that must be finite are checked to be."""
    leaves = [x for x in jax.tree_util.tree_leaves(tree) if eqx.is_array(x) and jnp.issubdtype(x.dtype, jnp.inexact)]
    if not leaves:
        return jnp.asarray(False)
    return functools.reduce(jnp.logical_or, [jnp.any(jnp.isnan(x)) for x in leaves])


def check(x, ok: Callable, message: str, *, reads=()):
    """Return ``x``, raising ``ValueError(message)`` if ``ok(x)`` is false.

    ``ok`` must work on NumPy and on JAX arrays (use ``xnp``-agnostic operators or
    the array's own methods).  ``reads``: the other values ``ok`` reads (``t0``
    in ``t1 >= t0``).  When ``x`` or one of them is traced, the check is made
    inside the program: ``x`` comes back NaN (every floating entry of it)
    where ``ok`` fails, which the solve reports (`first_invalid`).  Keep the
    returned ``x``, or the check is dead code.
    """
    traced = is_traced(x, reads)
    if traced:
        x = jax.tree_util.tree_map(_traced, x)
        predicate = _Predicate.of(ok)
        return _nan_unless(x, ok) if predicate is None else _nan_unless_program(x, predicate)
    if not bool(np.all(ok(np.asarray(x)))):
        raise ValueError(message.format(value=show(x)) if "{value}" in message else message)
    return x


def check_together(checks: list) -> list:
    """`check` for several values at once: ``checks``, a list of ``(x, ok,
    message)`` (``ok(x)`` may read the other values); returns the ``x``s.

    Known values are checked now, in order, as `check` does; each traced one
    becomes NaN where its own ``ok`` fails, all in one compiled program (see
    `_nan_unless_program`).
    """
    xs = [x for x, _, _ in checks]
    traced = [i for i, x in enumerate(xs) if is_traced(x)]
    for i, (x, ok, message) in enumerate(checks):
        if i not in traced:
            check(x, ok, message)
    if not traced:
        return xs
    values = tuple(jax.tree_util.tree_map(_traced, checks[i][0]) for i in traced)
    oks = tuple(checks[i][1] for i in traced)
    predicates = tuple(_Predicate.of(ok) for ok in oks)
    if any(p is None for p in predicates):
        values = _nan_unless_each(values, oks)
    else:
        values = _nan_unless_each_program(values, predicates)
    for i, x in zip(traced, values):
        xs[i] = x
    return xs


def poisoned(x, good):
    """``x`` where the traced bool ``good`` holds, else NaN in every floating
    entry, in value and in every derivative: ``x`` times 1 or NaN, where a
    ``jnp.where`` would hand a Jacobian the finite tangent of a refused value."""

    def leaf(v):
        if not jnp.issubdtype(v.dtype, jnp.inexact):
            return v
        return v * jnp.where(good, jnp.ones((), v.dtype), jnp.full((), jnp.nan, v.dtype))

    return jax.tree_util.tree_map(leaf, x)


def _nan_unless(x, ok: Callable):
    """``x`` as it is where ``ok(x)`` holds (all of it), else NaN in every
    floating entry and its derivatives: a traced input that failed its check."""
    return poisoned(x, jnp.all(ok(x)))


def _nan_unless_each(xs: tuple, oks: tuple) -> tuple:
    return tuple(_nan_unless(x, ok) for x, ok in zip(xs, oks))


class _Predicate:
    """A check's predicate, equal to any other with the same code and the same
    (hashable) closed-over values, so that `_nan_unless_program` compiles once per
    predicate rather than once per call (a call site's lambda is a new object
    each time)."""

    def __init__(self, ok: Callable, key):
        self.ok, self.key = ok, key

    @classmethod
    def of(cls, ok: Callable) -> "_Predicate | None":
        """None where ``ok`` is not a plain function or closes over an
        unhashable value (an array)."""
        code = getattr(ok, "__code__", None)
        if code is None:
            return None
        try:
            # With each value's type: 1 == 1.0 == True, but they trace differently.
            values = [c.cell_contents for c in ok.__closure__ or ()] + list(ok.__defaults__ or ())
            key = (code, tuple((type(v), v) for v in values))
            hash(key)
        except (TypeError, ValueError):
            return None
        return cls(ok, key)

    def __hash__(self):
        return hash(self.key)

    def __eq__(self, other):
        return isinstance(other, _Predicate) and self.key == other.key

    def __call__(self, x):
        return self.ok(x)


# Why a jitted check: a traced value outside `jax.jit` (under an eager
# `jax.jacfwd` or `jax.grad`) runs each operation of the predicate as a
# program of its own, and a rigid body's checks were about 50 of them.
# Inside `jax.jit` the call is inlined.
_nan_unless_program = jax.jit(_nan_unless, static_argnums=1)
_nan_unless_each_program = jax.jit(_nan_unless_each, static_argnums=1)


def show(x) -> str:
    """An array (or number) on one line, six significant digits, as lierk's
    error messages print values: ``show([1, 2.5])`` is ``"[1. , 2.5]"``."""
    return " ".join(np.array2string(np.asarray(x), precision=6, separator=", ").split())


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
    return check(x, ok, f"{name} must be {bound}, a finite number, got {{value}}")


def check_attitude(R0: ArrayLike | None, dtype) -> Array:
    """An initial attitude ``R0`` (body -> space), ``(3, 3)``, checked: finite,
    and a rotation to 1e-6 (``||R^T R - I|| < 1e-6``, ``det R > 0``).
    Returns it as a JAX array of ``dtype`` (the identity for None); raises
    `ValueError` naming ``R0`` otherwise.  A traced ``R0`` is checked in the
    program: NaN where it fails (`check`)."""
    if R0 is None:
        return as_jax(np.eye(3), dtype)
    R0 = asarray(R0, dtype, "R0")
    check_shape(R0, (3, 3), "R0")
    tol = 1e-6
    xp = np if isinstance(R0, np.ndarray) else jnp
    R0 = check(R0, lambda R: (R == R).all() & (abs(R) < float("inf")).all(), "R0 has NaN or inf entries: {value}")
    R0 = check(
        R0,
        lambda R: (xp.linalg.norm(R.T @ R - xp.eye(3, dtype=R.dtype)) < tol) & (xp.linalg.det(R) > 0),
        f"R0 must be a rotation matrix (||R^T R - I|| < {tol:g} and det R = +1), got {{value}}",
    )
    return as_jax(R0)


class _Shown:
    """A leaf of `describe_tree`'s outline, printed as its text."""

    def __init__(self, text: str):
        self.text = text

    def __repr__(self):
        return self.text


def describe_tree(tree) -> str:
    """A pytree as an outline of its arrays' dtypes and shapes, for messages:
    ``(m, speeds)`` of a body with three wheels is ``"(float64[3], float64[3])"``."""

    def leaf(x):
        if hasattr(x, "dtype") and hasattr(x, "shape"):
            return _Shown(f"{np.dtype(x.dtype).name}{list(np.shape(x))}")
        return _Shown(type(x).__name__)

    return repr(jax.tree_util.tree_map(leaf, tree)) if tree is not None else "None"


def check_like(x, reference, name: str):
    """``x`` checked to have the structure, shapes and dtypes of the pytree of
    arrays ``reference`` (a problem's state): returned with the structure of
    ``reference``, each part a JAX array.

    Where ``reference`` has an array, ``x`` may give an array of its shape
    and dtype, or Python numbers (a list), which are converted to its dtype;
    an array of another floating dtype is refused rather than cast (a
    float32 state would lose a float64 body's digits, and float64 on a
    float32 body would not run).  A traced ``x`` is checked the same way
    (shapes and dtypes are known while tracing).  Raises `ValueError` naming
    the part that differs (``name``, ``name[1]``, ...) and what was due."""
    due = describe_tree(reference)
    if reference is None:
        if x is not None:
            raise ValueError(f"{name}: this problem has no state besides R (its y0 is None), got {describe_tree(x)}")
        return None
    structure = jax.tree_util.tree_structure(reference)
    wrong = ValueError(f"{name} must have the structure of the problem's state, {due}, got {describe_tree(x)}")
    try:
        parts = structure.flatten_up_to(x)
    except (TypeError, ValueError):
        raise wrong from None
    # Numbers in a list stand for an array; arrays in one are another structure.
    if any(isinstance(p, (list, tuple)) and any(np.ndim(v) for v in jax.tree_util.tree_leaves(p)) for p in parts):
        raise wrong
    paths = [jax.tree_util.keystr(p) for p, _ in jax.tree_util.tree_flatten_with_path(reference)[0]]
    out = []
    for path, ref, part in zip(paths, jax.tree_util.tree_leaves(reference), parts):
        where = f"{name}{path}"
        dtype = np.dtype(ref.dtype)
        if hasattr(part, "dtype") and hasattr(part, "shape"):
            if np.dtype(part.dtype).kind == "f" and np.dtype(part.dtype) != dtype:
                raise ValueError(
                    f"{where} is {np.dtype(part.dtype).name}, and the problem's state {due} is "
                    f"{dtype.name}: convert it (.astype({dtype.name}))"
                )
        part = asarray(part, dtype, where)
        if np.shape(part) != np.shape(ref):
            trajectory = np.ndim(part) == np.ndim(ref) + 1 and np.shape(part)[1:] == np.shape(ref)
            raise ValueError(
                f"{where} has shape {np.shape(part)}, where the problem's state {due} has "
                f"{np.shape(ref)}" + (": a saved trajectory? pass one state (its last row, [-1])" if trajectory else "")
            )
        out.append(as_jax(part))
    return jax.tree_util.tree_unflatten(structure, out)


def tolerances_below_rounding(rtol: float, atol: float, dtype) -> str | None:
    """Why the tolerances ``rtol`` and ``atol`` (concrete) cannot be met in
    ``dtype``, or None: their sum is below its rounding (eps), and no step
    control can hold a solve to that.  `lierk.solve` refuses them with this
    message, and so does a scene (``run.rtol``, ``run.atol``)."""
    eps = float(np.finfo(dtype).eps)
    total = float(np.asarray(rtol)) + float(np.asarray(atol))
    if total < eps:
        return (
            f"rtol + atol = {total:g} is below the rounding of {np.dtype(dtype).name} (eps = {eps:.2g}): "
            f"no solve can meet it; ask for at least {eps:.2g}"
        )
    return None


def check_vector(x: ArrayLike, name: str, dtype) -> Array:
    x = asarray(x, dtype, name)
    check_shape(x, (3,), name)
    x = check(x, lambda v: (v == v).all() & (abs(v) < float("inf")).all(), f"{name} has NaN or inf entries: {{value}}")
    return as_jax(x)


def rigid_body_inputs(inertia: ArrayLike, omega0: ArrayLike, R0: ArrayLike | None):
    """Validate a rigid body's inertia and initial state, in one common float dtype.

    Besides `check_inertia`'s checks, the body's state must fit the dtype
    (`state_range_error`): checked now when the inertia and ``omega0`` are
    known, in the program (NaN unless it passes: `check`) when either is
    traced.  A concrete
    inertia that is nearly singular is warned about, once per body (see
    `check_inertia`).

    Returns ``(inertia (3, 3), omega0 (3,), R0 (3, 3))``.
    """
    given = inertia
    inertia = check_inertia(inertia)
    dtype = jnp.result_type(inertia.dtype, asarray(omega0, name="omega0").dtype, float)
    inertia = _remember(as_jax(inertia, dtype))
    known = concrete_inertia(inertia, given)
    if known is not None and not _warned(given):
        text = nearly_singular_inertia(known, dtype)
        if text is not None:
            warnings.warn(text, stacklevel=3)
    if is_traced(omega0):
        # Checked at run time with the state's range, as one check.
        omega0 = as_jax(asarray(omega0, dtype, "omega0"))
        check_shape(omega0, (3,), "omega0")
    else:
        omega0 = check_vector(omega0, "omega0", dtype)
    if is_traced(inertia, omega0):
        omega0 = _state_in_range(inertia, omega0)
    else:
        reason = state_range_error(inertia, omega0, dtype)
        if reason is not None:
            raise ValueError(
                f"inertia {show(np.diagonal(inertia) if _diagonal(inertia) else inertia)} kg m^2 "
                f"with omega0 {show(omega0)} rad/s: {reason}"
            )
    return inertia, omega0, check_attitude(R0, dtype)


@jax.jit
def _state_in_range(inertia, omega0):
    """``omega0``, checked in the program (NaN unless it passes): finite,
    and a body state within `state_range_error`'s bounds, as one predicate
    (a NaN or infinite ``omega0`` makes its squares so)."""
    return poisoned(omega0, _in_range(inertia, omega0))


def _in_range(I, w):
    """`state_range_error`'s bounds as a yes or no, from the quantities
    themselves: a moment is a normal number and a square is finite exactly
    when their computed values are (up to the last rounding), with no
    intermediate that overflows sooner.  Entry by entry, with no logarithm,
    reduction or matrix product: XLA compiles the check as one kernel, where
    those were kernels of their own.  (`state_range_error` works in
    logarithms, to name the sizes.)"""
    info = jnp.finfo(w.dtype)
    tiny, big = float(info.tiny), float(info.max)
    tr, minors, det = _principal_invariants(I)
    smallest = det / minors  # 1/tr(I^-1)
    moments = [(x >= tiny) & (x <= big) for x in (tr, smallest, det)]
    Iw = I[:, 0] * w[0] + I[:, 1] * w[1] + I[:, 2] * w[2]

    def dot(a, b):
        ab = a * b
        return ab[0] + ab[1] + ab[2]

    T2 = dot(w, Iw)
    squares = [jnp.isfinite(x) for x in (dot(w, w), dot(Iw, Iw), T2, T2 * tr, T2 * smallest)]
    return functools.reduce(jnp.logical_and, moments + squares)


def _diagonal(I) -> bool:
    I = np.asarray(I)
    return not np.any(I - np.diag(np.diagonal(I)))


def _log_range(dtype) -> tuple[float, float]:
    """log10 of the smallest normal and of the largest number of ``dtype``."""
    info = np.finfo(dtype)
    return math.log10(float(info.tiny)), math.log10(float(info.max))


_MOMENTS = (
    "tr(I), the sum of the principal moments,",
    "1/tr(I^-1), about the smallest principal moment,",
    "det(I), the product of the principal moments,",
)
_SQUARES = ("|omega|^2", "|L|^2 = |I omega|^2", "2T = omega . I omega", "2T tr(I)", "2T / tr(I^-1)")


def _principal_invariants(J):
    """``(tr J, sum of the principal 2x2 minors, det J)`` of a ``(3, 3)`` NumPy
    or JAX array, entry by entry.  For an inertia, ``tr(I^-1) = minors / det``:
    no eigendecomposition."""
    tr = J[0, 0] + J[1, 1] + J[2, 2]
    minors = _principal_minors([[J[i, j] for j in range(3)] for i in range(3)])
    det = (
        J[0, 0] * (J[1, 1] * J[2, 2] - J[1, 2] * J[2, 1])
        - J[0, 1] * (J[1, 0] * J[2, 2] - J[1, 2] * J[2, 0])
        + J[0, 2] * (J[1, 0] * J[2, 1] - J[1, 1] * J[2, 0])
    )
    return tr, minors, det


def _principal_minors(J):
    """The sum of the principal 2x2 minors of ``J``, given as rows of
    entries (``J[i][j]``, scalars or arrays of one shape)."""
    return (
        J[0][0] * J[1][1]
        - J[0][1] * J[1][0]
        + J[0][0] * J[2][2]
        - J[0][2] * J[2][0]
        + J[1][1] * J[2][2]
        - J[1][2] * J[2][1]
    )


def _state_logs(inertia, omega0, xp):
    """log10 of `_MOMENTS` and of `_SQUARES` (``-inf`` for a body at rest),
    two ``(3,)`` and ``(5,)`` arrays, computed from the scaled inertia and
    ``omega0`` so that nothing overflows on the way."""
    I, w = inertia, omega0
    s = xp.max(xp.abs(I))
    s = xp.where(s > 0, s, 1.0)
    J = I / s
    tr, minors, det = _principal_invariants(J)
    ls = xp.log10(s)
    moments = [ls + xp.log10(tr), ls + xp.log10(det / minors), 3 * ls + xp.log10(det)]
    sw = xp.max(xp.abs(w))
    moving = sw > 0
    v = w / xp.where(moving, sw, 1.0)
    lw = xp.log10(xp.where(moving, sw, 1.0))
    Jv = J @ v
    T2 = 2 * lw + ls + xp.log10(v @ Jv)
    squares = [2 * lw + xp.log10(v @ v), 2 * lw + 2 * ls + xp.log10(Jv @ Jv), T2, T2 + moments[0], T2 + moments[1]]
    return xp.stack(moments), xp.where(moving, xp.stack(squares), -xp.inf)


def state_range_error(inertia: ArrayLike, omega0: ArrayLike, dtype=None) -> str | None:
    """Why a body's state does not fit ``dtype`` (default: the float type JAX
    uses now), or None when it does.

    The rigid-body quantities lierk computes are second order in the state:
    the invariants ``|L|^2 = |I omega|^2`` and ``2T = omega . I omega``, and
    ``2T I_k`` beside ``|L|^2`` in the flip test (`lierk.conditions.flip`)
    and the exact solution (`lierk.exact`), which also divides by the
    product of the moments.  The principal moments (as ``tr(I)`` and
    ``1/tr(I^-1)``, within a factor 3 of the largest and the smallest) and
    their product ``det(I)`` must be normal numbers of ``dtype``: neither
    infinite (at 1e150 kg m^2 the exact flip interval came out ``inf``) nor
    below the smallest normal number (where they lose their digits: the
    ``|L|^2`` of a 1e-300 kg m^2 body spinning at 1 rad/s is 0, and its flips
    went unseen).  In float64 that admits moments from about 3e-103 to 5e102
    kg m^2, in float32 from about 2e-13 to 7e12.  ``|omega|^2`` and the
    squares above must be finite (an inertia of 1e100 kg m^2 at 1e55 rad/s
    has ``|L|^2 = 1e310``, and ``|L|`` came out ``nan``); below the smallest
    normal number they may fall, since with moments in range only a body at
    rest to any precision that matters (``|omega|`` under 1e-51 rad/s in
    float64) gets there.  ``inertia`` ``(3, 3)`` positive definite and
    ``omega0`` ``(3,)`` finite, both concrete.
    """
    dtype = jnp.result_type(float) if dtype is None else dtype
    I = np.asarray(inertia, np.float64)
    I = np.diag(I) if I.shape == (3,) else I
    with np.errstate(all="ignore"):
        moments, squares = _state_logs(I, np.asarray(omega0, np.float64), np)
    lo, hi = _log_range(dtype)
    bounds = [(n, x, lo) for n, x in zip(_MOMENTS, moments)] + [(n, x, -math.inf) for n, x in zip(_SQUARES, squares)]
    for name, x, low in bounds:
        if not low <= x <= hi:
            info = np.finfo(dtype)
            return (
                f"{name} = {_power_of_ten(x)} {'overflows' if x > hi else 'underflows'} {np.dtype(dtype).name}, "
                f"whose normal numbers lie between {float(info.tiny):.2g} and {float(info.max):.2g} "
                "(lierk forms |L|^2, 2T, 2T I_k and det(I) from the body); give it in other units"
            )
    return None


def _power_of_ten(x: float) -> str:
    """``10**x`` written out, for exponents beyond any float: ``"1e+600"``."""
    if x == -math.inf:
        return "0"
    e = math.floor(x)
    m = 10 ** (x - e)
    if round(m, 1) >= 10:
        m, e = m / 10, e + 1
    return f"{m:.2g}e{e:+03d}"


def rigid_body_state(inertia: ArrayLike, omega0: ArrayLike, R0: ArrayLike | None):
    """`rigid_body_inputs` and the inverse inertia: ``(inertia (3, 3),
    inertia_inv (3, 3), omega0 (3,), R0 (3, 3))``."""
    checked, omega0, R0 = rigid_body_inputs(inertia, omega0, R0)
    return checked, inverse_inertia(checked, inertia), omega0, R0


def inverse_inertia(inertia: Array, given: ArrayLike | None = None) -> Array:
    """``I^-1`` ``(3, 3)`` in ``inertia``'s dtype, for a checked ``inertia``
    (`check_inertia`, `rigid_body_inputs`) and, if it differs, the argument
    as ``given`` (``(3,)`` or ``(3, 3)``).

    A known inertia (`concrete_inertia`) is inverted by NumPy (in float64,
    then rounded).  Inside `jax.jit` the checked copy is traced even when the
    argument is a constant (JAX stages every array it makes), and a traced
    inverse is an LU factorisation: a while loop that XLA compiled into every
    program that builds a body (about 100 of the heavy top's adaptive
    solve's 2,400 instructions).  A traced inertia is inverted in one
    compiled program (`_inverse`)."""
    known = concrete_inertia(inertia, given)
    if known is None:
        return _inverse(inertia)
    return as_jax(np.linalg.inv(known).astype(inertia.dtype))


def concrete_inertia(inertia: ArrayLike, given: ArrayLike | None = None) -> np.ndarray | None:
    """An inertia (``(3,)`` or ``(3, 3)``) as a float64 NumPy ``(3, 3)`` when
    its value is known: itself if concrete, else the argument as ``given``
    if that is.  Inside `jax.jit` a checked copy is staged even when the
    argument is a constant.  None when neither is known."""
    for source in (inertia, given):
        if source is not None and not is_traced(source):
            I = np.asarray(source, np.float64)
            return np.diag(I) if I.shape == (3,) else I
    return None


def concrete_diagonal(inertia: ArrayLike) -> np.ndarray | None:
    """The diagonal ``(3,)`` of a concrete inertia with zero off-diagonal
    entries (given as ``(3,)`` or ``(3, 3)``); None if traced or not diagonal."""
    I = concrete_inertia(inertia)
    if I is None:
        return None
    d = np.diagonal(I)
    return None if np.any(I - np.diag(d)) else d


@jax.jit
def _inverse(inertia: Array) -> Array:
    return jnp.linalg.inv(inertia)


def check_inertia(inertia: ArrayLike) -> Array:
    """Validate an inertia tensor and return it as a ``(3, 3)`` array (a
    traced one as its symmetric part ``(I + I^T)/2``, the same values, so
    that a derivative along one off-diagonal entry keeps it symmetric).

    A concrete inertia whose principal moments break the triangle inequality
    ``I_max <= I_a + I_b`` (no rigid body has them) is warned about, once per
    body: not again when an inertia this module returned (a body's own
    ``inertia``) comes back, say to `lierk.exact`, nor inside
    `inertia_warned`.  A traced inertia is not: a host warning cannot see
    its value, and a run-time one would be a host callback in the program.
    It needs none: the equations are well posed for any positive-definite
    inertia, which is checked at run time, and are solved as given, as they
    are after the warning.

    Args:
        inertia: ``(3, 3)`` symmetric positive-definite matrix, or ``(3,)``
            principal moments (kg m^2).

    Raises:
        ValueError: wrong shape, NaN/inf, not symmetric, or not positive
            definite (when traced, checked in the program: see `check`).
    """
    given = inertia
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
    # (Sylvester); this avoids an eigendecomposition in the traced check.  They
    # are taken of I scaled to entries of at most 1: the determinant is cubic
    # in I, and unscaled it overflowed for moments of 1e150 and vanished for
    # 1e-150 ("not positive definite").
    def positive_definite(I):
        s = abs(I).max()
        I = I / xp.where(s > 0, s, 1.0)
        return (
            (I[0, 0] > 0)
            & (I[0, 0] * I[1, 1] - I[0, 1] * I[1, 0] > 0)
            & (
                I[0, 0] * (I[1, 1] * I[2, 2] - I[1, 2] * I[2, 1])
                - I[0, 1] * (I[1, 0] * I[2, 2] - I[1, 2] * I[2, 0])
                + I[0, 2] * (I[1, 0] * I[2, 1] - I[1, 1] * I[2, 0])
                > 0
            )
        )

    inertia = check(inertia, positive_definite, "inertia must be positive definite, got {value}")
    if not isinstance(inertia, np.ndarray):
        # A traced inertia is read through its symmetric part (the same
        # values): a derivative along one off-diagonal entry (`jax.jacfwd`,
        # `lierk.sensitivity(wrt="inertia")`) moved the tensor off the
        # symmetric matrices, where each solver read it otherwise (Strang's
        # and RKMK4's derivatives were 3.6 and -0.29 for the same entry).
        inertia = 0.5 * (inertia + inertia.T)
    if isinstance(inertia, np.ndarray) and not _warned(given):
        text = impossible_inertia(inertia)
        if text is not None:
            warnings.warn(text, stacklevel=3)
    return _remember(as_jax(inertia))


def impossible_inertia(inertia: ArrayLike, name: str = "inertia") -> str | None:
    """The warning for a concrete, positive-definite ``inertia`` (``(3, 3)``,
    kg m^2) whose principal moments break the triangle inequality
    ``I_max <= I_a + I_b`` (no rigid body has them), naming it ``name``;
    None when they keep it."""
    moments = np.linalg.eigvalsh(np.asarray(inertia, np.float64))
    if moments.max() > 0.5 * moments.sum() * (1 + 1e-9):
        # Canonical test problems (Hairer, Lubich and Wanner's I = (2, 1, 2/3))
        # break it too, so this warns rather than refuses.
        return (
            f"{name} {show(moments)} breaks the triangle inequality I_max <= I_a + I_b: "
            "no rigid body has these principal moments; the equations are solved as given"
        )
    return None


def nearly_singular_inertia(inertia: ArrayLike, dtype, name: str = "inertia") -> str | None:
    """The warning for a concrete, positive-definite ``inertia`` (``(3, 3)``,
    kg m^2) too close to singular for ``dtype`` (``I_min/I_max`` below 1e-10
    in float64, 1e-5 in float32), naming it ``name``; None otherwise."""
    moments = np.linalg.eigvalsh(np.asarray(inertia, np.float64))
    limit = 1e-10 if dtype == jnp.float64 else 1e-5
    if moments.min() < limit * moments.max():
        return (
            f"{name} is nearly singular (I_min/I_max = {moments.min() / moments.max():.1e}): omega = I^-1 m "
            "turns tiny momentum errors into huge spins, so expect a stiff, inaccurate run; "
            "check the units, or drop the rotation about that axis"
        )
    return None


# The inertia arrays `check_inertia` and `rigid_body_inputs` returned, by id:
# a body's own ``inertia``, which the library hands back to them (lierk.exact,
# the flip event, a gravity-gradient effect) and which was warned about when
# the body was built.  Weak: they go when the body does.
_VALIDATED: weakref.WeakValueDictionary = weakref.WeakValueDictionary()
_INERTIA_WARNED = contextvars.ContextVar("lierk_inertia_warned", default=False)


def _remember(x):
    if not is_traced(x):
        _VALIDATED[id(x)] = x
    return x


def _warned(given) -> bool:
    """Whether the warnings about the inertia ``given`` (an argument, as
    passed) have been given already."""
    return _INERTIA_WARNED.get() or _VALIDATED.get(id(given)) is given


@contextlib.contextmanager
def inertia_warned():
    """Build bodies in this block without warning about their inertia (an
    impossible or a nearly singular one): the caller has warned once
    already, in its own words (`lierk.app.scene` names the key), and builds
    the body's effects and problem from it.  Errors are still raised."""
    token = _INERTIA_WARNED.set(True)
    try:
        yield
    finally:
        _INERTIA_WARNED.reset(token)
