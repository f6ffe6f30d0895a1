"""Work-precision with torques: heavy tops and satellites, lierk against diffrax, MuJoCo and SciPy.

Five families of scenes, each a batch of bodies (256; ``--quick``: 8) with
initial conditions drawn from a fixed seed, in float64 and SI units (kg m^2,
kg, m, m/s^2, N m, N m s, rad/s, s).  Inertias are about the point the body
turns about: the pivot for the tops (`lierk.Gravity`'s convention),
the centre of mass for the satellite.  ``R`` maps body -> space, space z up.

- ``lagrange_fast``: the Simo-Wong heavy symmetric top, I = diag(5, 5, 1),
  mass 1, g = 10, centre of mass chi = (0, 0, 2) (M g l = 20); body omega0 =
  (U(-0.5, 0.5), U(-0.5, 0.5), U(45, 55)); tilt U(0.2, 0.6) rad about a
  horizontal axis at azimuth U(0, 2 pi); T = 2 s.
- ``lagrange_slow``: the same top spun at U(2, 5) rad/s (large nutation), T = 5 s.
- ``asymmetric``: an asymmetric heavy top, I = diag(0.6, 0.8, 0.3), mass 1,
  g = 9.81, chi = (0.02, 0.01, 0.5); omega0 = (U(-2, 2), U(-2, 2), U(30, 120));
  tilt 0.3 rad at azimuth U(0, 2 pi); T = 2 s.
- ``satellite``: I = diag(310, 420, 560), no gravity, `Damping` c = 6 N m s,
  `BodyTorque` (1.5, -1, 2) N m, `SpaceTorque` (-1, 2, 1) N m; omega0 uniform
  in direction with |omega0| ~ U(0.1, 1); R0 uniform; T = 60 s.
- ``spacecraft``: I = diag(10, 14, 6) in a circular orbit at n = 0.0011
  rad/s: `GravityGradient`, a constant `Rotor` (0, 0.3, 0) kg m^2/s and a
  B-dot `MagneticTorque` (gain 1e7 A m^2 s/T) in Earth's dipole field tilted
  1.1 rad from the orbit normal; omega0 uniform in direction with |omega0| ~
  U(0.02, 0.1); R0 uniform; T = 320 s.  MuJoCo has no model of these
  effects and sits it out.

Programs, every one on both cores:

- lierk (`lierk.RigidBodyWithEffects`): adaptive DOP853, DP54, RKF45 over
  ``rtol = atol``; fixed-step RKMK4, CF4, RKMK(DOP853) and, when lierk has
  them, the splitting solvers Strang, Yoshida4, BlanesMoan4, Yoshida6,
  BlanesMoan6, BlanesMoanRKN4 and BlanesMoanRKN6 (the last two refuse the
  satellite's damping), over dt.  Jitted, vmapped, and split over the 2 XLA host
  devices with `jax.shard_map` (each device runs its half of the batch on its
  own, so an adaptive loop on one device does not wait for the other's).
- diffrax Tsit5 and Dopri8, ``PIDController(rtol, atol)``, and Dopri8 with
  ``ConstantStepSize`` over the same dt as lierk's RKMK(DOP853) (lierk's
  fixed-step programs compete, so the peer's do too), on the 12-component ODE
  ``m' = m x omega + tau``, ``R' = R hat(omega)``, with the torques written
  out here (not lierk's effects); sharded the same way.
- MuJoCo RK4: one body on a ball joint at the pivot (gravity from the mass at
  the centre-of-mass offset, the inertia at the centre of mass so that the
  pivot inertia matches, joint damping for `Damping`, three motors on the ball
  joint for `BodyTorque`, ``xfrc_applied`` for `SpaceTorque`); the batch
  through `mujoco.rollout` with one thread and MjData per core, fed in chunks
  of steps.  Its conventions are checked against lierk at dt = 1e-4 for every
  family, each run.  The finest dt of the fixed-step sweep is left out for it.
- SciPy DOP853 on ONE body (member 0, the 12-component ODE); its time is
  multiplied by the batch size and its error is that member's.

Error: the largest ``||R(T) - R_ref(T)||_F`` over the batch.  Reference: lierk
DOP853 at rtol = atol = 1e-14, cross-checked against diffrax Dopri8 at 1e-14
on the whole batch and SciPy DOP853 at 2.5e-14 on two members; levels within
10x of the larger disagreement are not claimed.  Timing: compile and a warm-up call
excluded, median of at least 3 calls (more, up to 51, until they add up to
0.25 s), all programs of a family measured in one run.
Each program's time at an error level is interpolated log-log along its
work-precision front (`common.interp_time`).

Writes benchmarks/results/torqued.{json,md,png}.  Run:
``python benchmarks/torqued.py`` (about 8 minutes on 2 cores);
``--quick`` (8 bodies, fewer settings, no repeats, about 2 minutes) only
checks that the script works and writes to a temporary directory unless
``--out`` is given.
"""

from __future__ import annotations

import functools
import os

import host_devices

host_devices.split()  # one XLA host device per core

import time  # noqa: E402
from dataclasses import dataclass  # noqa: E402

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import diffrax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import mujoco  # noqa: E402
import numpy as np  # noqa: E402
import peers  # noqa: E402
import scipy  # noqa: E402
from common import cli, interp_time, machine_info, max_err, series_table, timed, write_results  # noqa: E402
from jax.sharding import Mesh, NamedSharding, PartitionSpec  # noqa: E402

import lierk  # noqa: E402

QUICK, OUT = cli(
    __doc__, "tiny run (8 bodies, few settings, no repeats) to check the script works", __name__ == "__main__"
)

N = 8 if QUICK else 256
SEED = 0
REPEATS = 1 if QUICK else 3
# Calls of a few ms are repeated until they add up to this (common.timed).
MIN_TIME = 0.0 if QUICK else 0.25
LEVELS = [10.0**-k for k in range(4, 11)]
REF_TOL = 1e-14  # lierk DOP853 and diffrax Dopri8
SCIPY_CHECK_TOL = 2.5e-14  # SciPy floors rtol at 100 eps
CHECK_IDS = [0, 1]  # members on which SciPy cross-checks the reference
MAX_STEPS = 1_000_000
MUJOCO_THREADS = os.cpu_count() or 1
MUJOCO_CHUNK = 2000  # steps per rollout call (bounds the state buffer)
SPLITTING = ("Strang", "Yoshida4", "BlanesMoan4", "Yoshida6", "BlanesMoan6", "BlanesMoanRKN4", "BlanesMoanRKN6")
# A splitting's dt sweep (coarse to fine) stops after a call longer than this
# (s): their steps cost 10 to 100 times an RKMK step, and the finest settings
# would otherwise take most of the run.
SPLIT_BUDGET_S = 1.0

DEVICES = jax.devices()
MESH = Mesh(np.array(DEVICES), ("batch",))
BATCH = NamedSharding(MESH, PartitionSpec("batch"))


# --- the families -------------------------------------------------------------


def _rot(axis: np.ndarray, angle: float) -> np.ndarray:
    axis = axis / np.linalg.norm(axis)
    K = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


def tilted(rng, n: int, tilt) -> np.ndarray:
    """``(n, 3, 3)``: body z tilted from the vertical by ``tilt`` (rad, ``(n,)``)
    about a horizontal axis at a random azimuth."""
    phi = rng.uniform(0, 2 * np.pi, n)
    return np.stack([_rot(np.array([np.cos(p), np.sin(p), 0.0]), a) for p, a in zip(phi, np.broadcast_to(tilt, n))])


@dataclass(frozen=True)
class Family:
    name: str
    title: str
    T: float
    inertia: tuple  # principal moments about the pivot (kg m^2)
    omega: tuple  # ((lo, hi) per body axis) for U(lo, hi), or None: random direction, |omega| ~ U(*speed)
    tilt: tuple | None  # U(lo, hi) rad about a random horizontal axis; None: uniform random attitude
    mass: float = 1.0  # kg
    g: float = 0.0  # m/s^2
    chi: tuple = (0.0, 0.0, 0.0)  # pivot -> centre of mass, body frame (m)
    c: float = 0.0  # damping (N m s)
    tau_b: tuple = (0.0, 0.0, 0.0)  # body-frame torque (N m)
    tau_s: tuple = (0.0, 0.0, 0.0)  # space-frame torque (N m)
    speed: tuple | None = None
    # spacecraft (lierk._problems.spacecraft): circular orbit rate (rad/s) for
    # the gravity gradient and the dipole field, a constant rotor momentum
    # (kg m^2/s, body frame), the B-dot gain (A m^2 s/T) and the field's tilt
    orbit_n: float = 0.0
    rotor: tuple = (0.0, 0.0, 0.0)
    bdot: float = 0.0
    field_tilt: float = 1.1
    # step sizes (s), each dividing T
    dts4: tuple = ()  # RKMK4, CF4, MuJoCo RK4, Strang, Yoshida4, BlanesMoan4
    # RKMK(DOP853), the order-6 splittings and BlanesMoanRKN4 (order 4, but as
    # accurate per step as BlanesMoan6 on the heavy tops)
    dts8: tuple = ()

    @property
    def gravity(self) -> bool:
        return self.g * self.mass * float(np.linalg.norm(self.chi)) > 0

    def effects(self) -> tuple:
        out = []
        if self.gravity:
            out.append(lierk.Gravity(jnp.asarray(self.chi), self.mass, self.g))
        if self.c:
            out.append(lierk.Damping(self.c))
        if any(self.tau_b):
            out.append(lierk.BodyTorque(jnp.asarray(self.tau_b)))
        if any(self.tau_s):
            out.append(lierk.SpaceTorque(jnp.asarray(self.tau_s)))
        if self.orbit_n:
            out.append(lierk.GravityGradient(np.diag(self.inertia), mean_motion=self.orbit_n))
        if any(self.rotor):
            out.append(lierk.Rotor(np.asarray(self.rotor)))
        if self.bdot:
            out.append(
                lierk.MagneticTorque(lierk.dipole_field(self.orbit_n, tilt=self.field_tilt), bdot_gain=self.bdot)
            )
        return tuple(out)

    @property
    def spacecraft(self) -> bool:
        """Orbit effects: MuJoCo has no model of them, so it sits this family out."""
        return bool(self.orbit_n)

    @functools.cached_property
    def torque(self):
        """``torque(xp, t, R, omega)``: the body-frame torque (N m), written out
        for the peers (``xp``: numpy or jax.numpy)."""
        gravity = peers.gravity_torque(self.mass, self.g, self.chi) if self.gravity else None
        orbit = None
        if self.orbit_n:
            orbit = peers.orbit_torque(self.inertia, self.orbit_n, self.rotor, self.bdot, self.field_tilt)

        def torque(xp, t, R, omega):
            tau = -self.c * omega + xp.asarray(self.tau_b) + R.T @ xp.asarray(self.tau_s)
            if gravity is not None:
                tau = tau + gravity(xp, t, R, omega)
            if orbit is not None:
                tau = tau + orbit(xp, t, R, omega)
            return tau

        return torque

    def initial(self, n: int) -> tuple[np.ndarray, np.ndarray]:
        """``(omega0 (n, 3) rad/s body frame, R0 (n, 3, 3))`` from the fixed seed."""
        rng = np.random.default_rng(SEED)
        if self.omega is not None:
            omega = np.stack([rng.uniform(lo, hi, n) for lo, hi in self.omega], axis=1)
        else:
            d = rng.normal(size=(n, 3))
            omega = rng.uniform(*self.speed, n)[:, None] * d / np.linalg.norm(d, axis=1, keepdims=True)
        if self.tilt is not None:
            R0 = tilted(rng, n, rng.uniform(*self.tilt, n))
        else:
            q = rng.normal(size=(n, 4))
            q /= np.linalg.norm(q, axis=1, keepdims=True)
            R0 = np.empty((n, 3, 3))
            for i in range(n):
                r9 = np.empty(9)
                mujoco.mju_quat2Mat(r9, q[i])
                R0[i] = r9.reshape(3, 3)
        return omega, R0

    def describe(self) -> dict:
        return {
            "T_s": self.T,
            "inertia_about_pivot_kg_m2": list(self.inertia),
            "mass_kg": self.mass,
            "g_m_s2": self.g,
            "pivot_to_com_m": list(self.chi),
            "damping_N_m_s": self.c,
            "body_torque_N_m": list(self.tau_b),
            "space_torque_N_m": list(self.tau_s),
            "orbit_mean_motion_rad_s": self.orbit_n,
            "rotor_momentum_kg_m2_s": list(self.rotor),
            "bdot_gain_A_m2_s_T": self.bdot,
            "omega0_rad_s": (
                f"body axes ~ U{tuple(self.omega)}" if self.omega else f"uniform direction, |omega| ~ U{self.speed}"
            ),
            "R0": f"tilt ~ U{self.tilt} rad about a horizontal axis at azimuth U(0, 2 pi)" if self.tilt else "uniform",
            "effects": [type(e).__name__ for e in self.effects()],
        }


LAGRANGE = dict(inertia=(5.0, 5.0, 1.0), mass=1.0, g=10.0, chi=(0.0, 0.0, 2.0), tilt=(0.2, 0.6))
FAMILIES = [
    Family(
        "lagrange_fast",
        "Lagrange top, fast (spin 45-55 rad/s)",
        2.0,
        omega=((-0.5, 0.5), (-0.5, 0.5), (45.0, 55.0)),
        **LAGRANGE,
        dts4=(8e-3, 4e-3, 2e-3, 1e-3, 5e-4, 2.5e-4),
        dts8=(4e-2, 2e-2, 1e-2, 5e-3, 2.5e-3),
    ),
    Family(
        "lagrange_slow",
        "Lagrange top, slow (spin 2-5 rad/s)",
        5.0,
        omega=((-0.5, 0.5), (-0.5, 0.5), (2.0, 5.0)),
        **LAGRANGE,
        dts4=(5e-2, 2.5e-2, 1.25e-2, 6.25e-3, 3.125e-3, 1.5625e-3),
        dts8=(0.5, 0.25, 0.125, 6.25e-2, 3.125e-2, 1.5625e-2),
    ),
    Family(
        "asymmetric",
        "asymmetric heavy top (spin 30-120 rad/s)",
        2.0,
        inertia=(0.6, 0.8, 0.3),
        mass=1.0,
        g=9.81,
        chi=(0.02, 0.01, 0.5),
        tilt=(0.3, 0.3),
        omega=((-2.0, 2.0), (-2.0, 2.0), (30.0, 120.0)),
        dts4=(8e-3, 4e-3, 2e-3, 1e-3, 5e-4, 2.5e-4),
        dts8=(2e-2, 1e-2, 5e-3, 2.5e-3, 1.25e-3),
    ),
    Family(
        "satellite",
        "damped satellite, body and space torques",
        60.0,
        inertia=(310.0, 420.0, 560.0),
        omega=None,
        speed=(0.1, 1.0),
        tilt=None,
        c=6.0,
        tau_b=(1.5, -1.0, 2.0),
        tau_s=(-1.0, 2.0, 1.0),
        dts4=(0.8, 0.4, 0.2, 0.1, 0.05, 0.025),
        dts8=(2.0, 1.0, 0.5, 0.25, 0.125),
    ),
    Family(
        "spacecraft",
        "satellite in orbit: gravity gradient, pitch rotor, B-dot",
        320.0,
        inertia=(10.0, 14.0, 6.0),
        omega=None,
        speed=(0.02, 0.1),
        tilt=None,
        orbit_n=0.0011,
        rotor=(0.0, 0.3, 0.0),
        bdot=1e7,
        dts4=(8.0, 4.0, 2.0, 1.0, 0.5, 0.25),
        dts8=(32.0, 16.0, 8.0, 4.0, 2.0),
    ),
]
# Tolerances (rtol = atol): every decade for the eighth-order pairs, the contenders;
# every other decade for the lower orders.
TOLS_HIGH = (1e-4, 1e-5, 1e-6, 1e-7, 1e-8, 1e-9, 1e-10, 1e-11, 1e-12, 1e-13)
TOLS_LOW = (1e-4, 1e-6, 1e-8, 1e-10)


def sweep(values: tuple, k: int = 2) -> tuple:
    """The full sweep, or with --quick ``k`` settings from it (the finest, then the coarsest)."""
    return tuple(values) if not QUICK else tuple(values[::-1][:: max(1, len(values) - 1)])[:k]


# --- batched JAX programs, one half of the batch per device ------------------


def on_devices(one):
    """``one(omega0, R0, setting) -> outputs`` for one body, as a jitted function
    of the whole batch: vmapped, and each device runs its own rows."""
    spec = PartitionSpec("batch")
    return jax.jit(
        jax.shard_map(
            jax.vmap(one, in_axes=(0, 0, None)),
            mesh=MESH,
            in_specs=(spec, spec, PartitionSpec()),
            out_specs=spec,
            check_vma=False,
        )
    )


def lierk_fn(fam: Family, solver, dt: float | None = None):
    """Adaptive (``dt`` None; the setting is ``rtol = atol``) or fixed-step solve."""
    effects = fam.effects()

    def one(w, R0, tol):
        # A NumPy inertia stays concrete under jit, so a symmetric top gets the
        # splittings' closed-form drift (`RigidBodyWithEffects.symmetry_axis`).
        problem = lierk.RigidBodyWithEffects(np.asarray(fam.inertia), w, R0, effects=effects)
        if dt is None:
            sol = lierk.solve(problem, solver, fam.T, rtol=tol, atol=tol, max_steps=MAX_STEPS, throw=False)
        else:
            sol = lierk.solve(problem, solver, fam.T, dt=dt, max_steps=lierk.num_steps(0.0, fam.T, dt), throw=False)
        return sol.R[-1], sol.stats["num_steps"], sol.result

    return on_devices(one)


def diffrax_fn(fam: Family, solver, dt: float | None = None):
    """Adaptive (``dt`` None; the setting is ``rtol = atol``) or constant-step solve."""
    field = peers.rigid_body_field(fam.inertia, fam.torque)
    control = dict(max_steps=MAX_STEPS) if dt is None else dict(dt=dt, max_steps=lierk.num_steps(0.0, fam.T, dt) + 1)

    def one(w, R0, tol):
        return peers.diffrax_solve(field, solver, fam.T, peers.initial_state(fam.inertia, w, R0), rtol=tol, **control)

    return on_devices(one)


def scipy_one(fam: Family, w, R0, tol):
    field = peers.rigid_body_field(fam.inertia, fam.torque, xp=np)
    return peers.scipy_solve(field, fam.T, peers.initial_state(fam.inertia, w, R0, xp=np), tol)


# --- MuJoCo -------------------------------------------------------------------
#
# The body frame is the joint frame, with its origin at the pivot (the ball
# joint's centre).  <inertial> puts the mass at chi with the inertia about the
# centre of mass, I_pivot - M (|chi|^2 E - chi chi^T) (parallel axis), so the
# joint-space inertia is lierk's pivot inertia; MuJoCo diagonalises a full
# inertia itself.  Gravity acts on the mass at chi.  Joint damping c on the
# ball joint is the torque -c qvel, qvel being the body angular velocity.
# Three motors on the ball joint with gears e_x, e_y, e_z carry the body-frame
# torque as ctrl; the space-frame torque is the body's xfrc_applied (world
# frame).  Both are constant controls passed to rollout (control_spec
# CTRL | XFRC_APPLIED).  Everything MuJoCo would do besides is switched off.

MJ_FLAGS = (
    "constraint",
    "equality",
    "frictionloss",
    "limit",
    "contact",
    "spring",
    "warmstart",
    "filterparent",
    "sensor",
    "midphase",
    "clampctrl",
)


def mujoco_xml(fam: Family, dt: float) -> str:
    I, M, chi = np.diag(fam.inertia), fam.mass, np.asarray(fam.chi)
    I_cm = I - M * (chi @ chi * np.eye(3) - np.outer(chi, chi))
    if np.allclose(I_cm, np.diag(np.diag(I_cm)), rtol=0, atol=0):
        inertia = 'diaginertia="{:.17g} {:.17g} {:.17g}"'.format(*np.diag(I_cm))
    else:
        inertia = 'fullinertia="{:.17g} {:.17g} {:.17g} {:.17g} {:.17g} {:.17g}"'.format(
            I_cm[0, 0], I_cm[1, 1], I_cm[2, 2], I_cm[0, 1], I_cm[0, 2], I_cm[1, 2]
        )
    flags = " ".join(f'{f}="disable"' for f in MJ_FLAGS)
    motors = ""
    if any(fam.tau_b):
        motors = (
            "<actuator>"
            + "".join(
                f'<motor joint="pivot" gear="{" ".join("1" if j == k else "0" for j in range(3))} 0 0 0"/>'
                for k in range(3)
            )
            + "</actuator>"
        )
    return f"""<mujoco model="{fam.name}">
  <option gravity="0 0 {-fam.g:.17g}" integrator="RK4" timestep="{dt:.17g}">
    <flag {flags}/>
  </option>
  <worldbody>
    <body name="body">
      <joint name="pivot" type="ball" damping="{fam.c:.17g}"/>
      <inertial pos="{chi[0]:.17g} {chi[1]:.17g} {chi[2]:.17g}" mass="{M:.17g}" {inertia}/>
    </body>
  </worldbody>
  {motors}
</mujoco>
"""


def mujoco_control(fam: Family, model) -> tuple[np.ndarray, int]:
    """``(constant control vector, control_spec)``: ctrl = body torque, xfrc_applied = space torque."""
    spec = mujoco.mjtState.mjSTATE_CTRL.value | mujoco.mjtState.mjSTATE_XFRC_APPLIED.value
    ctrl = np.zeros(model.nu)
    ctrl[:] = np.asarray(fam.tau_b)[: model.nu]
    xfrc = np.zeros((model.nbody, 6))
    xfrc[1, 3:] = fam.tau_s
    return np.concatenate([ctrl, xfrc.ravel()]), spec


def mujoco_runner(fam: Family, omegas, R0s, dt: float, T: float | None = None):
    """A function that rolls the batch out to ``T`` (default the family's) and
    returns the final full states; plus its model."""
    model = mujoco.MjModel.from_xml_string(mujoco_xml(fam, dt))
    init = peers.mujoco_initial_states(model, omegas, peers.mujoco_quats(R0s))
    u, spec = mujoco_control(fam, model)
    n = lierk.num_steps(0.0, fam.T if T is None else T, dt)
    return peers.mujoco_rollout(model, init, n, MUJOCO_THREADS, u, spec, chunk=MUJOCO_CHUNK), model


def mujoco_check(fam: Family, omega, R0) -> dict:
    """MuJoCo's conventions against lierk: one body, dt = 1e-4 for min(T, 1) s,
    against lierk DOP853 at 1e-13; with the body torque also read as a space
    torque, which must disagree if it matters."""
    T = min(fam.T, 1.0)
    go, model = mujoco_runner(fam, omega[None], R0[None], 1e-4, T)
    R_mj, w_mj, t_mj = peers.mujoco_final(model, go())

    def lierk_ref(effects):
        p = lierk.RigidBodyWithEffects(jnp.asarray(fam.inertia), omega, R0, effects=effects)
        sol = lierk.solve(p, lierk.DOP853(), T, rtol=REF_TOL, atol=REF_TOL, max_steps=MAX_STEPS)
        return np.asarray(sol.R[-1]), np.asarray(p.inertia_inv @ sol.y[-1])

    R_ref, w_ref = lierk_ref(fam.effects())
    out = {
        "t": float(t_mj[0]),
        "dt": 1e-4,
        "R_error": float(np.linalg.norm(R_mj[0] - R_ref)),
        "qvel_minus_body_omega": float(np.linalg.norm(w_mj[0] - w_ref)),
    }
    if any(fam.tau_b):
        swapped = [e for e in fam.effects() if not isinstance(e, lierk.BodyTorque)] + [
            lierk.SpaceTorque(jnp.asarray(fam.tau_b))
        ]
        out["R_error_if_motor_torque_were_space_frame"] = float(np.linalg.norm(R_mj[0] - lierk_ref(tuple(swapped))[0]))
    return out


# --- one family -----------------------------------------------------------------


def run_family(fam: Family) -> dict:
    t_family = time.perf_counter()
    print(f"\n=== {fam.name}: {fam.title}, N = {N}, T = {fam.T:g} s", flush=True)
    omegas_np, R0_np = fam.initial(N)
    omegas, R0s = jax.device_put(jnp.asarray(omegas_np), BATCH), jax.device_put(jnp.asarray(R0_np), BATCH)
    records = []

    def add(method, program, kind, param, R, seconds, first, steps=None, results=None, R_ref=None, note=""):
        ok = results is None or not np.any(np.isin(np.asarray(results), [1, 2, 3]))
        rec = {
            "method": method,
            "program": program,
            "kind": kind,
            "param": param,
            "time_s": seconds,
            "first_call_s": first,
            "error": max_err(R, R_ref) if ok else float("nan"),
            "note": note,
        }
        if steps is not None:
            rec["max_steps"] = int(np.max(steps))
            rec["mean_steps"] = float(np.mean(steps))
            # Under vmap each device steps its whole half of the batch until its
            # slowest member is done: the cost of one such body-step, per core.
            lockstep = float(np.sum(np.max(np.asarray(steps).reshape(len(DEVICES), -1), axis=1))) * N / len(DEVICES)
            rec["us_per_body_step"] = 1e6 * seconds * len(DEVICES) / lockstep
        if results is not None:
            rec["results"] = np.bincount(np.asarray(results).ravel(), minlength=1).tolist()
        records.append(rec)
        steps_s = f"  steps {rec['max_steps']:6d}, {rec['us_per_body_step']:5.2f} us/step" if steps is not None else ""
        print(
            f"  {method:26s} {param:9.2e}  err {rec['error']:.2e}  time {seconds:8.4f} s  "
            f"(first {first:6.2f} s){steps_s}{'' if ok else '  FAILED ' + str(rec['results'])}",
            flush=True,
        )

    # Reference: lierk DOP853 at 1e-13, against diffrax Dopri8 (whole batch) and SciPy DOP853 (two members).
    dop853 = lierk_fn(fam, lierk.DOP853())
    t = time.perf_counter()
    R_ref, _, res = jax.block_until_ready(dop853(omegas, R0s, REF_TOL))
    ref_s = time.perf_counter() - t  # with compilation
    assert np.all(np.isin(np.asarray(res), [0, 5])), f"reference failed: {np.bincount(np.asarray(res))}"
    R_ref = jnp.asarray(R_ref)
    dopri8 = diffrax_fn(fam, diffrax.Dopri8())
    R_dx, _, res_dx = jax.block_until_ready(dopri8(omegas, R0s, REF_TOL))
    assert not np.any(np.asarray(res_dx)), "diffrax Dopri8 cross-check failed"
    check_diffrax = max_err(R_dx, R_ref)
    check_scipy = [
        float(np.linalg.norm(scipy_one(fam, omegas_np[i], R0_np[i], SCIPY_CHECK_TOL)[0] - np.asarray(R_ref[i])))
        for i in CHECK_IDS
    ]
    agreement = max(check_diffrax, *check_scipy)
    print(
        f"  reference lierk DOP853({REF_TOL:.0e}) {ref_s:.1f} s; |ref - diffrax Dopri8({REF_TOL:.0e})| = "
        f"{check_diffrax:.1e} (batch max), |ref - SciPy DOP853({SCIPY_CHECK_TOL:.1e})| = "
        f"{', '.join(f'{c:.1e}' for c in check_scipy)}",
        flush=True,
    )

    def adaptive(method, program, fn, tols):
        for tol in tols:
            (R, steps, res), s, first = timed(fn, omegas, R0s, tol, repeats=REPEATS, min_time=MIN_TIME)
            add(method, program, "tol", tol, R, s, first, steps, res, R_ref)

    def fixed(method, solver, dts, budget=None, program="lierk"):
        """dts coarse to fine; with a ``budget`` (s), stop after a setting whose
        call took longer or whose error is already at the reference's."""
        for dt in dts:
            fn = lierk_fn(fam, solver, dt) if program == "lierk" else diffrax_fn(fam, solver, dt)
            (R, steps, res), s, first = timed(fn, omegas, R0s, 0.0, repeats=REPEATS, min_time=MIN_TIME)
            add(method, program, "dt", dt, R, s, first, steps, res, R_ref)
            if budget is not None and (s > budget or records[-1]["error"] <= agreement):
                break

    # --quick runs one method of each code path (the others differ only in the
    # solver object), and fixed steps at one dt, to keep compilation short.
    adaptive("lierk DOP853", "lierk", dop853, sweep(TOLS_HIGH))
    if not QUICK:
        for solver in (lierk.DP54(), lierk.RKF45()):
            adaptive(f"lierk {solver.name}", "lierk", lierk_fn(fam, solver), TOLS_LOW)
    fixed("lierk RKMK4 fixed", lierk.RKMK4(), sweep(fam.dts4, 1))
    if not QUICK:
        fixed("lierk CF4 fixed", lierk.CF4(), fam.dts4)
        fixed("lierk RKMK(DOP853) fixed", lierk.RKMK(lierk.tableaux.DOP853), fam.dts8)
    skipped = {}
    for k, name in enumerate(SPLITTING):
        cls = getattr(lierk, name, None)
        if cls is None:
            skipped[name] = "not in lierk"
            continue
        if QUICK and k % len(FAMILIES) != FAMILIES.index(fam):
            skipped[name] = "--quick: run on another family"  # each compiles for 5 to 20 s
            continue
        dts = fam.dts4 if name in ("Strang", "Yoshida4", "BlanesMoan4") else fam.dts8
        try:
            fixed(f"lierk {name}", cls(), dts[:1] if QUICK else dts, budget=SPLIT_BUDGET_S)
        except Exception as e:  # a splitting that cannot take this family's effects
            skipped[name] = f"{type(e).__name__}: {e}".splitlines()[0][:200]
            print(f"  lierk {name}: skipped ({skipped[name]})", flush=True)

    adaptive("diffrax Tsit5", "diffrax", diffrax_fn(fam, diffrax.Tsit5()), sweep(TOLS_LOW))
    adaptive("diffrax Dopri8", "diffrax", dopri8, sweep(TOLS_HIGH))
    # lierk's fixed-step programs are measured, so the peer's are too.
    fixed("diffrax Dopri8 fixed", diffrax.Dopri8(), sweep(fam.dts8, 1), program="diffrax")

    check = mujoco_check(fam, omegas_np[0], R0_np[0]) if not fam.spacecraft else "no orbit effects in MuJoCo: not run"
    print(f"  MuJoCo check against lierk at dt 1e-4: {check}", flush=True)
    # The finest dt is left out for MuJoCo (it is the slowest program per step
    # and its finest point would take a quarter of the whole run).
    for dt in sweep(fam.dts4[:-1]) if not fam.spacecraft else ():
        go, model = mujoco_runner(fam, omegas_np, R0_np, dt)
        final, s, first = timed(go, repeats=REPEATS, min_time=MIN_TIME)
        R, _, t_end = peers.mujoco_final(model, final)
        assert np.all(np.abs(t_end - fam.T) <= 1e-9 * fam.T), f"MuJoCo ended at {t_end.min()}..{t_end.max()}"
        add("MuJoCo RK4", "mujoco", "dt", dt, R, s, first, R_ref=R_ref, note=f"rollout, {MUJOCO_THREADS} threads")

    for tol in sweep(TOLS_HIGH):
        t = time.perf_counter()
        R, nfev = scipy_one(fam, omegas_np[0], R0_np[0], tol)
        s = (time.perf_counter() - t) * N
        add(
            f"SciPy DOP853 (x{N})", "scipy", "tol", tol, R[None], s, 0.0, R_ref=R_ref[:1], note=f"member 0, nfev {nfev}"
        )

    table = level_table(records, agreement)
    for row in table:
        r = row["ratio"]
        print(f"  error <= {row['level']:.0e}: lierk/best peer = {'-' if r is None else f'{r:.2f}'}", flush=True)
    total = time.perf_counter() - t_family
    print(f"  {fam.name} done in {total:.0f} s", flush=True)
    return {
        "definition": fam.describe(),
        "batch": N,
        "reference": f"lierk DOP853 rtol=atol={REF_TOL:.0e}",
        "reference_s": ref_s,
        "reference_vs_diffrax_dopri8": check_diffrax,
        "reference_vs_scipy_dop853": dict(zip(map(str, CHECK_IDS), check_scipy)),
        "reference_agreement": agreement,
        "mujoco_check": check,
        "mujoco_model": mujoco_xml(fam, fam.dts4[0]) if not fam.spacecraft else None,
        "splitting_skipped": skipped,
        "runtime_s": total,
        "records": records,
        "table": table,
    }


PROGRAMS = [
    ("lierk", "lierk best"),
    ("diffrax", "diffrax best"),
    ("mujoco", "MuJoCo RK4"),
    ("scipy", "SciPy DOP853 (x N)"),
]
PEERS = ("diffrax", "mujoco", "scipy")


def level_table(records, agreement: float) -> list[dict]:
    """Per error level: each program's cheapest method (interpolated time), the
    best peer and lierk / best peer.  Levels within 10x of the reference
    agreement are not claimed (all None)."""
    rows = []
    for level in LEVELS:
        row = {"level": level, "claimed": level >= 10 * agreement}
        for program, _ in PROGRAMS:
            best = None
            for method in dict.fromkeys(r["method"] for r in records if r["program"] == program):
                hit = interp_time([(r["error"], r["time_s"]) for r in records if r["method"] == method], level)
                if hit and (best is None or hit[0] < best["time_s"]):
                    best = {"method": method, "time_s": hit[0], "clamped": hit[1]}
            row[program] = best if row["claimed"] else None
        peers = [row[p] | {"program": p} for p in PEERS if row[p]]
        row["best_peer"] = min(peers, key=lambda x: x["time_s"]) if peers else None
        row["ratio"] = (
            row["lierk"]["time_s"] / row["best_peer"]["time_s"] if row["lierk"] and row["best_peer"] else None
        )
        rows.append(row)
    return rows


# --- outputs -------------------------------------------------------------------


def _cell(x) -> str:
    if x is None:
        return "-"
    return f"{x['time_s']:.3g}{'*' if x['clamped'] else ''} ({x['method']})"


def ratio_table(families: dict) -> list[str]:
    names = list(families)
    lines = ["| error <= | " + " | ".join(names) + " |", "|---" * (len(names) + 1) + "|"]
    for k, level in enumerate(LEVELS):
        cells = []
        for name in names:
            row = families[name]["table"][k]
            if not row["claimed"]:
                cells.append("(below reference)")
            elif row["ratio"] is None:
                cells.append("-" if row["lierk"] is None else "no peer reaches it")
            else:
                mark = "" if row["ratio"] <= 0.3 else " (missed)"
                cells.append(
                    f"{row['ratio']:.2f}{mark}: {row['lierk']['method'].removeprefix('lierk ')} vs "
                    f"{row['best_peer']['method']}"
                )
        lines.append(f"| {level:.0e} | " + " | ".join(cells) + " |")
    return lines


def markdown(p) -> list[str]:
    m = p["machine"]
    lines = [
        f"# Work-precision with torques: {len(p['families'])} families, batch {N}, float64",
        "",
        ("**QUICK RUN (tiny size, timings meaningless).**\n\n" if p["quick"] else "")
        + f"Machine: {m['cpu_count']} cores ({m['cpu']}), {len(m['devices'])} XLA host devices; jax {m['jax']}, "
        f"diffrax {m['diffrax']}, mujoco {m['mujoco']}, scipy {m['scipy']}. Load average at start "
        f"{m['load_average_at_start']}, at end {m['load_average_at_end']}. Total runtime {p['total_runtime_s']:.0f} s.",
        "",
        f"Error: {p['error']}. Timing: {p['timing']}. Each program's time at a level is interpolated log-log "
        "along its work-precision front; `*` marks a time where even the coarsest setting was more accurate "
        "than the level (an upper bound).",
        "",
        "## lierk best / best peer",
        "",
        "Target: at most 0.3 at every level on each family. Best peer: the cheapest of diffrax "
        "(Tsit5 and Dopri8 adaptive, Dopri8 at constant step), "
        "MuJoCo RK4 and SciPy DOP853 (one body x N) at that level.",
        "",
        *ratio_table(p["families"]),
    ]
    for name, f in p["families"].items():
        d, c = f["definition"], f["mujoco_check"]
        lines += [
            "",
            f"## {name}",
            "",
            "Definition: " + "; ".join(f"{k} = {v}" for k, v in d.items()) + ".",
            "",
            f"Reference {f['reference']} ({f['reference_s']:.1f} s with compilation); "
            "|ref - diffrax Dopri8 at the same tolerance| "
            f"= {f['reference_vs_diffrax_dopri8']:.1e} (batch max), |ref - SciPy DOP853 at {SCIPY_CHECK_TOL:.1e}| = "
            + ", ".join(f"{v:.1e}" for v in f["reference_vs_scipy_dop853"].values())
            + f" (members {', '.join(f['reference_vs_scipy_dop853'])}). "
            + (
                f"MuJoCo: {c}."
                if isinstance(c, str)
                else (
                    f"MuJoCo against lierk at dt 1e-4 over "
                    f"{c['t']:g} s: |R - R_lierk| = {c['R_error']:.1e}, "
                    f"|qvel - omega_body| = {c['qvel_minus_body_omega']:.1e}"
                    + (
                        "; with the motors' torque read as a space-frame torque instead: "
                        f"{c['R_error_if_motor_torque_were_space_frame']:.1e}"
                        if "R_error_if_motor_torque_were_space_frame" in c
                        else ""
                    )
                    + "."
                )
            )
            + (f" Splitting solvers not run: {f['splitting_skipped']}." if f["splitting_skipped"] else ""),
            "",
            "| error <= | " + " | ".join(h for _, h in PROGRAMS) + " | lierk / best peer |",
            "|---" * (len(PROGRAMS) + 2) + "|",
        ]
        for row in f["table"]:
            ratio = "-" if row["ratio"] is None else f"{row['ratio']:.2f}"
            lines.append(f"| {row['level']:.0e} | " + " | ".join(_cell(row[k]) for k, _ in PROGRAMS) + f" | {ratio} |")
        lines += [
            "",
            "Max error (median time, s) at each tolerance:",
            "",
            *series_table(f["records"], "tol", "tol", "{:.0e}"),
            "",
            "... and at each step size:",
            "",
            *series_table(f["records"], "dt", "dt (s)", "{:.4g}"),
        ]
    return lines


def plot(families: dict):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    methods = list(dict.fromkeys(r["method"] for f in families.values() for r in f["records"]))
    colours = plt.get_cmap("tab20").colors
    markers = ["o", "s", "^", "v", "D", "P", "X", "<", ">", "h", "p", "d", "H", "8", "x", "+"]
    style = {"lierk": "-", "diffrax": "--", "mujoco": "-.", "scipy": ":"}
    fig, axes = plt.subplots(2, 2, figsize=(13, 10))
    for ax, (name, f) in zip(axes.ravel(), families.items()):
        for k, method in enumerate(methods):
            rs = sorted(
                (r for r in f["records"] if r["method"] == method and np.isfinite(r["error"])),
                key=lambda r: r["time_s"],
            )
            if rs:
                ax.loglog(
                    [r["time_s"] for r in rs],
                    [max(r["error"], 1e-16) for r in rs],
                    style[rs[0]["program"]],
                    marker=markers[k % len(markers)],
                    ms=4,
                    color=colours[k % len(colours)],
                    label=method,
                )
        ax.axhline(f["reference_agreement"], color="grey", lw=0.8, ls=":")
        ax.set_title(f"{name}: T = {f['definition']['T_s']:g} s, N = {f['batch']}")
        ax.set_xlabel("wall time for the batch (s)")
        ax.set_ylabel("max ||R(T) - R_ref(T)||_F")
        ax.grid(True, which="both", alpha=0.3)
    handles, labels = axes[0, 0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=6, fontsize=8)
    fig.tight_layout(rect=(0, 0.08, 1, 1))
    fig.savefig(OUT / "torqued.png", dpi=110)


def main():
    OUT.mkdir(parents=True, exist_ok=True)
    machine = machine_info(diffrax=diffrax.__version__, mujoco=mujoco.__version__, scipy=scipy.__version__)
    print(
        f"{machine['cpu_count']} cores, {machine['cpu']}, devices {machine['devices']}, "
        f"load {machine['load_average_at_start']}",
        flush=True,
    )
    t_start = time.perf_counter()
    families = {fam.name: run_family(fam) for fam in FAMILIES}
    machine["load_average_at_end"] = os.getloadavg() if hasattr(os, "getloadavg") else None
    payload = {
        "quick": QUICK,
        "batch": N,
        "seed": SEED,
        "levels": LEVELS,
        "error": "max over the batch of ||R(T) - R_ref(T)||_F (SciPy: member 0 only)",
        "timing": f"median of at least {REPEATS} calls (up to 51, until they add up to {MIN_TIME} s) "
        f"after a warm-up call; SciPy: one body x {N}",
        "machine": machine,
        "total_runtime_s": time.perf_counter() - t_start,
        "families": families,
    }
    write_results(OUT, "torqued", payload, markdown(payload))
    plot(families)
    print("\n" + "\n".join(ratio_table(families)))
    print(f"and torqued.png; total {payload['total_runtime_s']:.0f} s")


if __name__ == "__main__":
    main()
