"""lierk: Lie-group integrators for rigid-body rotation, in JAX.

The public API is re-exported here; each concept lives in its own module.
Data flows one way: scene -> problem (``problems``) -> ``solve(solver)`` ->
`Solution` -> plot/CLI.
"""

import importlib

from . import adjoint as adjoint
from . import batch as batch
from . import body as body
from . import cache as cache
from . import conditions as conditions
from . import effects as effects
from . import exact as exact
from . import fields as fields
from . import inertia as inertia
from . import interpolation as interpolation
from . import problems as problems
from . import rigid_body as rigid_body
from . import so3 as so3
from . import tableaux as tableaux
from .adjoint import DirectAdjoint as DirectAdjoint
from .adjoint import ForwardMode as ForwardMode
from .adjoint import ForwardSensitivity as ForwardSensitivity
from .adjoint import RecursiveCheckpointAdjoint as RecursiveCheckpointAdjoint
from .cache import compilation_cache_dir as compilation_cache_dir
from .cache import using_cache as using_cache
from .controller import Controller as Controller
from .event import Event as Event
from .event import EventRecord as EventRecord
from .problems import AbstractProblem as AbstractProblem
from .problems import AbstractRigidBody as AbstractRigidBody
from .problems import FreeRigidBody as FreeRigidBody
from .problems import RigidBodyWithEffects as RigidBodyWithEffects
from .problems import SpatialFreeRigidBody as SpatialFreeRigidBody
from .problems.effects import BodyTorque as BodyTorque
from .problems.effects import Damping as Damping
from .problems.effects import Gravity as Gravity
from .problems.effects import SpaceTorque as SpaceTorque
from .problems.effects import TimedTorque as TimedTorque
from .problems.spacecraft import GravityGradient as GravityGradient
from .problems.spacecraft import MagneticTorque as MagneticTorque
from .problems.spacecraft import ReactionWheels as ReactionWheels
from .problems.spacecraft import Rotor as Rotor
from .problems.spacecraft import dipole_field as dipole_field
from .solution import RESULTS as RESULTS
from .solution import SaveAt as SaveAt
from .solution import Solution as Solution
from .batch import sweep as sweep
from .batch import sweep_chunks as sweep_chunks
from .solve import solve as solve
from .sensitivity import Sensitivity as Sensitivity
from .sensitivity import sensitivity as sensitivity
from .sensitivity import sensitivity_method as sensitivity_method
from .solvers import CF4 as CF4
from .solvers import DOP853 as DOP853
from .solvers import DP54 as DP54
from .solvers import RKF45 as RKF45
from .solvers import RKMK as RKMK
from .solvers import RKMK4 as RKMK4
from .solvers import AbstractSolver as AbstractSolver
from .solvers import ExplicitEuler as ExplicitEuler
from .solvers import LieEuler as LieEuler
from .solvers import NaiveLieRK4 as NaiveLieRK4
from .solvers import AbstractSplitting as AbstractSplitting
from .solvers import BlanesMoan4 as BlanesMoan4
from .solvers import BlanesMoan6 as BlanesMoan6
from .solvers import BlanesMoanRKN4 as BlanesMoanRKN4
from .solvers import BlanesMoanRKN6 as BlanesMoanRKN6
from .solvers import Splitting as Splitting
from .solvers import Strang as Strang
from .solvers import Yoshida4 as Yoshida4
from .solvers import Yoshida6 as Yoshida6

__version__ = "0.1.0"

# What a scene's runs and reports need (scenes, simulations, accuracy,
# sweeps of omega0, diagnostics, counting compilations) is imported when
# first used, so that `import lierk` loads only the integrators.
_APPLICATION = ("accuracy", "compilations", "diagnostics", "omega_sweep", "scene", "simulation")


def __getattr__(name: str):
    if name in _APPLICATION:
        return importlib.import_module(f"{__name__}.{name}")
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__():
    return sorted([*globals(), *_APPLICATION])
