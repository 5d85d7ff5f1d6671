"""The unit's geometry as its own no-contact frame shows it.

Pitch deviations of a few per cent move the moiré period by tens of per cent (that is
the amplification), so before anything else each unit's moiré wavevectors are measured
on a no-contact frame, and the upper grating's apparent pitch and angle are set so that
the model reproduces them.
"""

import dataclasses
import math

import jax.numpy as jnp
import numpy as np

from ..physics import Device, wavenumber_grid
from ._peaks import spectral_peak, windowed_power_spectrum


def measure_moire_wavevectors(frame: np.ndarray, device: Device, search: float = 0.6) -> np.ndarray:
    """Spectral peak nearest each nominal moiré wavevector, refined to sub-bin precision.

    Searches within `search * |K|` of the nominal `K` of each family (rad/mm, x right,
    y up), and farther than `0.3 |K|` from DC, with `spectral_peak`. Returns an array
    `(families, 2)`.
    """
    power = windowed_power_spectrum(frame)
    dx = 1.0 / float(device.px_per_mm)
    kx, ky = wavenumber_grid(power.shape, dx, xp=np)
    KX, KY = kx[None, :], ky[:, None]
    found = []
    for K in np.asarray(device.moire_wavevectors()):
        norm = float(np.hypot(*K))
        mask = (np.hypot(KX - K[0], KY - K[1]) < search * norm) & (np.hypot(KX, KY) > 0.3 * norm)
        found.append(spectral_peak(power, mask, dx))
    return np.asarray(found)


def match_reference_geometry(device: Device, frame: np.ndarray) -> Device:
    """`device` with the upper grating's pitch and angle set to reproduce the moiré
    wavevectors measured on the no-contact `frame`.

    `K = k_1' - k_2`, so `k_1' = K + k_2` for each line set: its length gives the
    apparent pitch (converted back through the parallax `(Z + a)/Z`), its direction the
    angle. Which grating really deviated cannot be told from `K` alone; calibration
    against reference wrenches refines the split.
    """
    measured = measure_moire_wavevectors(frame, device)
    k2 = np.asarray(device.reference_wavevectors())
    k1 = measured + k2
    magnification = float(device.surface_magnification)
    pitch = float(np.mean(2 * np.pi / np.hypot(k1[:, 0], k1[:, 1]))) * magnification
    angles = np.arctan2(k1[:, 1], k1[:, 0])
    if device.n_sets == 2:
        second = angles[1] - float(device.cross_angle)
        alpha = math.atan2(np.sin(angles[0]) + np.sin(second), np.cos(angles[0]) + np.cos(second))
    else:
        alpha = float(angles[0])
    return dataclasses.replace(
        device, p1=jnp.asarray(pitch, dtype=device.p1.dtype), alpha1=jnp.asarray(alpha, dtype=device.p1.dtype)
    )
