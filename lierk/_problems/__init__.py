"""What lierk integrates: a vector field on SO(3) x R^n with its initial state.

- `base`: `AbstractProblem` (the field interface solvers call) and
  `AbstractRigidBody` (what solvers and tools rely on for a rigid body:
  omega0, torque-free or not, the splitting interface, the invariants);
- `rigid_body`: `RigidBodyWithEffects` and `FreeRigidBody` (attitude and body
  momentum as state);
- `spatial`: the report's `SpatialFreeRigidBody` (spatial momentum fixed);
- `effects`: gravity, torques and damping a body opts into;
- `spacecraft`: gravity gradient, magnetic torque and rotors (wheels);
- `kinematics`: momentum, energy and angular velocity of a rigid body;
- `variational`: a rigid body with its variational equations (the
  sensitivity of the exact flow, `lierk.sensitivity(method="variational")`).
"""

from . import effects as effects
from . import kinematics as kinematics
from . import spacecraft as spacecraft
from .base import AbstractProblem as AbstractProblem
from .base import AbstractRigidBody as AbstractRigidBody
from .rigid_body import FreeRigidBody as FreeRigidBody
from .rigid_body import RigidBodyWithEffects as RigidBodyWithEffects
from .rigid_body import heavy_top as heavy_top
from .spatial import SpatialFreeRigidBody as SpatialFreeRigidBody
from .variational import Variational as Variational
