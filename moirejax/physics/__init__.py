"""The sensor's physics: grating and moiré geometry, the elastomer, contact loads, the device description, optics and the renderer with its camera noise model.

It imports only `data` and the foundation modules (`_plotting`, `_fileio`, `_conventions`).
"""

from ._contact import (
    Contact as Contact,
    grid_shape as grid_shape,
    surface_grid as surface_grid,
    surface_tractions as surface_tractions,
    SurfaceGrid as SurfaceGrid,
    traction_resultant as traction_resultant,
    traction_spectrum as traction_spectrum,
)
from ._device import (
    Device as Device,
    device_from_json as device_from_json,
    device_to_json as device_to_json,
    Elastomer as Elastomer,
    load_device as load_device,
    Optics as Optics,
    preset as preset,
    PRESET_PITCHES as PRESET_PITCHES,
    save_device as save_device,
)
from ._elastomer import (
    half_space_compliance as half_space_compliance,
    layer_compliance as layer_compliance,
    layer_response as layer_response,
    LayerResponse as LayerResponse,
    surface_displacement as surface_displacement,
)
from ._fourier import wavenumber_grid as wavenumber_grid
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
from ._optics import (
    background_radiance as background_radiance,
    binary_harmonics as binary_harmonics,
    camera_response as camera_response,
    gaussian_blur_fft as gaussian_blur_fft,
    gaussian_mtf as gaussian_mtf,
    image_coordinates as image_coordinates,
    line_transmission as line_transmission,
    separable_gaussian_blur as separable_gaussian_blur,
)
from ._render import (
    camera_noise as camera_noise,
    deformation as deformation,
    HighFidelity as HighFidelity,
    Mechanics as Mechanics,
    mechanics as mechanics,
    noise_as_arrays as noise_as_arrays,
    pixel_noise_variance as pixel_noise_variance,
    reference_grating_phase as reference_grating_phase,
    render_deformed as render_deformed,
    render_deformed_high as render_deformed_high,
    render_frame as render_frame,
    render_frame_high as render_frame_high,
    scene_radiance as scene_radiance,
    upper_grating_phase as upper_grating_phase,
)
