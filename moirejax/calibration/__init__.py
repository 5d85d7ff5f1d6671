"""Calibration of a unit from recorded frames: the physical-parameter fit and its recipes, the residual head, the calibrate, evaluate and transfer workflows, and the wrench metrics.

It imports `inverse` and the layers below, never `design`.
"""

from ._calibration import (
    CalibrationResult as CalibrationResult,
    fit_physical_parameters as fit_physical_parameters,
    load_recipe as load_recipe,
    Recipe as Recipe,
)
from ._metrics import format_metrics as format_metrics, wrench_metrics as wrench_metrics
from ._residual_head import ResidualHead as ResidualHead
from ._workflows import (
    calibrate as calibrate,
    calibration_verdict as calibration_verdict,
    dataset_reference as dataset_reference,
    evaluate as evaluate,
    heldout_ridge_r2 as heldout_ridge_r2,
    identification_problems as identification_problems,
    load_calibrated as load_calibrated,
    ridge_baseline as ridge_baseline,
    spanning_frames as spanning_frames,
    transfer as transfer,
)
