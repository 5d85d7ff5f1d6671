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

from ..physics import Device


def measure_moire_wavevectors(frame: np.ndarray, device: Device, search: float = 0.6) -> np.ndarray:
    """Spectral peak nearest each nominal moiré wavevector, refined to sub-bin precision.

    Searches within `search * |K|` of the nominal `K` of each family (rad/mm, x right,
    y up) on a Hann-windowed spectrum; a parabola through the log magnitude refines the
    peak. Returns an array `(families, 2)`.
    """
    frame = np.asarray(frame, dtype=np.float64)
    h, w = frame.shape
    dx = 1.0 / float(device.px_per_mm)
    window = np.outer(np.hanning(h), np.hanning(w))
    spectrum = np.abs(np.fft.fftshift(np.fft.fft2((frame - frame.mean()) * window)))
    kx = np.fft.fftshift(np.fft.fftfreq(w, dx)) * 2 * np.pi
    ky = -np.fft.fftshift(np.fft.fftfreq(h, dx)) * 2 * np.pi
    KX, KY = np.meshgrid(kx, ky)
    logs = np.log(spectrum + 1e-300)
    found = []
    for K in np.asarray(device.moire_wavevectors()):
        norm = float(np.hypot(*K))
        mask = (np.hypot(KX - K[0], KY - K[1]) < search * norm) & (np.hypot(KX, KY) > 0.3 * norm)
        i, j = np.unravel_index(np.argmax(np.where(mask, spectrum, 0.0)), spectrum.shape)
        i = min(max(i, 1), h - 2)
        j = min(max(j, 1), w - 2)

        def refine(lm, l0, lp):
            denominator = lm - 2 * l0 + lp
            return 0.0 if denominator == 0 else 0.5 * (lm - lp) / denominator

        dj = refine(logs[i, j - 1], logs[i, j], logs[i, j + 1])
        di = refine(logs[i - 1, j], logs[i, j], logs[i + 1, j])
        found.append([kx[j] + dj * (kx[1] - kx[0]), ky[i] + di * (ky[1] - ky[0])])
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
    magnification = float((device.Z + device.a) / device.Z)
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
