"""What a frame shows: demodulation into fringe fields and observables, the band model that predicts them without rendering, and the match of a reference frame's geometry.

It imports `physics` and the layers below, never `simulate`.
"""

from ._band_model import (
    band_model as band_model,
    BandModel as BandModel,
    carrier_band_radius as carrier_band_radius,
    carrier_coefficients as carrier_coefficients,
    complex_ratio as complex_ratio,
    predicted_bands as predicted_bands,
    stray_beat_clearance as stray_beat_clearance,
)
from ._observables import (
    BAND_FRACTION as BAND_FRACTION,
    BAND_ROLLOFF as BAND_ROLLOFF,
    BasebandPass as BasebandPass,
    brightness_baseline as brightness_baseline,
    BrightnessBaseline as BrightnessBaseline,
    DemodulationWindowTooSmall as DemodulationWindowTooSmall,
    Demodulator as Demodulator,
    frame_summary as frame_summary,
    FrameSummary as FrameSummary,
    fringe_observables as fringe_observables,
    FringeFields as FringeFields,
    FringeObservables as FringeObservables,
    NumpyDemodulator as NumpyDemodulator,
    raised_cosine_window as raised_cosine_window,
    RealBandPass as RealBandPass,
    white_noise_map as white_noise_map,
    white_noise_variance as white_noise_variance,
)
from ._peaks import spectral_peak as spectral_peak, windowed_power_spectrum as windowed_power_spectrum
from ._reference import (
    match_reference_geometry as match_reference_geometry,
    measure_moire_wavevectors as measure_moire_wavevectors,
)
