"""The learned residual: a small linear correction of what the physics leaves.

Its inputs are the physical estimate (wrench over the paper's ranges, contact centre and
log radius); its output is a correction in the same scaled units. The correction is linear
in those inputs and in the normal force times the contact's position and size: a unit's
systematic errors are offsets, cross-talk between axes (a pressure tilt read as shear
along line gratings), and a sensitivity to the normal force that varies over the pad (a
press read a few per cent high on one side); the products carry the last.

A correction of that form adds up over the axes of a load, so what it learned from the
isolated-axis presses, shears and twists of a calibration protocol holds for their
combinations. A multilayer perceptron in its place fitted the calibration frames as well
and extrapolated to combined loads arbitrarily: on a unit whose glow its device did not
describe, its correction took the held-out Fx from R² 0.9995 (the physics alone) to 0.85,
where this one leaves it at 0.9995; on an independent renderer's unit both lifted the
shear along the lines from 0.52 to 0.67-0.70 and the tilts to 0.97-0.99. Products of the
shear or the twist with the position, which such a protocol does not excite (it shears
and twists at the centre), took their weights from noise and read combined loads worse.

It is fitted in closed form by ridge regression, the penalty chosen by cross-validation on
the calibration frames; an axis whose cross-validated error it does not lower, beyond the
noise of that comparison, below its mean residual's keeps just that mean.

The solver's standard errors hold the camera noise only, not the error of a model that
describes a unit inexactly, which on such a unit is most of the error: a corrected
estimate's standard error adds the head's cross-validated residual to the solver's, in
quadrature. That residual holds part of the noise as well, so the interval errs wide where
the model fits; it is the error the calibration measured on frames the correction did not
learn from.
"""

import json
from pathlib import Path

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._conventions import WRENCH_SCALE
from .._fileio import atomic_write_bytes, atomic_write_text, DataError


N_FEATURES = 9
# The basis: the nine features, and the scaled normal force times the contact's x0, y0 and
# log radius.
N_BASIS = N_FEATURES + 3
# The ridge penalties tried (per frame, on a basis in units of the axes' ranges), and the
# folds of the cross-validation that chooses among them.
_PENALTIES = (1e-5, 1e-4, 1e-3, 1e-2, 1e-1, 1.0)
_FOLDS = 5
# How many standard errors of the frames' paired gains the cross-validated error must fall
# by for an axis to be corrected. The gains are heavy-tailed (a few poorly read frames carry
# most of an axis' error): on an independent renderer's line gratings, the shear along the
# lines, whose held-out R² the correction lifts from 0.52 to 0.70, fell by 1.6 of them.
_SIGNIFICANCE = 1.0
# What a head file holds, in order: a file of another layout is refused by name.
_LEAVES = ["weight", "bias", "residual_sd"]


def head_features(wrench: np.ndarray, x0: np.ndarray, y0: np.ndarray, radius: np.ndarray) -> np.ndarray:
    """Head inputs from physical estimates: `(n, 9)`."""
    return np.concatenate(
        [wrench / WRENCH_SCALE, (x0 / 10.0)[:, None], (y0 / 10.0)[:, None], np.log(np.maximum(radius, 1e-3))[:, None]],
        axis=1,
    )


def head_basis(features: Float[Array | np.ndarray, "*b 9"]) -> Float[Array | np.ndarray, "*b 12"]:
    """The terms the correction is linear in: the features, and the scaled normal force times
    the contact's x0, y0 and log radius (module notes). NumPy in, NumPy out (the fit runs in
    double precision whatever JAX's setting); JAX in, JAX out."""
    xp = np if isinstance(features, np.ndarray) else jnp
    return xp.concatenate([features, features[..., 2:3] * features[..., 6:]], axis=-1)


class ResidualHead(eqx.Module):
    """Linear correction of a physical wrench estimate on `head_basis` (module notes).

    **Arguments:**

    - `weight`: `(6, 12)`, the scaled correction per basis term.
    - `bias`: `(6,)`, the scaled correction of every estimate.
    - `residual_sd`: `(6,)`, the scaled root-mean-square error the correction left on
      calibration frames it did not learn from (module notes).
    """

    weight: Float[Array, "6 12"]
    bias: Float[Array, "6"]
    residual_sd: Float[Array, "6"]

    def __check_init__(self):
        if self.weight.shape != (6, N_BASIS) or self.bias.shape != (6,) or self.residual_sd.shape != (6,):
            raise ValueError(
                f"a residual head has a (6, {N_BASIS}) weight, a (6,) bias and a (6,) residual_sd, got "
                f"{self.weight.shape}, {self.bias.shape} and {self.residual_sd.shape}"
            )

    def __call__(self, features: Float[Array, " 9"]) -> Float[Array, " 6"]:
        return self.weight @ head_basis(features) + self.bias

    def correct(self, wrench: np.ndarray, x0: np.ndarray, y0: np.ndarray, radius: np.ndarray) -> np.ndarray:
        """Corrected wrenches `(n, 6)` in N and N·m. NumPy throughout: a live stream corrects
        one frame at a time without dispatching JAX operations."""
        # In the head's own precision: a head saved in float32 also corrects float64 runs.
        weight, bias = np.asarray(self.weight), np.asarray(self.bias)
        basis = head_basis(head_features(wrench, x0, y0, radius).astype(weight.dtype))
        return wrench + np.asarray(basis @ weight.T + bias, dtype=np.float64) * WRENCH_SCALE

    def residual_variance(self) -> np.ndarray:
        """The variance `(6,)` in N² and (N·m)² the head adds to a corrected estimate's: the
        square of its cross-validated residual (module notes)."""
        return (np.asarray(self.residual_sd, dtype=np.float64) * WRENCH_SCALE) ** 2

    def corrected_sigma(self, sigma: np.ndarray) -> np.ndarray:
        """Standard errors `(n, 6)` of corrected wrenches, in N and N·m, from the solver's
        `sigma`: both in quadrature."""
        return np.sqrt(np.asarray(sigma, dtype=np.float64) ** 2 + self.residual_variance())

    def corrected_covariance(self, covariance: np.ndarray) -> np.ndarray:
        """Covariances `(..., 6, 6)` of corrected wrenches from the solver's: the head's
        residual variance added on the diagonal, so that their diagonals are the squares of
        [`corrected_sigma`][ResidualHead.corrected_sigma]."""
        return np.asarray(covariance, dtype=np.float64) + np.diag(self.residual_variance())


def _ridge(basis: np.ndarray, targets: np.ndarray, penalty: float):
    """Weights and bias of the ridge fit of `targets` on the centred `basis`.

    The basis is not standardised: its terms are in units of the axes' ranges and of 10 mm,
    so a term the calibration frames barely vary (the shear times the position, where the
    protocol shears only at the centre) keeps a weight the penalty holds small instead of one
    scaled up to fit its noise, which combined loads would then multiply."""
    mean = basis.mean(axis=0)
    centred = basis - mean
    offset = targets.mean(axis=0)
    gram = centred.T @ centred + penalty * len(basis) * np.eye(basis.shape[1])
    weight = np.linalg.solve(gram, centred.T @ (targets - offset)).T
    return weight, offset - weight @ mean


def train_residual_head(
    features: np.ndarray, targets: np.ndarray, *, seed: int = 0, dtype=np.float32
) -> tuple[ResidualHead, dict]:
    """Fit a [`ResidualHead`][] to `targets - physical estimate` (both scaled), by ridge
    regression with the penalty chosen by cross-validation over the frames. An axis gets
    the linear correction only where it lowers the axis' cross-validated squared error, against
    the mean residual alone, by more than that reduction's standard error over the frames
    (`_SIGNIFICANCE`): a correction that does not beat the noise of its own validation is not
    learned, and the axis keeps its mean residual. Returns the head and its training
    record (the penalty, each axis' cross-validated mean squared error without and with the
    correction, and the corrected axes). The head's `residual_sd` is the cross-validated
    root-mean-square error of what each axis keeps: the correction, or the mean alone."""
    basis = np.asarray(head_basis(np.asarray(features, np.float64)), np.float64)
    targets = np.asarray(targets, np.float64)
    n = len(basis)
    folds = np.random.default_rng(seed).permutation(n) % _FOLDS
    without = np.zeros((n, 6))
    errors = np.zeros((len(_PENALTIES), n, 6))
    for fold in range(_FOLDS):
        train, test = folds != fold, folds == fold
        without[test] = (targets[test] - targets[train].mean(axis=0)) ** 2
        for k, penalty in enumerate(_PENALTIES):
            weight, bias = _ridge(basis[train], targets[train], penalty)
            errors[k, test] = (targets[test] - basis[test] @ weight.T - bias) ** 2
    best = int(np.argmin(errors.sum(axis=(1, 2))))
    gain = without - errors[best]
    corrected = gain.mean(axis=0) > _SIGNIFICANCE * gain.std(axis=0) / np.sqrt(n)
    weight, bias = _ridge(basis, targets, _PENALTIES[best])
    # An axis not corrected keeps the mean of its residual, the correction it was compared with.
    weight, bias = np.where(corrected[:, None], weight, 0.0), np.where(corrected, bias, targets.mean(axis=0))
    kept = np.where(corrected, errors[best].mean(axis=0), without.mean(axis=0))
    head = ResidualHead(jnp.asarray(weight, dtype), jnp.asarray(bias, dtype), jnp.asarray(np.sqrt(kept), dtype))
    return head, {
        "penalty": _PENALTIES[best],
        "cv_mse_without": without.mean(axis=0).tolist(),
        "cv_mse_with": errors[best].mean(axis=0).tolist(),
        "axes_corrected": [axis for axis, keep in zip(("fx", "fy", "fz", "tx", "ty", "tz"), corrected) if keep],
    }


def save_head(path: str | Path, head: ResidualHead) -> None:
    """Write the head's weights (equinox serialisation) and what it is beside them."""
    import io

    buffer = io.BytesIO()
    eqx.tree_serialise_leaves(buffer, head)
    atomic_write_bytes(path, buffer.getvalue())
    meta = {"kind": "linear", "basis": N_BASIS, "leaves": _LEAVES, "dtype": str(head.weight.dtype)}
    atomic_write_text(str(path) + ".json", json.dumps(meta) + "\n")


def load_head(path: str | Path) -> ResidualHead:
    """Read a head written by [`save_head`][], in the precision it was saved in (a head
    saved in float32 loads under `jax_enable_x64` too)."""
    meta = json.loads(Path(str(path) + ".json").read_text())
    if meta.get("kind") != "linear" or meta.get("basis") != N_BASIS or meta.get("leaves") != _LEAVES:
        raise DataError(
            f"{path}: a residual head of another kind ({meta}), written by an earlier moirejax; "
            "calibrate the unit again, or read the device alone with moirejax.load_device"
        )
    dtype = jnp.dtype(meta["dtype"])
    skeleton = ResidualHead(jnp.zeros((6, N_BASIS), dtype), jnp.zeros(6, dtype), jnp.zeros(6, dtype))
    with open(path, "rb") as f:
        return eqx.tree_deserialise_leaves(f, skeleton)
