"""Solvers: one file per family; `base` holds what they share."""

from .base import AbstractSolver as AbstractSolver
from .base import Step as Step
from .cf import CF4 as CF4
from .euler import ExplicitEuler as ExplicitEuler
from .euler import LieEuler as LieEuler
from .rkmk import DOP853 as DOP853
from .rkmk import DP54 as DP54
from .rkmk import RKF45 as RKF45
from .rkmk import RKMK as RKMK
from .rkmk import RKMK4 as RKMK4
from .rkmk import AbstractRKMK as AbstractRKMK
from .rkmk import NaiveLieRK4 as NaiveLieRK4
from .splitting import AbstractSplitting as AbstractSplitting
from .splitting import BlanesMoan4 as BlanesMoan4
from .splitting import BlanesMoan6 as BlanesMoan6
from .splitting import BlanesMoanRKN4 as BlanesMoanRKN4
from .splitting import BlanesMoanRKN6 as BlanesMoanRKN6
from .splitting import Splitting as Splitting
from .splitting import Strang as Strang
from .splitting import Yoshida4 as Yoshida4
from .splitting import Yoshida6 as Yoshida6
