"""Moved: the problems live in `lierk.problems`, their validators in
`lierk.validation`.  This module keeps the old names importable for one
release."""

from .problems.base import AbstractProblem as AbstractProblem
from .problems.spatial import SpatialFreeRigidBody as SpatialFreeRigidBody
from .validation import check_attitude as check_attitude
from .validation import check_vector as check_vector
from .validation import rigid_body_state as rigid_body_state
