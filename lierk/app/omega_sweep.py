"""A sweep over initial angular velocities, with sensitivities: what
``lierk sweep`` computes, as one library call.

`omega_grid` builds the grid around a scene's omega0; `sweep_omega0` solves
every point with `lierk.sensitivity` in chunks (`lierk.sweep_chunks`), kept
in a resumable `lierk.app.store.ChunkStore` when given a directory, and returns an
`OmegaSweep`: per point the final attitude angle, the sensitivity
``||dR(T)/d omega0||_F`` with its estimated error, the finite-time Lyapunov
exponent of the body's state (`lierk.Sensitivity.ftle`) and, for a torque-free body, the exact flip interval
(`OmegaSweep.summary`: their ranges, as ``lierk sweep`` prints them).
"""

from __future__ import annotations

import dataclasses
import hashlib
import os
from collections.abc import Callable, Sequence

import numpy as np

__all__ = ["OmegaSweep", "omega_grid", "open_sweep_store", "sweep_method", "sweep_omega0"]

# Per point: angle, sensitivity, its error, Lyapunov exponent, flip interval, result, omega0.
_VALUES_PER_POINT = 7


@dataclasses.dataclass(frozen=True)
class OmegaSweep:
    """The outcome of `sweep_omega0`.

    Attributes:
        axes: per component of omega0, its values (rad/s); length 1 when fixed.
        values: per quantity an array of shape `shape`: ``"angle"``
            (``|log R(T)|``, rad), ``"sensitivity"`` (``||dR(T)/d omega0||_F``,
            s), ``"sensitivity_error"`` (its estimated error, s),
            ``"lyapunov"`` (the finite-time Lyapunov exponent of the body's
            state, `lierk.Sensitivity.ftle`, 1/s) and, for a torque-free body,
            ``"flip_interval"`` (s, ``inf``: no flip).  NaN where the point
            failed (except the flip interval, which is exact).
        failed: bool array of shape `shape`: the solve did not succeed.
        t1: the final time T (s).
        method: how the sensitivity was taken (`lierk.sensitivity_method`):
            ``"variational"`` or ``"derivative"``.
    """

    axes: tuple[np.ndarray, np.ndarray, np.ndarray]
    values: dict[str, np.ndarray]
    failed: np.ndarray
    t1: float
    method: str = "derivative"

    @property
    def varied(self) -> list[int]:
        """The components of omega0 that vary (0, 1, 2 for x, y, z)."""
        return [k for k in range(3) if len(self.axes[k]) > 1]

    @property
    def shape(self) -> tuple[int, ...]:
        return tuple(len(self.axes[k]) for k in self.varied)

    @property
    def grid(self) -> np.ndarray:
        """``(*shape, 3)`` the initial angular velocities (rad/s)."""
        return _grid(self.axes).reshape(*self.shape, 3)

    def summary(self) -> str:
        """What ``lierk sweep`` prints about the values, one indented line
        each: how many points failed (if any), the range of the sensitivity
        and its largest estimated relative error, of the Lyapunov exponent
        and, for a torque-free body that flips somewhere, of the flip interval."""
        v, lines = self.values, []
        if self.failed.any():
            lines.append(f"  {int(self.failed.sum())} points failed to integrate (NaN in the outputs)")
        s = v["sensitivity"]
        how = "variational equations" if self.method == "variational" else "derivative of the solve"
        lines.append(
            f"  ||dR(T)/d omega0|| ({how}): {np.nanmin(s):.3g} .. {np.nanmax(s):.3g} s "
            f"(estimated error of it: up to {np.nanmax(v['sensitivity_error'] / s):.1g} relative)"
        )
        lam = v["lyapunov"]
        lines.append(f"  finite-time Lyapunov exponent: {np.nanmin(lam):.3g} .. {np.nanmax(lam):.3g} 1/s")
        f = v["flip_interval"][np.isfinite(v["flip_interval"])] if "flip_interval" in v else ()
        if len(f):
            lines.append(f"  flip interval: {f.min():.3g} .. {f.max():.3g} s")
        return "\n".join(lines)


def omega_grid(
    omega0: Sequence[float],
    ranges: Sequence[tuple[float, float, int] | None] = (None, None, None),
    span: float | None = None,
    n: int = 21,
) -> list[np.ndarray]:
    """The values (rad/s) of each component of omega0 to sweep.

    With any of ``ranges`` given (``(start, stop, count)`` per component),
    those components take ``linspace(start, stop, count)`` and the others
    stay at ``omega0``.  Otherwise the two smallest components of ``omega0``
    vary over ``omega0 +- span`` in ``n`` values; ``span`` defaults to a
    quarter of ``|omega0|``, rounded to two digits (so grids centred on round
    components hit round values).

    Raises:
        ValueError: ``omega0`` is zero and no span or range is given.
    """
    omega0 = np.asarray(omega0, dtype=float)
    if any(r is not None for r in ranges):
        return [np.array([omega0[k]]) if r is None else np.linspace(r[0], r[1], r[2]) for k, r in enumerate(ranges)]
    span = span if span is not None else float(f"{0.25 * float(np.linalg.norm(omega0)):.2g}")
    if not span > 0:
        raise ValueError("the scene's omega0 is zero: give a span or ranges of omega0 to sweep")
    varied = sorted(np.argsort(np.abs(omega0), kind="stable")[:2])
    return [
        np.linspace(omega0[k] - span, omega0[k] + span, n) if k in varied else np.array([omega0[k]]) for k in range(3)
    ]


def _grid(axes) -> np.ndarray:
    return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)


def _checked(scene, axes):
    """``(axes, varied, grid, solve keywords)`` of a sweep of ``scene``."""
    from lierk import num_steps

    if scene.target_error is not None:
        raise ValueError(
            "sweep needs a scene with run.dt or run.rtol: target_error chooses a setting per solve, and the "
            "sensitivity is a derivative through one fixed setting"
        )
    axes = tuple(np.asarray(a, dtype=float).reshape(-1) for a in axes)
    varied = [k for k in range(3) if len(axes[k]) > 1]
    if not varied:
        raise ValueError("nothing to sweep: at least one component of omega0 needs more than one value")
    if len(varied) > 2:
        raise ValueError("at most two components can vary (a heatmap); give the third as a single value")
    kw = dict(scene.solve_kwargs)
    if not scene.adaptive:
        # Under vmap/jit the step count cannot be read from t1 and dt.
        kw["max_steps"] = num_steps(0.0, float(scene.t1), float(kw["dt"]), None)
    return axes, varied, _grid(axes), kw


def sweep_method(scene) -> str:
    """How a sweep of ``scene`` takes each point's sensitivity: ``"variational"``
    (the body's variational equations, integrated with it by the scene's
    solver) where `lierk.sensitivity` offers it, else ``"derivative"`` (the
    derivative of each solve)."""
    from lierk import sensitivity_method

    return sensitivity_method(scene.problem, scene.solver, "omega0", "forward", "auto")


def open_sweep_store(
    scene, axes: Sequence[np.ndarray], directory: str | os.PathLike, *, chunk_size: int = 256, key: dict | None = None
):
    """The `lierk.app.store.ChunkStore` that keeps a sweep's chunks in ``directory``,
    so that a run stopped part-way resumes (`sweep_omega0` with ``store=``).

    Its key holds everything that decides the numbers (grid, solver,
    settings, dtype, chunk size, device layout) and ``key`` (e.g. the scene
    file's hash): a directory holding another run is refused.

    Raises:
        ValueError: the sweep cannot fit in memory or on disk, the directory
            holds another run, or the sweep itself is refused (`sweep_omega0`).
    """
    import jax

    from .store import ChunkStore, check_size

    axes, varied, grid, kw = _checked(scene, axes)
    dtype = scene.problem.R0.dtype
    full_key = {
        **(key or {}),
        "t1": float(scene.t1),
        "grid": hashlib.sha256(np.ascontiguousarray(grid, dtype).tobytes()).hexdigest(),
        "grid_shape": [len(axes[k]) for k in varied],
        "solver": scene.solver.name,
        "sensitivity_method": sweep_method(scene),
        "settings": {k: repr(v) for k, v in sorted(kw.items())},
        "dtype": np.dtype(dtype).name,
        "chunk_size": chunk_size,
        # How the batch is split decides the reduction order, hence the last
        # bit: a resume on another device layout would not be identical.
        "devices": jax.device_count(),
        "processes": jax.process_count(),
    }
    # Per member: R(T) and its three tangents (jacfwd), a few copies each,
    # for the solve and the finer one of the error estimate.
    check_size(
        memory=chunk_size * 2 * 4 * 4 * scene.bytes_per_saved(),
        disk=2 * len(grid) * _VALUES_PER_POINT * np.dtype(dtype).itemsize,
        directory=directory,
        what=f"a sweep of {len(grid)} points",
    )
    return ChunkStore.open(directory, key=full_key, n_chunks=-(-len(grid) // chunk_size))


def sweep_omega0(
    scene,
    axes: Sequence[np.ndarray],
    *,
    chunk_size: int = 256,
    store=None,
    compiling: Callable | None = None,
    on_chunk: Callable[[int], None] | None = None,
) -> OmegaSweep | None:
    """Solve ``scene`` from every omega0 of the grid ``axes`` (`omega_grid`)
    with its sensitivity (`lierk.sensitivity`, forward mode, ``method="auto"``:
    the variational equations where they apply, see `sweep_method`).

    Args:
        scene: a `lierk.app.scene.Scene` with ``run.dt`` or ``run.rtol``.
        axes: per component of omega0, its values (rad/s); at most two vary.
        chunk_size: points solved at once (one compilation for all chunks).
        store: a `ChunkStore` from `open_sweep_store` (same ``axes`` and
            ``chunk_size``): finished chunks are written there and skipped
            when the run is resumed.  None: in memory only.
        compiling: a context manager factory entered while the chunk program
            compiles (a progress bar's).
        on_chunk: called with the number of points done after each chunk.

    Returns:
        An `OmegaSweep`; None in a process other than the first of a
        multi-process run (only the first writes and reads the store).

    Raises:
        ValueError: a ``target_error`` scene (a setting chosen per point is
            not differentiable), or no component or more than two varying.
    """
    import jax
    import jax.numpy as jnp

    from lierk import sensitivity, so3, sweep_chunks

    from ..exact import flip_interval

    axes, varied, grid, kw = _checked(scene, axes)
    problem, solver, t1 = scene.problem, scene.solver, float(scene.t1)
    shape = tuple(len(axes[k]) for k in varied)

    method = sweep_method(scene)

    def point(w):
        s = sensitivity(problem.with_omega0(w), solver, t1, method=method, throw=False, **kw)
        out = {
            "angle": jnp.linalg.norm(so3.log(s.R), axis=-1),
            "sensitivity": jnp.sqrt(jnp.sum(s.jacobian_R**2)),
            "sensitivity_error": s.jacobian_R_error,
            "lyapunov": s.ftle,
            "result": s.result,
        }
        if problem.torque_free:
            out["flip_interval"] = flip_interval(problem.inertia, w)
        return out

    skip = () if store is None else store.done
    writer = jax.process_index() == 0
    done = min(len(skip) * chunk_size, len(grid))
    results = {}
    chunks = sweep_chunks(
        point, np.asarray(grid, problem.R0.dtype), chunk_size=chunk_size, skip=skip, compiling=compiling
    )
    for k, a, b, out in chunks:
        if store is not None and writer:
            store.write(k, out)
        results[k] = out
        done += b - a
        if on_chunk is not None:
            on_chunk(done)
    if not writer:
        return None
    if store is not None:
        res = store.read_all()
    else:
        res = {name: np.concatenate([np.asarray(results[k][name]) for k in sorted(results)]) for name in results[0]}
    res = {k: np.asarray(v).reshape(shape) for k, v in res.items()}
    failed = res.pop("result") != 0
    values = {k: (v if k == "flip_interval" else np.where(failed, np.nan, v)) for k, v in res.items()}
    return OmegaSweep(axes, values, failed, t1, method)
