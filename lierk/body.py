"""Moved: `lierk.problems.kinematics`.  This module keeps the old names
importable for one release."""

from .problems.kinematics import angular_momentum as angular_momentum
from .problems.kinematics import body_angular_velocity as body_angular_velocity
from .problems.kinematics import kinetic_energy as kinetic_energy
