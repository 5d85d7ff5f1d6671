"""Type aliases shared by the live modules."""

import numpy as np


# A real scalar as users pass it: Python or NumPy, int or float (annotations are checked
# at run time under pytest, where a plain `float` would reject `2`).
Real = float | int | np.floating | np.integer
