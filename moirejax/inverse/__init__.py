"""Wrench inversion: the unknowns of a frame and what an inversion returns, the band
inversion of a frame (`Inverter`), its two entry points (`invert` for sets and recordings,
`frame_tracker` for camera streams), the whole-frame pixel refinement, and inverting
recordings into a wrench CSV, their traction maps and plots.

It imports `observe` and the layers below.
"""

from ._distributed import invert_distributed as invert_distributed
from ._inversion import (
    default_carriers as default_carriers,
    default_model_shape as default_model_shape,
    Inverter as Inverter,
    model_grid_for as model_grid_for,
)
from ._invert import frame_tracker as frame_tracker, FrameTracker as FrameTracker, invert as invert
from ._invert_io import (
    check_source as check_source,
    count_source_frames as count_source_frames,
    find_reference as find_reference,
    invert_recording as invert_recording,
    load_reference_image as load_reference_image,
)
from ._maps import (
    map_grid as map_grid,
    patch_tractions as patch_tractions,
    patches_area_mm2 as patches_area_mm2,
    read_traction_maps as read_traction_maps,
    read_wrench_csv as read_wrench_csv,
    row_number as row_number,
    row_patches as row_patches,
    stack_patches as stack_patches,
    TRACTION_MAP_SHAPE as TRACTION_MAP_SHAPE,
    TractionMaps as TractionMaps,
    write_traction_maps as write_traction_maps,
)
from ._pixel_fit import PixelFit as PixelFit, refine_in_pixels as refine_in_pixels
from ._plots import frames_worth_a_look as frames_worth_a_look, plot_inversion as plot_inversion
from ._state import Estimate as Estimate, LoadState as LoadState, Status as Status, Track as Track
