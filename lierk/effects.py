"""Moved: `lierk.problems.effects`.  This module keeps the old names
importable for one release."""

from .problems.effects import AbstractEffect as AbstractEffect
from .problems.effects import BodyTorque as BodyTorque
from .problems.effects import Damping as Damping
from .problems.effects import Gravity as Gravity
from .problems.effects import SpaceTorque as SpaceTorque
from .problems.effects import TimedTorque as TimedTorque
