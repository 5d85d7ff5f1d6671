"""moirejax: differentiable modelling, simulation and inversion of moire visuotactile sensors."""

import importlib.metadata

from ._band_model import (
    band_model as band_model,
    BandModel as BandModel,
    predicted_bands as predicted_bands,
    stray_beat_clearance as stray_beat_clearance,
)
from ._calibration import (
    CalibrationResult as CalibrationResult,
    fit_physical_parameters as fit_physical_parameters,
    load_recipe as load_recipe,
    Recipe as Recipe,
)
from ._contact import (
    Contact as Contact,
    surface_grid as surface_grid,
    surface_tractions as surface_tractions,
    SurfaceGrid as SurfaceGrid,
    traction_resultant as traction_resultant,
)
from ._conventions import (
    WRENCH_AXES as WRENCH_AXES,
    WRENCH_CONVENTION as WRENCH_CONVENTION,
    WRENCH_UNITS as WRENCH_UNITS,
)
from ._dataset import (
    Batch as Batch,
    Dataset as Dataset,
    DatasetWriter as DatasetWriter,
    export_recording as export_recording,
    import_recording as import_recording,
    ImportReport as ImportReport,
    open_dataset as open_dataset,
)
from ._design import (
    design_table as design_table,
    format_design_table as format_design_table,
    plot_design_maps as plot_design_maps,
)
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
from ._elastomer import (
    half_space_compliance as half_space_compliance,
    layer_compliance as layer_compliance,
    layer_response as layer_response,
    LayerResponse as LayerResponse,
    surface_displacement as surface_displacement,
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
from ._inversion import (
    default_model_shape as default_model_shape,
    Estimate as Estimate,
    frame_tracker as frame_tracker,
    initial_state as initial_state,
    invert_batch as invert_batch,
    invert_chunk as invert_chunk,
    invert_frame as invert_frame,
    invert_sequence as invert_sequence,
    Inverter as Inverter,
    model_grid_for as model_grid_for,
    Status as Status,
    Track as Track,
    track_frame as track_frame,
)
from ._metrics import format_metrics as format_metrics, wrench_metrics as wrench_metrics
from ._observability import (
    axis_ranges as axis_ranges,
    band_weight as band_weight,
    cramer_rao as cramer_rao,
    fisher_information as fisher_information,
    force_sensitivity as force_sensitivity,
    nominal_load as nominal_load,
    observability_table as observability_table,
    optimise_design as optimise_design,
    plot_observability as plot_observability,
    reduced_device as reduced_device,
    surface_phase_shift as surface_phase_shift,
)
from ._observables import (
    brightness_baseline as brightness_baseline,
    BrightnessBaseline as BrightnessBaseline,
    Demodulator as Demodulator,
    frame_summary as frame_summary,
    FrameSummary as FrameSummary,
    fringe_observables as fringe_observables,
    FringeFields as FringeFields,
    FringeObservables as FringeObservables,
    NumpyDemodulator as NumpyDemodulator,
    RealBandPass as RealBandPass,
    white_noise_variance as white_noise_variance,
)
from ._optics import binary_harmonics as binary_harmonics, gaussian_mtf as gaussian_mtf
from ._pixel_fit import PixelFit as PixelFit, refine_in_pixels as refine_in_pixels
from ._reference import match_reference_geometry as match_reference_geometry
from ._render import (
    camera_noise as camera_noise,
    deformation as deformation,
    HighFidelity as HighFidelity,
    pixel_noise_variance as pixel_noise_variance,
    render_deformed as render_deformed,
    render_frame as render_frame,
    render_frame_high as render_frame_high,
)
from ._simulate import (
    Deviations as Deviations,
    load_schedule as load_schedule,
    LoadSchedule as LoadSchedule,
    perturb_device as perturb_device,
    simulate_dataset as simulate_dataset,
)
from ._workflows import (
    calibrate as calibrate,
    dataset_reference as dataset_reference,
    evaluate as evaluate,
    heldout_ridge_r2 as heldout_ridge_r2,
    invert_frames as invert_frames,
    load_calibrated as load_calibrated,
    ridge_baseline as ridge_baseline,
    spanning_frames as spanning_frames,
    transfer as transfer,
)


__version__ = importlib.metadata.version("moirejax")
