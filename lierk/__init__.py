"""lierk: Lie-group integrators for rigid-body rotation, in JAX.

`import lierk` is the library's whole API: the names below.  The modules
that implement them are private (``lierk._solve``, ``lierk._loops``, ...).
Six public namespaces hold families of functions a user imports together:

- `lierk.so3`: the rotation group (exp, log, dexpinv, conversions);
- `lierk.exact`: the free rigid body's closed-form motion;
- `lierk.inertia`: inertia tensors of shapes, composites and meshes;
- `lierk.conditions`: initial conditions and events (the flip, tilt);
- `lierk.tableaux`: the Butcher and splitting tableaux;
- `lierk.checks`: the checks of a body's inputs, for front ends that word
  their own messages (scene files).

The application (scene files, the ``lierk`` command, simulations, accuracy
reports, figures, resumable sweeps, multi-process set-up and the
compilation cache) is the sub-package `lierk.app`, which uses only this API.

Data flows one way: problem -> ``solve(problem, solver, ...)`` ->
`Solution` -> `lierk.app` (figures, reports, the CLI).
"""

import importlib as _importlib

from . import checks as checks
from . import conditions as conditions
from . import exact as exact
from . import inertia as inertia
from . import so3 as so3
from . import tableaux as tableaux
from ._adjoint import AbstractAdjoint as AbstractAdjoint
from ._adjoint import DirectAdjoint as DirectAdjoint
from ._adjoint import ForwardMode as ForwardMode
from ._adjoint import ForwardSensitivity as ForwardSensitivity
from ._adjoint import RecursiveCheckpointAdjoint as RecursiveCheckpointAdjoint
from ._batch import sweep as sweep
from ._batch import sweep_chunks as sweep_chunks
from ._controller import AbstractStepController as AbstractStepController
from ._controller import ConstantStep as ConstantStep
from ._controller import Controller as Controller
from ._controller import Decision as Decision
from ._event import Event as Event
from ._event import EventRecord as EventRecord
from ._global_error import finer_options as finer_options
from ._global_error import richardson as richardson
from ._interpolation import DenseInterpolation as DenseInterpolation
from ._problems import AbstractProblem as AbstractProblem
from ._problems import AbstractRigidBody as AbstractRigidBody
from ._problems import FreeRigidBody as FreeRigidBody
from ._problems import RigidBodyWithEffects as RigidBodyWithEffects
from ._problems import SpatialFreeRigidBody as SpatialFreeRigidBody
from ._problems import heavy_top as heavy_top
from ._problems.effects import AbstractEffect as AbstractEffect
from ._problems.effects import BodyTorque as BodyTorque
from ._problems.effects import Damping as Damping
from ._problems.effects import Gravity as Gravity
from ._problems.effects import SpaceTorque as SpaceTorque
from ._problems.effects import TimedTorque as TimedTorque
from ._problems.kinematics import angular_momentum as angular_momentum
from ._problems.kinematics import body_angular_velocity as body_angular_velocity
from ._problems.kinematics import kinetic_energy as kinetic_energy
from ._problems.spacecraft import GravityGradient as GravityGradient
from ._problems.spacecraft import MagneticTorque as MagneticTorque
from ._problems.spacecraft import ReactionWheels as ReactionWheels
from ._problems.spacecraft import Rotor as Rotor
from ._problems.spacecraft import dipole_field as dipole_field
from ._programs import one_body_compiler_options as one_body_compiler_options
from ._progress import Progress as Progress
from ._sampled import solve_sampled as solve_sampled
from ._sensitivity import Sensitivity as Sensitivity
from ._sensitivity import sensitivity as sensitivity
from ._sensitivity import sensitivity_method as sensitivity_method
from ._solution import RESULTS as RESULTS
from ._solution import SaveAt as SaveAt
from ._solution import Solution as Solution
from ._solve import num_steps as num_steps
from ._solve import solve as solve
from ._solvers import CF4 as CF4
from ._solvers import DOP853 as DOP853
from ._solvers import DP54 as DP54
from ._solvers import RKF45 as RKF45
from ._solvers import RKMK as RKMK
from ._solvers import RKMK4 as RKMK4
from ._solvers import SOLVERS as SOLVERS
from ._solvers import AbstractRKMK as AbstractRKMK
from ._solvers import AbstractSolver as AbstractSolver
from ._solvers import AbstractSplitting as AbstractSplitting
from ._solvers import BlanesMoan4 as BlanesMoan4
from ._solvers import BlanesMoan6 as BlanesMoan6
from ._solvers import BlanesMoanRKN4 as BlanesMoanRKN4
from ._solvers import BlanesMoanRKN6 as BlanesMoanRKN6
from ._solvers import ExplicitEuler as ExplicitEuler
from ._solvers import LieEuler as LieEuler
from ._solvers import NaiveLieRK4 as NaiveLieRK4
from ._solvers import Splitting as Splitting
from ._solvers import Strang as Strang
from ._solvers import Yoshida4 as Yoshida4
from ._solvers import Yoshida6 as Yoshida6
from ._solvers import solver_class as solver_class
from ._validation import checked_on_host as checked_on_host

__version__ = "0.1.0"


def __getattr__(name: str):
    # The application is imported when first used, so that `import lierk`
    # loads only the integrators (no matplotlib, no tqdm, no TOML parser).
    if name == "app":
        return _importlib.import_module(f"{__name__}.app")
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__():
    return sorted([*globals(), "app"])
