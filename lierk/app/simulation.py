"""A scene run once and read: what ``lierk simulate`` computes, as one
library call.

`simulate` solves a `lierk.app.scene.Scene` (in pieces, with progress if asked),
with the scene's events and the intermediate-axis flip
(`lierk.app.scene.Scene.with_flip_event`; not with a solver that cannot locate
events, ExplicitEuler, which the report says), and takes its
`lierk.app.diagnostics.diagnostics`; the `Simulation` it returns
gives the arrays ``lierk simulate`` saves (`Simulation.record`, one
``.npz``) and the report it prints (`Simulation.summary`).

Example:
    >>> sim = lierk.app.simulation.simulate(lierk.app.scene.load("examples/tee_handle_a.toml"))
    >>> print(sim.summary())
    >>> np.savez("tee_handle_a.npz", **sim.record())
"""

from __future__ import annotations

import dataclasses
import math
import sys
import time
from typing import Any

import numpy as np

from lierk import AbstractSplitting, Solution

from .diagnostics import Diagnostics

__all__ = ["Simulation", "simulate"]


@dataclasses.dataclass(frozen=True)
class Simulation:
    """A solved scene with its diagnostics.

    Attributes:
        scene: the `lierk.app.scene.Scene` that was solved.
        solution: its `lierk.Solution`.
        diagnostics: `lierk.app.diagnostics.diagnostics` of the solution, with
            its Euler angles in the scene's `lierk.app.scene.Scene.euler_convention`.
        wall: the solve's wall time (s), compilation included.
        flips_untracked: why the flip is not among the scene's events
            although the body has an intermediate axis (the solver's own
            words: ExplicitEuler has no interpolant to locate events on), or
            None.
    """

    scene: Any
    solution: Solution
    diagnostics: Diagnostics
    wall: float
    flips_untracked: str | None = None

    @property
    def flip_interval(self) -> float | None:
        """`lierk.exact.flip_interval` of a torque-free body (``inf``: it
        never flips); None for a body with effects
        (`lierk.app.diagnostics.Diagnostics.flip_interval`)."""
        return self.diagnostics.flip_interval

    @property
    def event_times(self) -> dict[str, np.ndarray]:
        """The times (s) of each of the scene's events, by name
        (`lierk.app.scene.Scene.event_times`)."""
        return self.scene.event_times(self.solution)

    def record(self) -> dict[str, np.ndarray]:
        """The arrays ``lierk simulate`` saves, for `numpy.savez`: ``ts``
        ``(n,)``; ``R`` ``(n, 3, 3)`` (body -> space); ``quaternion``
        ``(n, 4)`` (``w, x, y, z`` of ``R``, ``w >= 0``); ``omega`` and ``L``
        ``(n, 3)`` (`Diagnostics`); ``inertia``, ``omega0``, ``R0``, ``t1``;
        ``solver`` and ``scene`` (names); ``invariant_<name>`` ``(n,)`` per
        invariant (`lierk.app.scene.identifier` of its name: ``|L|`` ->
        ``invariant_abs_L``); ``y``, the state besides ``R`` (when the
        problem has one: the body momentum; with reaction wheels also
        ``wheel_speeds`` ``(n, k)``, rad/s relative to the body); ``error_estimate`` ``(n,)`` (when the solve
        estimated its error); and ``event_<name>``, the times of each event
        (`event_times`)."""
        from .scene import identifier

        scene, sol, diag = self.scene, self.solution, self.diagnostics
        problem = scene.problem
        ts, R, y = sol.trajectory()
        data = {
            "ts": ts,
            "R": R,
            "quaternion": diag.quaternion,
            "omega": diag.omega,
            "L": diag.L,
            "inertia": np.asarray(problem.inertia),
            "omega0": np.asarray(problem.omega0),
            "R0": np.asarray(problem.R0),
            "t1": np.asarray(scene.t1),
            "solver": np.asarray(scene.solver.name),
            "scene": np.asarray(scene.name),
            **{f"invariant_{identifier(k)}": v for k, v in diag.invariants.items()},
        }
        if isinstance(y, tuple):  # reaction wheels: (m, Omega)
            data["y"], data["wheel_speeds"] = y
        elif y is not None:
            data["y"] = y
        if sol.error_estimate is not None:
            data["error_estimate"] = np.asarray(sol.error_estimate)[: len(ts)]
        data.update({f"event_{identifier(k)}": v for k, v in self.event_times.items()})
        return data

    def summary(self) -> str:
        """The report ``lierk simulate`` prints, one line each: the scene; the
        solver, settings, steps, field evaluations (drifts for a splitting)
        and wall time; with
        ``target_error``, the setting chosen and the estimated error; the
        largest relative change of each invariant; ``max ||R^T R - I||``;
        for a torque-free body, the exact flip interval; the times of each
        event, and the one that ended the run."""
        scene, sol, diag = self.scene, self.solution, self.diagnostics
        st = sol.stats
        lines = [
            f"scene {scene.name}" + (f": {scene.description}" if scene.description else ""),
            f"{scene.describe_run(sol)}, t1 = {scene.t1:g} s: {st['num_accepted_steps']} steps"
            + (f" ({st['num_rejected_steps']} rejected)" if st.get("num_rejected_steps") else "")
            + f", {st['num_fevals']} "
            f"{'drifts' if isinstance(scene.solver, AbstractSplitting) else 'field evaluations'}, "
            f"{self.wall:.2f} s wall (incl. compilation)",
        ]
        if scene.target_error is not None:
            est = np.asarray(sol.error_estimate)
            est = est[~np.isnan(est)]  # NaN: times a terminating event kept the run from
            where = "t1" if len(est) == len(sol.ts) else "the last saved time"
            found = ", events found by one more solve at that setting" if scene.events else ""
            lines.append(
                f"  target_error {scene.target_error:.3g}: chose {sol.chosen_setting()} "
                f"after {st['num_solves']} solves (steps above: the last, finest solve{found}); "
                f"estimated error at {where} {est[-1]:.2e}, max over saved times {est.max():.2e}"
            )
        conserved = scene.problem.conserved()
        for k, v in diag.drift.items():
            note = "" if k in conserved else "  (not conserved by this scene)"
            shown = f"{v:.2e}" if math.isfinite(v) else f"not finite ({k} is inf or nan at a saved time)"
            lines.append(f"  max relative change of {k}: {shown}{note}")
        lines.append(f"  max ||R^T R - I||: {diag.orthogonality:.2e}")
        flip = self.flip_interval
        if flip is not None and math.isfinite(flip):
            lines.append(f"  intermediate-axis flip interval (exact): {flip:.3f} s")
        elif flip is not None:
            lines.append("  no flip of the intermediate axis (exact solution: lierk.exact.flip_interval is inf)")
        if self.flips_untracked is not None:
            lines.append(f"  flips not tracked with {scene.solver.name}: {self.flips_untracked}")
        for (name, _), times, record in zip(scene.events, self.event_times.values(), sol.events or ()):
            shown = ", ".join(f"{t:.6g}" for t in times[:8]) + (", ..." if len(times) > 8 else "")
            count = int(record.count)
            lines.append(f"  event {name}: {count} at t = {shown} s" if count else f"  event {name}: none")
            if bool(record.stopped):
                lines.append(f"  the run ended at the {name} event, t = {times[min(count, len(times)) - 1]:.9g} s")
        return "\n".join(lines)


def simulate(scene, *, n_pieces: int | None = None, progress: bool = False) -> Simulation:
    """Solve ``scene`` (`lierk.app.scene.Scene.solve`, in ``n_pieces`` with
    ``progress`` on stderr if asked), with its events and the flip
    (`lierk.app.scene.Scene.with_flip_event`; `Simulation.scene` is that scene),
    and read the solution's diagnostics.

    A solver that cannot locate events (`lierk.AbstractSolver.no_interpolant`:
    ExplicitEuler leaves SO(3), so its steps have no interpolant) solves the
    scene without the flip, and `Simulation.flips_untracked` says why.  The
    scene's own events it cannot do without: they raise.

    Raises:
        ValueError: the solve refused its arguments (`lierk.solve`).
        RuntimeError: the solve failed (`lierk.app.scene.Scene.solve`).
    """
    from .diagnostics import diagnostics

    flipped = scene.with_flip_event()
    untracked = scene.solver.no_interpolant if flipped is not scene else None
    tracked = flipped if untracked is None else scene
    if untracked is not None and progress:
        print(f"{scene.name}: flips not tracked with {scene.solver.name}: {untracked}", file=sys.stderr)
    start = time.perf_counter()
    sol = tracked.solve(n_pieces=n_pieces, progress=progress)
    wall = time.perf_counter() - start
    return Simulation(
        tracked, sol, diagnostics(tracked.problem, sol, euler_convention=tracked.euler_convention), wall, untracked
    )
