"""Wrench inversion: the band inversion of a frame, its chunked and tracked forms, the whole-frame pixel refinement, and inverting recordings into a wrench CSV.

It imports `observe` and the layers below.
"""

from ._inversion import (
    default_carriers as default_carriers,
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
from ._invert_io import (
    check_source as check_source,
    find_reference as find_reference,
    invert_recording as invert_recording,
    load_reference_image as load_reference_image,
)
from ._pixel_fit import PixelFit as PixelFit, refine_in_pixels as refine_in_pixels
