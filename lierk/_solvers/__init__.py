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

SOLVERS: dict[str, type] = {
    c.__name__: c
    for c in (
        ExplicitEuler,
        LieEuler,
        NaiveLieRK4,
        RKMK4,
        CF4,
        RKF45,
        DP54,
        DOP853,
        Strang,
        Yoshida4,
        BlanesMoan4,
        Yoshida6,
        BlanesMoan6,
        BlanesMoanRKN4,
        BlanesMoanRKN6,
    )
}
"""Solver names (as scenes, the command line and `lierk.app.accuracy` take them)
to their classes."""


def solver_class(name: str) -> type:
    """The solver class called ``name`` in `SOLVERS`, in any letter case.

    Raises:
        ValueError: an unknown name; the message lists the known ones.
    """
    names = {n.lower(): n for n in SOLVERS}
    if not isinstance(name, str) or name.lower() not in names:
        raise ValueError(f"unknown solver {name!r}; choose from: {', '.join(SOLVERS)}")
    return SOLVERS[names[name.lower()]]
