"""The wrench convention, its axes and units, and the paper's load ranges: the one definition of each.

Every layer that names a wrench axis, converts a torque or scales a wrench by its range
reads it from here (see `docs/conventions.md`).
"""

import numpy as np


WRENCH_CONVENTION = (
    "x = image columns (right), y = image up, z into the sensor surface (pressing is +Fz), "
    "origin at the image centre on the contact surface; forces N, torques N*m"
)
WRENCH_AXES = ("fx", "fy", "fz", "tx", "ty", "tz")
"""The wrench's components in order: forces along x, y, z, then torques about x, y, z."""
WRENCH_UNITS = ("N", "N", "N", "N·m", "N·m", "N·m")
"""The unit of each component of [`WRENCH_AXES`][moirejax.WRENCH_AXES]."""
# Public torques are N·m, the model's are N·mm.
NMM_PER_NM = 1000.0
# The model's tractions are MPa (N/mm²); pressure maps for other tools are Pa.
PA_PER_MPA = 1e6
PAPER_RANGES = {"fx": 0.2, "fy": 0.2, "fz": 1.2, "tx": 0.012, "ty": 0.012, "tz": 0.008}
"""The paper's calibrated load range of each axis (N and N·m): the scale on which errors are
reported and the solver's unknowns are normalised."""
# Scale of each wrench axis in the solver and the residual head: the ranges in WRENCH_AXES order.
WRENCH_SCALE = np.array([PAPER_RANGES[name] for name in WRENCH_AXES])


def centre_of_pressure_mm(wrench: np.ndarray) -> np.ndarray:
    """The centre of pressure `(x, y)` in mm of wrenches `(..., 6)`: where the normal force
    would act alone to give the torques about x and y. With the origin on the contact
    surface, Tx = sum(y p dA) and Ty = -sum(x p dA), so x = -Ty / Fz and y = Tx / Fz (NaN
    where Fz is not positive: a pull or no load has no centre of pressure)."""
    wrench = np.asarray(wrench, np.float64)
    fz = wrench[..., 2]
    pressing = fz > 0
    safe = np.where(pressing, fz, 1.0)
    centre = np.stack([-wrench[..., 4] / safe, wrench[..., 3] / safe], axis=-1) * NMM_PER_NM
    return np.where(pressing[..., None], centre, np.nan)
