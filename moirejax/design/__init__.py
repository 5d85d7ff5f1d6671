"""Choosing a design: the design-space tables and maps, observability (fringe sensitivities, Fisher information, Cramér–Rao bounds) and the gradient design search.

It imports `observe`, `simulate` and the layers below, never `calibration` or `inverse`.
"""

from ._design import (
    design_table as design_table,
    format_design_table as format_design_table,
    plot_design_maps as plot_design_maps,
)
from ._observability import (
    axis_ranges as axis_ranges,
    band_weight as band_weight,
    cramer_rao as cramer_rao,
    fisher_information as fisher_information,
    force_sensitivity as force_sensitivity,
    nominal_load as nominal_load,
    observability_table as observability_table,
    plot_observability as plot_observability,
    reduced_device as reduced_device,
    surface_phase_shift as surface_phase_shift,
)
from ._optimise import optimise_design as optimise_design
