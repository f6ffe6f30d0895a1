"""Moved: `lierk.problems.rigid_body`.  This module keeps the old names
importable for one release."""

from .problems.rigid_body import FreeRigidBody as FreeRigidBody
from .problems.rigid_body import RigidBodyWithEffects as RigidBodyWithEffects
