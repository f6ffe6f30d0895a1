"""The checks lierk applies to a rigid body's inputs, for a front end that
checks a whole input first and names its own keys (as `lierk.app.scene`
does for scene files: ``body.inertia``, ``initial.attitude``).

The problems (`lierk.FreeRigidBody`, `lierk.RigidBodyWithEffects`) run the
same checks when they are built, naming their own arguments; these
functions let a caller run them first, word the messages itself, and then
build the problem inside `inertia_warned` so that nothing is warned twice.

- `check_attitude`: an initial attitude, a rotation matrix.
- `impossible_inertia`, `nearly_singular_inertia`: the warnings an inertia
  deserves (no rigid body has it; too close to singular for the precision).
- `state_range_error`: why a body's state does not fit a float type.
- `tolerances_below_rounding`: why ``rtol`` and ``atol`` cannot be met in
  a float type (`lierk.solve` refuses them with its message).
- `inertia_warned`: build bodies without repeating those warnings.
- `show`: a value on one line, as lierk's messages print them.
- `checking_on_host`: deprecated, always False (`lierk.checked_on_host`
  does nothing now).

They are host checks, of concrete values (NumPy arrays or numbers):
`check_attitude` also accepts a traced attitude, which it then checks in
the program (NaN where it fails, which a solve reports).
"""

from ._validation import check_attitude as check_attitude
from ._validation import checking_on_host as checking_on_host
from ._validation import impossible_inertia as impossible_inertia
from ._validation import inertia_warned as inertia_warned
from ._validation import nearly_singular_inertia as nearly_singular_inertia
from ._validation import show as show
from ._validation import state_range_error as state_range_error
from ._validation import tolerances_below_rounding as tolerances_below_rounding

__all__ = [
    "check_attitude",
    "impossible_inertia",
    "nearly_singular_inertia",
    "state_range_error",
    "inertia_warned",
    "show",
    "checking_on_host",
    "tolerances_below_rounding",
]
