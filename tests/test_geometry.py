import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import assume, given, settings, strategies as st

import moirejax as mj
from moirejax.physics._geometry import (
    apparent_pitch,
    effective_mismatch_first_order,
    geometric_amplification,
    grating_wavevector,
    moire_orientation,
    moire_period,
    moire_period_angle_dominated,
    moire_period_exact,
    moire_period_general,
    moire_period_pitch_dominated,
    moire_wavevector,
)

from .helpers import check_grad_against_fd


def _fft_moire_peak(p1, p2, alpha1, alpha2, n=1024):
    """Render cos(k1.x) cos(k2.x) in numpy and locate its lowest non-DC spectral peak."""
    dx = min(p1, p2) / 5
    coords = (np.arange(n) - n / 2) * dx
    x, y = np.meshgrid(coords, -coords)
    k1 = 2 * np.pi / p1 * np.array([np.cos(alpha1), np.sin(alpha1)])
    k2 = 2 * np.pi / p2 * np.array([np.cos(alpha2), np.sin(alpha2)])
    image = np.cos(k1[0] * x + k1[1] * y) * np.cos(k2[0] * x + k2[1] * y)
    # A Gaussian window makes each log-magnitude peak an exact parabola, so a three-point
    # fit recovers its sub-bin position.
    sigma = n / 7
    w = np.exp(-0.5 * ((np.arange(n) - n / 2) / sigma) ** 2)
    spectrum = np.abs(np.fft.fftshift(np.fft.fft2(image * np.outer(w, w))))
    freqs = np.fft.fftshift(np.fft.fftfreq(n, dx)) * 2 * np.pi
    kx, ky = np.meshgrid(freqs, -freqs)
    radius = np.hypot(kx, ky)
    k_min = min(np.linalg.norm(k1), np.linalg.norm(k2))
    mask = (radius > 6 * 2 * np.pi / (n * dx)) & (radius < k_min / 2)
    i, j = np.unravel_index(np.argmax(np.where(mask, spectrum, 0)), spectrum.shape)
    logs = np.log(spectrum + 1e-300)

    def refine(lm, l0, lp):
        return 0.5 * (lm - lp) / (lm - 2 * l0 + lp)

    dj = refine(logs[i, j - 1], logs[i, j], logs[i, j + 1])
    di = refine(logs[i - 1, j], logs[i, j], logs[i + 1, j])
    bin_k = freqs[1] - freqs[0]
    K_fft = np.array([freqs[j] + dj * bin_k, -(freqs[i] + di * bin_k)])
    return 2 * np.pi / np.linalg.norm(K_fft)


@settings(max_examples=25, deadline=None)
@given(
    p2=st.floats(0.2, 0.45),
    mismatch=st.floats(-0.12, 0.12),
    alpha1=st.floats(-0.3, 0.3),
    dalpha_deg=st.floats(-8.0, 8.0),
)
def test_general_period_matches_fft_peak(p2, mismatch, alpha1, dalpha_deg):
    p1 = p2 * (1 + mismatch)
    dalpha = math.radians(dalpha_deg)
    period = float(moire_period_general(p1, p2, dalpha))
    n = 1024
    field = n * min(p1, p2) / 5
    # At least four fringes in the rendered field, and a moire well below the gratings.
    assume(4 * period < field and period > 8 * max(p1, p2))
    measured = _fft_moire_peak(p1, p2, alpha1 + dalpha, alpha1, n=n)
    assert abs(measured - period) / period < 0.01


def test_wavevector_period_and_orientation_agree_with_eq5():
    p1, p2, a1, a2 = 0.35, 0.30, 0.1, 0.04
    K = moire_wavevector(grating_wavevector(p1, a1), grating_wavevector(p2, a2))
    assert np.isclose(moire_period(K), moire_period_general(p1, p2, a1 - a2), rtol=1e-12)
    # Orientation of k1 - k2 by hand.
    Kx = 2 * np.pi * (np.cos(a1) / p1 - np.cos(a2) / p2)
    Ky = 2 * np.pi * (np.sin(a1) / p1 - np.sin(a2) / p2)
    assert np.isclose(moire_orientation(K), np.arctan2(Ky, Kx), rtol=1e-12)


def test_limits_of_eq5():
    # Angle-dominated: equal pitches, small angle.
    p = 0.3
    for dalpha in (1e-3, 1e-2):
        assert np.isclose(moire_period_general(p, p, dalpha), moire_period_angle_dominated(p, p, dalpha), rtol=1e-4)
    # Pitch-dominated: aligned gratings, small mismatch: p1 p2/|p1-p2| vs p/delta agree to O(delta^2).
    p1, p2 = 0.301, 0.300
    assert np.isclose(moire_period_general(p1, p2, 0.0), moire_period_pitch_dominated(p1, p2), rtol=1e-5)
    assert np.isclose(moire_period_general(p1, p2, 0.0), p1 * p2 / (p1 - p2), rtol=1e-12)


@pytest.mark.parametrize(
    "name, amplification, delta_eff", [("dense", 4.00, 0.25), ("mid", 14.00, 0.10), ("sparse", 24.00, 0.07)]
)
def test_paper_sensitivity_table(name, amplification, delta_eff):
    d = mj.preset(name)
    assert abs(float(geometric_amplification(d.p1, d.p2, 0.0, d.a, d.Z)) - amplification) < 0.005
    assert abs(float(effective_mismatch_first_order(d.p1, d.p2, d.a, d.Z)) - delta_eff) < 0.01


def test_exact_parallax_matches_projected_wavevectors():
    d = mj.preset("mid")
    K = d.moire_wavevectors()[0]
    assert np.isclose(moire_period(K), moire_period_exact(d.p1, d.p2, 0.0, d.a, d.Z), rtol=1e-12)
    assert np.isclose(apparent_pitch(0.35, 3.0, 12.0), 0.28, rtol=1e-12)


def test_gradients_match_finite_differences():
    x = jnp.array([0.35, 0.30, 0.02, 3.0, 12.0])

    def figures(x):
        p1, p2, dalpha, a, Z = x
        return jnp.stack(
            [
                moire_period_exact(p1, p2, dalpha, a, Z),
                geometric_amplification(p1, p2, dalpha, a, Z),
                moire_orientation(
                    moire_wavevector(grating_wavevector(p1 * Z / (Z + a), dalpha), grating_wavevector(p2, 0.0))
                ),
            ]
        )

    check_grad_against_fd(figures, x)
    jac = jax.jacfwd(figures)(x)
    assert jnp.all(jnp.isfinite(jac))
    # dLambda/da is negative here: more separation shrinks p1' towards... away from p2.
    assert jac[0, 3] < 0


def test_jit_vmap_grad_compose():
    p1 = jnp.linspace(0.3, 0.4, 5)

    def amp(p1):
        return geometric_amplification(p1, 0.3, 0.01, 3.0, 12.0)

    g = jax.jit(jax.vmap(jax.grad(amp)))(p1)
    g2 = jax.vmap(jax.grad(amp))(p1)
    assert jnp.allclose(g, g2)
