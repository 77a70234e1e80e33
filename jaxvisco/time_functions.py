"""Time functions that scale dead loads and prescribed motions (`Scene(loads=...)`,
`Scene(prescribed=...)`): `Constant`, `Step`, `Ramp`, `Table`, `Sine`, and
`from_dict` for their scene-file form ``{ type = "ramp", t0 = 0.0, t1 = 1.0 }``."""

from ._time_functions import TIME_FUNCTIONS as TIME_FUNCTIONS
from ._time_functions import AbstractTimeFunction as AbstractTimeFunction
from ._time_functions import Constant as Constant
from ._time_functions import Ramp as Ramp
from ._time_functions import Sine as Sine
from ._time_functions import Step as Step
from ._time_functions import Table as Table
from ._time_functions import time_function_from_dict as from_dict  # noqa: F401  (public name)
