"""moirejax: differentiable modelling, simulation and inversion of moire visuotactile sensors."""

import importlib.metadata

from ._design import design_table as design_table, plot_design_maps as plot_design_maps
from ._device import (
    Device as Device,
    device_from_json as device_from_json,
    device_to_json as device_to_json,
    Elastomer as Elastomer,
    load_device as load_device,
    Optics as Optics,
    preset as preset,
    save_device as save_device,
)
from ._fileio import (
    atomic_write_bytes as atomic_write_bytes,
    atomic_write_text as atomic_write_text,
    DataError as DataError,
    read_json as read_json,
    write_json as write_json,
)
from ._geometry import (
    apparent_pitch as apparent_pitch,
    effective_mismatch_exact as effective_mismatch_exact,
    effective_mismatch_first_order as effective_mismatch_first_order,
    geometric_amplification as geometric_amplification,
    grating_wavevector as grating_wavevector,
    moire_orientation as moire_orientation,
    moire_period as moire_period,
    moire_period_angle_dominated as moire_period_angle_dominated,
    moire_period_exact as moire_period_exact,
    moire_period_general as moire_period_general,
    moire_period_pitch_dominated as moire_period_pitch_dominated,
    moire_wavevector as moire_wavevector,
    object_mismatch as object_mismatch,
    relative_mismatch as relative_mismatch,
    shear_amplification as shear_amplification,
)


__version__ = importlib.metadata.version("moirejax")
