"""`sensitivity`: the final state's Jacobian with respect to the inputs, with an error estimate.

The attitude's Jacobian is read in the algebra: a change ``dp`` of an input
moves the final attitude to ``R(t1) exp(hat(J dp))``, so ``J`` is the
derivative of ``log(R(t1)^T R(t1; p + dp))`` at ``dp = 0``: three numbers per
input direction instead of nine, and the form that the growth of
perturbations (the finite-time Lyapunov exponent) and the flip's sensitivity
are read from.  ``jacobian_R = R hat(J)`` gives ``dR(t1)/dp`` entry by entry.

The Jacobian is the derivative of the solve that was run (its steps and, for
adaptive solvers, its step-size decisions held fixed), by forward mode
(`jax.jacfwd`, the default: one pass carries every input direction, through
the solve's adjoint, `ForwardSensitivity` unless ``adjoint=`` says
otherwise, as a user's own `jax.jacfwd` of `solve` does) or
reverse mode (`jax.jacrev`: with the default `ForwardSensitivity` the solve
carries the derivatives and each output reads them; with a reverse adjoint
such as `RecursiveCheckpointAdjoint`, one backward pass per output, six of
them).  The error of each form (`Sensitivity.jacobian_error`,
`Sensitivity.jacobian_R_error`, `Sensitivity.jacobian_y_error`), against the
exact flow's Jacobian, is estimated like `solve`'s ``estimate_error``: by
Richardson's comparison with the Jacobians of a finer solve (``2 dt/3`` for
fixed steps, tolerances divided by 10 for adaptive ones).

``method="variational"`` instead integrates the body's variational equations
with it (`lierk._problems.Variational`): the Jacobian of the exact flow to the
solver's order, not the derivative of the discrete solve.  Per Jacobian
error it was the cheaper of the two on the benchmark's near-axis T-handles
and heavy tops, not on every state (``benchmarks/results/sensitivity.md``); use the default where the derivative
of the computed state is what is needed (an optimiser's line search on a
coarse solve, a check against finite differences of the solve).
"""

from __future__ import annotations

import warnings
from typing import Any, Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jax.typing import ArrayLike

from . import _validation as validation
from . import so3
from ._controller import Controller
from ._global_error import finer_options, richardson
from ._problems import AbstractProblem, AbstractRigidBody, RigidBodyWithEffects, Variational
from ._programs import Program
from ._solution import RESULTS, SaveAt, raise_if_failed
from ._solve import num_steps, solve
from ._solvers import AbstractSplitting
from ._solvers.base import AbstractSolver

__all__ = ["Sensitivity", "sensitivity", "sensitivity_method"]

_INPUTS = ("omega0", "R0", "inertia")


class Sensitivity(eqx.Module):
    """The final state of a solve and its Jacobian with respect to an input ``p``.

    Each Jacobian comes with its own error bar, named after it:
    `jacobian` with `jacobian_error`, `jacobian_R` with `jacobian_R_error`,
    `jacobian_y` with `jacobian_y_error`.

    Attributes:
        R: ``(3, 3)`` attitude at ``t1`` (body -> space).
        y: the problem's extra state at ``t1`` (the body momentum ``m``,
            kg m^2/s, for `RigidBodyWithEffects`; with `ReactionWheels` the
            pair ``(m, Omega)``), or None.
        jacobian: the attitude's Jacobian in the algebra, a pytree like ``p``
            whose leaves have shape ``(3,) + leaf.shape``: ``jacobian[i, ...]``
            is the body-frame rotation vector component ``i`` (rad) per unit
            of the input.  With respect to ``omega0``: ``(3, 3)``, in seconds.
        jacobian_y: ``d y(t1) / d p``, leaves ``y.shape + leaf.shape`` (None
            when the problem has no extra state).
        jacobian_error: estimated Frobenius norm of the error of `jacobian`
            (all inputs together, in its units), against the exact flow's
            Jacobian; NaN when not estimated, inf when the finer solve failed.
        jacobian_R_error: the same for `jacobian_R` (``dR(t1)/dp`` entry by
            entry).  About ``sqrt(2)`` times `jacobian_error`
            (``||R hat(v)||_F = sqrt(2) |v|``), plus the attitude's own error
            carried by ``R``.
        jacobian_y_error: the same for `jacobian_y`, in its units (None when
            the problem has no extra state).
        ftle: the finite-time Lyapunov exponent (1/s) of the body's state
            with respect to ``omega0`` (``wrt="omega0"`` only, else None):
            ``log(sigma_max(Phi)) / T`` with ``T = t1 - t0`` and ``Phi`` the
            ``(6, 3)`` state transition from a perturbation of ``omega0``
            to the final attitude and body angular velocity,
            ``Phi = [Omega jacobian; d omega(t1) / d omega0]``,
            ``omega = I^-1 m`` and ``Omega = |omega0|``.  Both blocks are
            dimensionless: the attitude's perturbation (rad) and the angular
            velocity's (in units of ``Omega``) per relative change of
            ``omega0``.  About a steady spin about the intermediate axis it
            tends to the linear growth rate ``Omega sqrt((I1 - I2)(I2 -
            I3)/(I1 I3))`` (``I2`` the intermediate moment) as ``T`` grows,
            with an offset of order ``1/T``.
            Without exponential growth it still decays only as ``log(T)/T``:
            the attitude's perturbation grows linearly (a sphere has
            ``log(sqrt(1 + (Omega T)^2)) / T``), so compare members at one
            ``T``.
        result: `RESULTS` code of the solve (0 is success).
        stats: the solve's statistics (`Solution.stats`).
        t0, t1: the interval (s).
    """

    R: Array
    y: Any
    jacobian: Any
    jacobian_y: Any
    jacobian_error: Array
    jacobian_R_error: Array
    jacobian_y_error: Array | None
    ftle: Array | None
    result: Array
    stats: dict
    t0: Array
    t1: Array

    @property
    def jacobian_R(self) -> Any:
        """``dR(t1)/dp`` entry by entry: leaves ``(3, 3) + leaf.shape`` (after
        any batch axes), ``R hat(jacobian)``.  Its error bar is
        `jacobian_R_error`."""
        return jax.tree_util.tree_map(lambda J: _jacobian_R(self.R, J), self.jacobian)

    @property
    def error_estimate(self) -> Array:
        """Deprecated: `jacobian_R_error`, the error bar of `jacobian_R`
        (`jacobian`'s is `jacobian_error`)."""
        warnings.warn(
            "Sensitivity.error_estimate is deprecated: it is the error of jacobian_R, now named "
            "jacobian_R_error; the error of jacobian (the algebra form) is jacobian_error",
            DeprecationWarning,
            stacklevel=2,
        )
        return self.jacobian_R_error

    @property
    def lyapunov_exponent(self) -> Array:
        """Deprecated: ``log(sigma_max(J) / T) / T`` with ``J`` the ``(3, 3)``
        algebra Jacobian with respect to ``omega0``, the attitude
        Jacobian's growth beyond the steady turn's ``J = T I``.  It is not
        the finite-time Lyapunov exponent of the body's state, which is
        `ftle`."""
        warnings.warn(
            "Sensitivity.lyapunov_exponent is deprecated: it is log(sigma_max(jacobian) / T) / T, not a "
            "Lyapunov exponent of the body's state; the finite-time Lyapunov exponent is Sensitivity.ftle",
            DeprecationWarning,
            stacklevel=2,
        )
        J = self.jacobian
        if not (isinstance(J, jax.Array | np.ndarray) and J.ndim == self.R.ndim and J.shape[-2:] == (3, 3)):
            raise ValueError("lyapunov_exponent needs the Jacobian with respect to a (3,) input such as omega0")
        T = self.t1 - self.t0
        sigma = jnp.linalg.svd(J, compute_uv=False)[..., 0]
        return jnp.log(sigma / T) / T


def _jacobian_R(R: Array, J: Array) -> Array:
    """``R hat(J)`` along J's component axis: ``R`` ``(*B, 3, 3)`` and ``J``
    ``(*B, 3, *S)`` -> ``(*B, 3, 3, *S)``, with leading batch axes ``B`` (vmap)."""
    nb = R.ndim - 2
    H = so3.hat(jnp.moveaxis(J, nb, -1))  # (*B, *S, 3, 3)
    R = R.reshape(R.shape[:nb] + (1,) * (H.ndim - nb - 2) + (3, 3))
    return jnp.moveaxis(so3.compose(R, H), (-2, -1), (nb, nb + 1))


def _jacobian_algebra(R: Array, dR: Array) -> Array:
    """``vee(R^T dR)`` along dR's two leading axes, the inverse of
    `_jacobian_R` for one body: ``R`` ``(3, 3)``, ``dR`` ``(3, 3, *S)`` ->
    ``(3, *S)``."""
    A = so3.compose(jnp.swapaxes(R, -1, -2), jnp.moveaxis(dR, (0, 1), (-2, -1)))  # (*S, 3, 3)
    return jnp.moveaxis(so3.vee(A), -1, 0)


def _check_input(problem: AbstractProblem, wrt) -> None:
    """`_input`'s refusals, without computing the input's value (a named
    input of a rigid body needs nothing computed to be accepted)."""
    if callable(wrt) and not isinstance(wrt, str):
        _input(problem, wrt)  # the selector must run to be checked
    elif wrt not in _INPUTS:
        raise ValueError(f"wrt must be one of {_INPUTS} or a function selecting fields of the problem, got {wrt!r}")
    elif not isinstance(problem, AbstractRigidBody):
        raise ValueError(
            f"wrt={wrt!r} needs a rigid-body problem with omega0 (FreeRigidBody, ...), got {type(problem).__name__}"
        )


def _input(problem: AbstractProblem, wrt) -> tuple[Any, Callable[[Any], AbstractProblem]]:
    """``(p0, rebuild)``: the input's value and the problem as a function of it."""
    if callable(wrt) and not isinstance(wrt, str):
        try:
            p0 = wrt(problem)
        except Exception as e:  # noqa: BLE001 - any failure of the user's selector is reported as such
            raise ValueError(f"wrt=: the selector failed on the problem: {e}") from None
        leaves = jax.tree_util.tree_leaves(p0)
        if not leaves or not all(eqx.is_inexact_array(x) for x in leaves):
            raise ValueError(
                f"wrt= must select floating-point arrays of the problem (e.g. lambda p: p.effects[0].mass), got {p0!r}"
            )
        held = [
            n
            for n in ("inertia", "inertia_inv")
            if isinstance(problem, AbstractRigidBody) and any(x is getattr(problem, n) for x in leaves)
        ]
        if held:
            # The constructor derives the inverse, the initial momentum and
            # the diagonal path from the inertia: replaced alone it gave a
            # Jacobian with none of that (as large an error as the Jacobian).
            raise ValueError(
                f"wrt= selects the body's {held[0]}, from which the problem derives other fields (the inverse "
                "inertia, the initial momentum): perturbed alone it would give a wrong Jacobian; use "
                "wrt='inertia' (omega0 held fixed)"
            )
        try:
            eqx.tree_at(wrt, problem, p0)
        except (ValueError, TypeError):  # a derived value: tree_at finds no leaf, or a property fails on its wrappers
            raise ValueError(
                "wrt= selects something that is not an input of the problem (a derived value, such as a property, "
                f"cannot be perturbed); select a field, or use one of {_INPUTS}"
            ) from None
        return p0, lambda p: eqx.tree_at(wrt, problem, p)
    _check_input(problem, wrt)
    omega0 = problem.omega0
    if wrt == "omega0":
        return omega0, problem.with_omega0
    if wrt == "R0":
        # A turn of the initial attitude by exp(hat(p)) in the body frame,
        # with the body angular velocity held fixed.
        def turned(p):
            # A rotation by construction: not checked again.
            return problem._restarted(so3.compose(problem.R0, so3.exp(p)), problem.y0).with_omega0(omega0)

        return jnp.zeros(3, problem.R0.dtype), turned

    # The inertia with omega0 held fixed.  Rebuilt through the constructor:
    # with a traced inertia the problem takes its general path (a concrete
    # diagonal would read only the diagonal, and its derivative along the
    # off-diagonal entries would be lost).
    def weighed(inertia):
        from ._problems import FreeRigidBody, RigidBodyWithEffects, SpatialFreeRigidBody

        if isinstance(problem, FreeRigidBody) or isinstance(problem, SpatialFreeRigidBody):
            return type(problem)(inertia, omega0, problem.R0)
        if isinstance(problem, RigidBodyWithEffects):
            return RigidBodyWithEffects(inertia, omega0, problem.R0, problem.effects)
        raise ValueError(
            f"wrt='inertia' is not defined for {type(problem).__name__}: select the field with wrt=lambda p: ..."
        )

    return problem.inertia, weighed


def sensitivity(
    problem: AbstractProblem,
    solver: AbstractSolver,
    t1: ArrayLike,
    *,
    wrt: str | Callable = "omega0",
    mode: str = "forward",
    method: str = "derivative",
    estimate_error: bool = True,
    throw: bool = True,
    **solve_options: Any,
) -> Sensitivity:
    """The final state at ``t1`` and its Jacobian with respect to ``wrt``.

    Args:
        problem: e.g. `FreeRigidBody`.
        solver: any lierk solver.
        t1: final time (s).  Numbers (``t1``, and ``t0``, ``dt``, ``rtol``,
            ``atol`` among the solve options) are traced: new values reuse the
            compiled program, except that a fixed-step solve without
            ``max_steps=`` compiles one program per step count.
        wrt: the input: ``"omega0"`` (body angular velocity, rad/s, ``(3,)``),
            ``"R0"`` (a body-frame turn ``R0 exp(hat(p))`` of the initial
            attitude, ``(3,)`` rad, with ``omega0`` held fixed), ``"inertia"``
            (the ``(3, 3)`` tensor, kg m^2, every entry on its own, with
            ``omega0`` held fixed; the tensor is read through its symmetric
            part, so the derivatives along ``I[i, j]`` and ``I[j, i]`` are
            equal, each half the derivative along the symmetric change of
            both), or a function selecting array fields of the
            problem, any pytree of them, e.g. ``lambda p: p.effects[0].mass``
            (not a body's ``inertia`` or ``inertia_inv``, from which it
            derives other fields: that is ``"inertia"``).
        mode: ``"forward"`` (`jax.jacfwd`: cheapest for a few inputs) or
            ``"reverse"`` (`jax.jacrev`: with the default adjoint,
            `ForwardSensitivity`, the same forward pass for a few inputs, and
            twelve reverse passes, R's nine and y's three, for many).
        method: ``"derivative"`` (the derivative of the solve that was run,
            by autodiff through it), ``"variational"`` (the variational
            equations integrated with the body by the same solver: the
            exact flow's Jacobian to the solver's order; a
            `RigidBodyWithEffects` with ``wrt="omega0"`` or ``"R0"``, any
            solver but the splittings, ``mode="forward"``; adaptive steps
            hold the Jacobian to the same tolerances as the state; fixed
            steps must resolve the rotation, since the tableau integrates
            ``xi' = xi x omega`` itself: past its stability bound on the
            imaginary axis, ``|omega| h`` of 2.8 for RK4, the derivatives
            grow without bound, 4e6 relative at 3.2, which the error
            estimate reports), or ``"auto"``: variational where it applies,
            else the derivative (`sensitivity_method` says which).
        estimate_error: also take the Jacobian of a finer solve and fill
            the error bars `Sensitivity.jacobian_error`,
            `Sensitivity.jacobian_R_error` and `Sensitivity.jacobian_y_error`
            (about 2.5x the cost; 3x for fixed steps, whose two solves share
            one compiled loop of the finer solve's length).  Both solves then run under the finer one's
            ``max_steps`` (1.5x or 2x the one given, or the default).
        throw: raise if the solve fails; with False read `Sensitivity.result`.
        **solve_options: passed to `solve`: ``dt=`` (and ``max_steps=``), or
            ``rtol=``/``atol=``/``controller=``, ``t0=``, ``adjoint=``, ...

    Returns:
        A `Sensitivity`.

    Raises:
        ValueError: ``target_error=`` (a setting chosen per member is not
            differentiable), ``saveat=``/``estimate_error=`` among the solve
            options, an unknown ``mode``, or a ``wrt`` that is not an input
            (or selects a body's inertia or its inverse).
    """
    if not isinstance(problem, AbstractProblem):
        raise ValueError(f"problem must be a lierk problem such as FreeRigidBody, got {type(problem).__name__}")
    if "target_error" in solve_options:
        raise ValueError(
            "sensitivity cannot use target_error=: it chooses a setting per solve, and that choice is not "
            "differentiable. Solve with target_error= first, then take the sensitivity at the setting it chose "
            "(dt=sol.stats['dt'] or rtol=sol.stats['rtol'])"
        )
    for name in ("saveat", "estimate_error"):
        if name in solve_options:
            raise ValueError(f"sensitivity takes the state at t1 and its own estimate_error=; {name}= cannot be given")
    if mode not in ("forward", "reverse"):
        raise ValueError(f"mode must be 'forward' or 'reverse', got {mode!r}")
    if not isinstance(estimate_error, bool):
        raise ValueError(f"estimate_error must be True or False, got {estimate_error!r}")
    method = sensitivity_method(problem, solver, wrt, mode, method)
    t1, solve_options = _numbers_traced(problem, t1, solve_options)
    fixed = solve_options.get("dt") is not None
    adjoint = solve_options.get("adjoint")
    if not fixed and method == "derivative" and getattr(adjoint, "resolve_modes", True):
        solve_options = _resolving_modes(solve_options)
    _check_input(problem, wrt)  # bad input raises here, before tracing
    return _sensitivity(problem, solver, t1, wrt, mode, method, estimate_error, throw, solve_options)


# The options that are numbers: traced, so that a new value reuses the program.
_NUMBERS = ("t0", "dt", "rtol", "atol", "dt0")


def _numbers_traced(problem, t1, options: dict) -> tuple[Any, dict]:
    """``t1`` and the numeric ``options`` (Python or NumPy numbers) as NumPy
    arrays in the problem's dtype, which the program traces: a new ``t1`` or
    ``rtol`` runs the compiled program again instead of compiling another.
    A fixed-step solve without ``max_steps`` gets its step count here, from
    the known values (it sizes the program's loop, so a new count is a new
    program; traced values need ``max_steps=`` as in `solve`)."""
    dtype = problem.R0.dtype

    def number(x):
        if isinstance(x, bool) or not isinstance(x, (int, float, np.number, np.ndarray)):
            return x  # JAX arrays (traced or not) and bad values go on as given
        return np.asarray(x, dtype) if np.issubdtype(np.asarray(x).dtype, np.number) else x

    options = {k: (number(v) if k in _NUMBERS and v is not None else v) for k, v in options.items()}
    t1 = number(t1)
    dt = options.get("dt")
    if dt is not None and options.get("max_steps") is None:
        t0 = options.get("t0", 0.0)
        if not validation.is_traced(t0, t1, dt):
            try:
                options["max_steps"] = max(1, num_steps(t0, t1, dt))
            except (TypeError, ValueError, OverflowError, ZeroDivisionError):
                pass  # `solve` names the bad value
    return t1, options


def sensitivity_method(problem, solver, wrt="omega0", mode: str = "forward", method: str = "auto") -> str:
    """The method `sensitivity` takes for these arguments: ``"derivative"``
    or ``"variational"``; ``"auto"`` is variational where it applies.

    Raises:
        ValueError: an unknown ``method``, or ``"variational"`` where it does
            not apply (the message says why).
    """
    if method not in ("derivative", "variational", "auto"):
        raise ValueError(f"method must be 'derivative', 'variational' or 'auto', got {method!r}")
    if method == "derivative":
        return method
    refusal = _variational_refusal(problem, solver, wrt, mode)
    if refusal is None:
        return "variational"
    if method == "auto":
        return "derivative"
    raise ValueError(refusal)


def _variational_refusal(problem, solver, wrt, mode) -> str | None:
    """Why ``method="variational"`` does not cover these arguments, or None."""
    if not isinstance(problem, RigidBodyWithEffects):
        return (
            f"method='variational' needs a RigidBodyWithEffects or FreeRigidBody, got {type(problem).__name__}; "
            "use method='derivative'"
        )
    if isinstance(solver, AbstractSplitting):
        return (
            f"method='variational' needs a solver that advances extra state with its tableau (RKMK, CF4), "
            f"not the splitting {solver.name}; use method='derivative'"
        )
    if not (isinstance(wrt, str) and wrt in ("omega0", "R0")):
        return f"method='variational' covers wrt='omega0' and wrt='R0', got {wrt!r}; use method='derivative'"
    if mode != "forward":
        return "method='variational' integrates the derivatives forward with the body: leave mode='forward'"
    return None


def _variational(problem, wrt: str):
    """The body with its variational equations along the input's unit
    directions: ``omega0`` moves the momentum by ``I e_j``, ``R0`` turns the
    attitude by ``e_j`` (rad, body frame)."""
    eye = jnp.eye(3, dtype=problem.R0.dtype)
    zero = jnp.zeros((3, 3), problem.R0.dtype)
    if wrt == "omega0":
        return Variational(problem, zero, jnp.swapaxes(problem.inertia, 0, 1))
    return Variational(problem, eye, zero)


# One program for the solve, its Jacobian and the estimate's: traced op by op,
# the few array operations around the solve would each be compiled on its own.
# A `wrt` function is static: pass the same function to reuse the compilation.
@Program
def _sensitivity(problem, solver, t1, wrt, mode, method, estimate_error, throw, solve_options) -> Sensitivity:
    p0, rebuild = _input(problem, wrt)
    jac = jax.jacfwd if mode == "forward" else jax.jacrev

    def run(options):
        if method == "variational":
            sol = solve(_variational(problem, wrt), solver, t1, saveat=SaveAt(t1=True), throw=False, **options)
            # The body's state and its derivative are pairs with reaction wheels.
            m, xi, dm = jax.tree_util.tree_map(lambda x: x[-1], sol.y)
            return xi.T, jax.tree_util.tree_map(lambda d: d.T, dm), sol.R[-1], m, sol

        def final(p):
            sol = solve(rebuild(p), solver, t1, saveat=SaveAt(t1=True), throw=False, **options)
            R, y = sol.R[-1], jax.tree_util.tree_map(lambda x: x[-1], sol.y)
            return (R, y), (R, y, sol)

        # The attitude's tangent in the body frame, vee(R^T dR), is formed
        # after the derivative, from R and dR that both depend on the input:
        # as the derivative of log(R_ref^T R) with R_ref = stop_gradient(R) it
        # had the same value, but a derivative of the Jacobian itself (jacfwd
        # of a sensitivity) lost the dR^T dR term, 37% off, with no sign.
        (dR, Jy), (R, y, sol) = jac(final, has_aux=True)(p0)
        return jax.tree_util.tree_map(lambda d: _jacobian_algebra(R, d), dR), Jy, R, y, sol

    if estimate_error:
        fine_options, ratio = finer_options(solver, **solve_options)
        pair = _stacked(solve_options, fine_options)
        if pair is None:
            (J, Jy, R, y, sol), (Jf, Jyf, Rf, _, solf) = run(solve_options), run(fine_options)
        else:
            # One trace of the solve and its Jacobian serves both settings
            # (a scan of 2): the program's largest part appears once, not
            # twice, and compiles once.
            dynamic, static = pair
            kept = []

            def one(d):
                out = run(eqx.combine(d, static))
                arrays, rest = eqx.partition(out, eqx.is_array)
                kept.append(rest)
                return arrays

            both = jax.lax.map(one, dynamic)
            (J, Jy, R, y, sol), (Jf, Jyf, Rf, _, solf) = (
                eqx.combine(jax.tree_util.tree_map(lambda x: x[i], both), kept[0]) for i in (0, 1)
            )
        failed = solf.result != RESULTS.successful

        def bar(gaps):
            est = richardson(jnp.sqrt(sum(jax.tree_util.tree_leaves(gaps))), ratio)
            return jax.lax.stop_gradient(jnp.where(failed, jnp.inf, est))

        sq = lambda a, b: jnp.sum((a - b) ** 2)  # noqa: E731
        est = bar(jax.tree_util.tree_map(lambda a, b: sq(_jacobian_R(R, a), _jacobian_R(Rf, b)), J, Jf))
        est_alg = bar(jax.tree_util.tree_map(sq, J, Jf))
        est_y = None if Jy is None else bar(jax.tree_util.tree_map(sq, Jy, Jyf))
    else:
        J, Jy, R, y, sol = run(solve_options)
        est = est_alg = jnp.full((), jnp.nan, R.dtype)
        est_y = None if Jy is None else est
    t0 = jnp.asarray(solve_options.get("t0", 0.0), R.dtype)
    t1 = jnp.asarray(t1, R.dtype)
    ftle = _ftle(problem, p0, rebuild, R, y, J, Jy, t1 - t0) if isinstance(wrt, str) and wrt == "omega0" else None
    out = Sensitivity(R, y, J, Jy, est_alg, est, est_y, ftle, sol.result, sol.stats, t0, t1)
    if throw:
        out = eqx.tree_at(lambda s: s.result, out, raise_if_failed(sol, True).result)
    return out


def _ftle(problem, omega0, rebuild, R, y, J, Jy, T) -> Array:
    """`Sensitivity.ftle`: ``log(sigma_max([Omega J; d omega / d omega0])) / T``.

    The body momentum's Jacobian is read from those of the final state
    ``(R, y)`` and of the problem itself (`SpatialFreeRigidBody` keeps its
    momentum as ``R^T L``, with ``L`` made from ``omega0``), one input
    direction at a time.  Held constant under differentiation: the singular
    values' derivatives are not defined where they coincide (a sphere's
    three), and would put NaN into the derivatives of everything else."""
    omega0, R, y, J, Jy = jax.lax.stop_gradient((omega0, R, y, J, Jy))
    eye = jnp.eye(3, dtype=R.dtype)
    dR = _jacobian_R(R, J)  # (3, 3, 3), the input direction last

    def momentum(R, y, w):
        return rebuild(w).body_momentum(R, y)

    def column(k):
        dy = None if Jy is None else jax.tree_util.tree_map(lambda d: d[..., k], Jy)
        return jax.jvp(momentum, (R, y, omega0), (dR[..., k], dy, eye[k]))[1]

    dm = jnp.stack([column(k) for k in range(3)], axis=-1)  # (3, 3): d m(t1) / d omega0
    domega = problem.inertia_inv @ dm
    phi = jnp.concatenate([jnp.sqrt(jnp.sum(omega0**2)) * J, domega], axis=0)
    return jnp.log(jnp.linalg.svd(phi, compute_uv=False)[0]) / T


def _stacked(coarse: dict, fine: dict) -> tuple[dict, dict] | None:
    """``(arrays, rest)``: the two solves' options as one, their arrays
    stacked on a leading axis of 2 and everything else shared, or None where
    they differ beyond that (then each is traced on its own).  Both take the
    finer solve's ``max_steps``: a fixed-step loop runs that many masked
    steps (the coarse solve costs the fine one's time: 3 units of work where
    it was 2.5, for half the compilation), an adaptive one stops when done."""
    steps = [o["max_steps"] for o in (coarse, fine) if o.get("max_steps") is not None]
    if steps:
        coarse, fine = ({**o, "max_steps": max(steps)} for o in (coarse, fine))
    (a, rest_a), (b, rest_b) = eqx.partition(coarse, eqx.is_array), eqx.partition(fine, eqx.is_array)
    leaves_a, tree_a = jax.tree_util.tree_flatten(a)
    leaves_b, tree_b = jax.tree_util.tree_flatten(b)
    same_rest = jax.tree_util.tree_structure(rest_a) == jax.tree_util.tree_structure(rest_b) and all(
        x is y or (type(x) is type(y) and isinstance(x, (int, float, str, bool)) and x == y)
        for x, y in zip(jax.tree_util.tree_leaves(rest_a), jax.tree_util.tree_leaves(rest_b))
    )
    if (
        tree_a != tree_b
        or not same_rest
        or any(
            jnp.shape(x) != jnp.shape(y) or jnp.result_type(x) != jnp.result_type(y) for x, y in zip(leaves_a, leaves_b)
        )
    ):
        return None
    return jax.tree_util.tree_unflatten(tree_a, [jnp.stack([x, y]) for x, y in zip(leaves_a, leaves_b)]), rest_a


def _resolving_modes(options: dict) -> dict:
    """Adaptive ``options`` with a `Controller` that resolves the body's
    perturbation modes (``resolve_modes=True``): about a steady spin the
    state's error estimate is 0 and the steps grow until the Jacobian is
    wrong (1e10 off for DP54 on a symmetric body spinning about its axis)."""
    controller = options.get("controller")
    if controller is None:
        if options.get("rtol") is None:
            return options  # `solve` says what is missing
        controller = Controller.from_tolerances(options["rtol"], options.get("atol"))
    if isinstance(controller, Controller):
        controller = controller.resolving_modes()
    return {**{k: v for k, v in options.items() if k not in ("rtol", "atol")}, "controller": controller}
