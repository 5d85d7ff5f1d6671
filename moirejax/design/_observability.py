r"""How well a design can see a wrench: fringe sensitivities, Fisher information, Cramér–Rao bounds.

Three views of one question, from the cheapest to the most honest:

- **Sensitivities** ([`force_sensitivity`][]): what a unit load does to the fringes near
  the contact, through the mechanics and the phase relation of `grating_phases`. A
  surface displacement $u$ and compression $w$ at surface point $X$ change the phase of
  fringe family $f$ by
  $$\Delta\psi_f = -k_{1f} \cdot \big(u + X\, w/(Z + a)\big),$$
  in radians, *whatever the moiré period*: the amplification $A$ moves the fringes
  farther in millimetres, but not in phase. Rotations and period changes, being ratios
  of the local fringe wavevector to $K_f$, do scale with $\Lambda/p_1$.
- **Fisher information** ([`fisher_information`][]): the Jacobian $J$ of the rendered
  frame with respect to the wrench (and the contact latents) weighted by the camera's
  pixel noise, $F = J^\top \Sigma^{-1} J$. It counts pixels, fringe contrast,
  saturation and the confusion between axes, which sensitivities do not.
- **Cramér–Rao bounds** ([`cramer_rao`][], [`observability_table`][]): the standard
  deviation no unbiased single-frame estimator can beat, with the contact position and
  radius estimated alongside (the marginal bound) or known (the conditional bound).

Two estimators, two bounds (`estimator=`). `"pixels"` is the bound of an estimator that
reads every pixel ([`refine_in_pixels`][]), the grating carriers included. `"bands"` is
the bound of one that reads only the Fourier bins of the moiré bands and the brightness
band, as the band inversion ([`Inverter`][], `moirejax invert`) does: the information
of each bin of the frame's spectrum, weighted by the demodulator's band windows. A
design chosen by the first can put its information in the carriers, where the band
inversion does not look; the design search therefore uses the second by default.

Wrenches are `[fx, fy, fz, tx, ty, tz]` in N and N·m; the paper's calibrated ranges
(`PAPER_RANGES` in `moirejax/_conventions.py`) scale the axes wherever they are compared.

The search over designs built on these bounds is `_optimise.py`; the three views stay in one
module because they share the nominal load, the parameter scaling and the estimators.
"""

import dataclasses
import math
from typing import Any, Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from .._conventions import WRENCH_AXES, WRENCH_SCALE
from ..observe import BAND_FRACTION, BAND_ROLLOFF, raised_cosine_window
from ..physics import (
    Contact,
    deformation,
    Device,
    HighFidelity,
    noise_as_arrays,
    pixel_noise_variance,
    PRESET_PITCHES,
    render_frame,
    surface_grid,
    SurfaceGrid,
    wavenumber_grid,
)


LATENT_NAMES = ("x0", "y0", "radius")
PARAMETER_NAMES = WRENCH_AXES + LATENT_NAMES
# The nominal contact of every report: a centred press of radius 3.5 mm under 0.6 N preload.
NOMINAL_WRENCH = (0.0, 0.0, 0.6, 0.0, 0.0, 0.0)
NOMINAL_RADIUS = 3.5


def axis_ranges(dtype=float) -> Float[Array, "6"]:
    """The paper's calibrated range of each wrench axis (N, N·m), in `WRENCH_AXES` order."""
    return jnp.asarray(WRENCH_SCALE, dtype=dtype)


def nominal_load(dtype=float) -> tuple[Float[Array, "6"], Contact]:
    """The nominal wrench and contact: a centred press, radius 3.5 mm, Fz = 0.6 N."""
    zero = jnp.zeros((), dtype)
    return jnp.asarray(NOMINAL_WRENCH, dtype), Contact(x0=zero, y0=zero, radius=zero + NOMINAL_RADIUS)


# ---------------------------------------------------------------------------------------
# Sensitivities.


def surface_phase_shift(
    device: Device, displacement: Float[Array, "3 h w"], X: Float[Array, "h w"], Y: Float[Array, "h w"]
) -> Float[Array, "sets h w"]:
    r"""Fringe phase change $-k_{1f}\cdot(u + X w/(Z + a))$ of every family at surface points (X, Y).

    This is the change of the upper-grating phase of `grating_phases` (the reference
    grating does not move), so it is exactly linear in the displacement.
    """
    ux, uy, w = displacement
    parallax = w / (device.Z + device.a)
    sx, sy = ux + X * parallax, uy + Y * parallax
    k1 = device.upper_wavevectors()
    return -(k1[:, 0, None, None] * sx[None] + k1[:, 1, None, None] * sy[None])


def _surface_gradient(field: Float[Array, "*c h w"], spacing) -> Float[Array, "*c 2 h w"]:
    """(d/dX, d/dY) of fields on a surface grid; rows run towards -Y."""
    d_row, d_col = jnp.gradient(field, axis=(-2, -1))
    return jnp.stack([d_col, -d_row], axis=-3) / spacing


def _sample_at(field: Float[Array, "*c h w"], grid: SurfaceGrid, x0, y0) -> Float[Array, "*c"]:
    """Bilinear value of grid fields at the surface point (x0, y0)."""
    h, w = field.shape[-2:]
    col = x0 / grid.spacing + (w - 1) / 2
    row = (h - 1) / 2 - y0 / grid.spacing
    sample = jax.vmap(lambda f: jax.scipy.ndimage.map_coordinates(f, [row[None], col[None]], order=1)[0])
    return sample(field.reshape(-1, h, w)).reshape(field.shape[:-2])


class _FringeResponse(eqx.Module):
    phase: Float[Array, "sets h w"]  # phase change on the surface grid
    rotation: Float[Array, ""]  # surface rotation at the contact centre (rad, counter-clockwise)
    compression: Float[Array, ""]  # w at the contact centre (mm)
    wavevector: Float[Array, "sets 2"]  # local moire wavevector at the contact centre (reference plane)
    parallax_wavevector: Float[Array, "sets 2"]  # the part of its change due to the parallax term


def _fringe_response(device: Device, wrench: Float[Array, "6"], contact: Contact, shape) -> _FringeResponse:
    state = deformation(device, wrench, contact, shape)
    grid = state.grid
    ux, uy, w = state.displacement
    at_centre = lambda f: _sample_at(_surface_gradient(f, grid.spacing), grid, contact.x0, contact.y0)
    zero = jnp.zeros_like(w)
    d_phase = at_centre(surface_phase_shift(device, state.displacement, grid.X, grid.Y))  # per mm of surface
    d_parallax = at_centre(surface_phase_shift(device, jnp.stack([zero, zero, w]), grid.X, grid.Y))
    d_u = at_centre(state.displacement[:2])  # [component, d/dX or d/dY]
    # The reference plane sees the surface demagnified by Z/(Z + a): gradients grow by (Z + a)/Z.
    magnification = device.surface_magnification
    return _FringeResponse(
        phase=surface_phase_shift(device, state.displacement, grid.X, grid.Y),
        rotation=0.5 * (d_u[1, 0] - d_u[0, 1]),
        compression=_sample_at(w, grid, contact.x0, contact.y0),
        wavevector=device.moire_wavevectors() + magnification * d_phase,
        parallax_wavevector=magnification * d_parallax,
    )


def _in_contact(contact: Contact, grid: SurfaceGrid) -> Array:
    return (grid.X - contact.x0) ** 2 + (grid.Y - contact.y0) ** 2 <= contact.radius**2


def _phase_jacobian(device: Device, wrench, contact: Contact, shape) -> Float[Array, "sets h w 6"]:
    # The phase change is linear in the wrench (linear layer, linear phase relation).
    return jax.jacfwd(lambda wr: _fringe_response(device, wr, contact, shape).phase)(wrench)


@eqx.filter_jit
def phase_range(
    device: Device, load: tuple[Float[Array, "6"], Contact] | None = None, *, mechanics_shape=(64, 64)
) -> Float[Array, "6"]:
    """Largest fringe phase change anywhere (rad) when each wrench axis alone spans the paper's range.

    A phase change beyond $\\pi$ at some point is ambiguous to a solver that starts from
    the unloaded fringes; this is the "range before the fringes wrap" of each axis.
    """
    wrench, contact = nominal_load(device.p1.dtype) if load is None else load
    jac = _phase_jacobian(device, wrench, contact, mechanics_shape)
    return jnp.max(jnp.abs(jac), axis=(0, 1, 2)) * axis_ranges(jac.dtype)


@eqx.filter_jit
def _sensitivity_arrays(device: Device, wrench, contact: Contact, shape) -> dict[str, Array]:
    response = lambda wr: _fringe_response(device, wr, contact, shape)
    state = response(wrench)
    d = jax.jacfwd(response)(wrench)  # every leaf gains a trailing wrench axis
    grid = surface_grid(shape, device.px_per_mm, (device.height, device.width), device.a, device.Z)
    inside = _in_contact(contact, grid)[None, :, :, None]
    K = state.wavevector
    K_norm2 = jnp.sum(K**2, axis=-1)
    K_unit = K / jnp.sqrt(K_norm2)[:, None]
    period = 2 * jnp.pi / jnp.sqrt(K_norm2)
    # d|K| along K; dLambda = -Lambda d|K|/|K|.
    dK_fz = jnp.sum(K_unit * d.wavevector[..., 2], axis=-1)
    dK_fz_parallax = jnp.sum(K_unit * d.parallax_wavevector[..., 2], axis=-1)
    # A rigid rotation dα of the upper grating rotates k1' = K + k2, so dK = R90 k1' dα and
    # dθ/dα = K·k1'/|K|² (= Λ/p1' for aligned gratings), here at the preloaded local fringes.
    k1_local = K + device.reference_wavevectors()
    rotation_gain = jnp.sum(K * k1_local, axis=-1) / K_norm2
    # The same rotation taken straight from the local wavevector (strain included).
    dtheta_tz = (K[:, 0] * d.wavevector[:, 1, 5] - K[:, 1] * d.wavevector[:, 0, 5]) / K_norm2
    return dict(
        phase_peak=jnp.max(jnp.where(inside, jnp.abs(d.phase), 0.0), axis=(1, 2)),
        phase_mean=jnp.abs(jnp.sum(jnp.where(inside, d.phase, 0.0), axis=(1, 2))) / jnp.sum(inside.astype(K.dtype)),
        K_norm=jnp.sqrt(K_norm2),
        period=period,
        dperiod_dfz=-period * dK_fz / jnp.sqrt(K_norm2),
        parallax_share=dK_fz_parallax / dK_fz,
        rotation_per_tz=d.rotation[5],
        rotation_gain=rotation_gain,
        dtheta_dtz=dtheta_tz,
        compression_per_fz=d.compression[2],
    )


def force_sensitivity(
    device: Device,
    *,
    load: tuple[Float[Array, "6"], Contact] | None = None,
    mechanics_shape: tuple[int, int] = (128, 128),
) -> dict[str, float]:
    r"""How much the fringes near a contact move per unit load, by `jax.jacfwd` through the mechanics.

    Every number is the derivative at `load` (default: centred contact of radius 3.5 mm
    under Fz = 0.6 N) for the fringe family that responds most:

    - `fx_phase_peak_rad_per_N`, `fx_phase_mean_rad_per_N` (and `fy_*`): fringe phase
      change per N of shear, the largest over the contact disc and the mean over it.
      Phase is set by $|k_1| = 2\pi/p_1$ alone, not by the amplification.
    - `fx_fringe_shift_mm_per_N` (and `fy_*`): the peak phase change as a fringe
      displacement in the reference plane, phase$/|K|$; this one carries the
      amplification $\Lambda/p_1'$.
    - `tz_surface_rotation_rad_per_Nm`: rotation of the surface at the contact centre per
      N·m of twist; `tz_rotation_gain`: $d\theta/d\alpha_1$, the fringe rotation per
      rigid rotation of the upper grating at the preloaded local fringes
      ($\Lambda/p_1'$ for aligned gratings); `tz_fringe_rotation_rad_per_Nm`: their
      product, the local fringe rotation per N·m.
    - `fz_compression_mm_per_N`: compression $w$ at the contact centre per N;
      `fz_period_change_mm_per_N` and `fz_period_change_rel_per_N`: change of the local
      moiré period there per N (from parallax, $w/(Z+a)$, and from in-plane strain);
      `fz_parallax_share`: the fraction due to parallax.
    - `period_mm`: local moiré period at the contact under the preload.

    **Arguments:**

    - `device`: the [`Device`][].
    - `load`: `(wrench, contact)` about which to linearise, or `None` for the nominal load.
    - `mechanics_shape`: grid of the elastomer solve.

    **Returns:** a dict of plain floats (units in the names).
    """
    wrench, contact = nominal_load(device.p1.dtype) if load is None else load
    arrays = {
        k: np.asarray(v, dtype=np.float64)
        for k, v in _sensitivity_arrays(device, wrench, contact, mechanics_shape).items()
    }
    out: dict[str, float] = {}
    for axis, name in ((0, "fx"), (1, "fy")):
        f = int(np.argmax(arrays["phase_peak"][:, axis]))
        peak = arrays["phase_peak"][f, axis]
        out[f"{name}_phase_peak_rad_per_N"] = float(peak)
        out[f"{name}_phase_mean_rad_per_N"] = float(arrays["phase_mean"][f, axis])
        out[f"{name}_fringe_shift_mm_per_N"] = float(peak / arrays["K_norm"][f])
    f = int(np.argmax(np.abs(arrays["rotation_gain"])))
    rotation = arrays["rotation_per_tz"]
    out["tz_surface_rotation_rad_per_Nm"] = float(rotation)
    out["tz_rotation_gain"] = float(arrays["rotation_gain"][f])
    out["tz_fringe_rotation_rad_per_Nm"] = float(abs(rotation * arrays["rotation_gain"][f]))
    f = int(np.argmax(np.abs(arrays["dperiod_dfz"])))
    out["fz_compression_mm_per_N"] = float(arrays["compression_per_fz"])
    out["fz_period_change_mm_per_N"] = float(arrays["dperiod_dfz"][f])
    out["fz_period_change_rel_per_N"] = float(arrays["dperiod_dfz"][f] / arrays["period"][f])
    out["fz_parallax_share"] = float(arrays["parallax_share"][f])
    out["period_mm"] = float(arrays["period"][f])
    return out


# ---------------------------------------------------------------------------------------
# Fisher information and Cramér–Rao bounds.


def _parameter_scale(dtype) -> Float[Array, "9"]:
    # Wrench axes in units of the paper's ranges, contact latents in mm: a well-conditioned
    # information matrix even in float32.
    return jnp.concatenate([axis_ranges(dtype), jnp.ones(3, dtype)])


Estimator = Literal["pixels", "bands"]
ESTIMATORS = ("pixels", "bands")


def _check_estimator(estimator: str) -> None:
    if estimator not in ESTIMATORS:
        raise ValueError(f"estimator must be one of {ESTIMATORS}, got {estimator!r}")


def band_weight(device: Device, band_fraction: float = BAND_FRACTION) -> Float[Array, "h w"]:
    r"""How much of each Fourier bin of a frame the band inversion reads, on the `fft2` grid.

    The [`Demodulator`][]'s windows: a raised-cosine disc of radius `band_fraction`
    $|\mathbf K_f|$ around $\pm\mathbf K_f$ for every fringe family (a real frame holds each
    band with its conjugate) and one of radius `band_fraction` $\min_f |\mathbf K_f|$ around
    DC for the brightness. The windows follow the design's moiré wavevectors, so the weight is
    differentiable in the pitches and angles (the demodulator's own windows sit on whole bins).
    """
    h, w = device.height, device.width
    dtype = device.p1.dtype
    kx, ky = wavenumber_grid((h, w), 1 / device.px_per_mm, dtype=dtype)
    KX, KY = kx[None, :], ky[:, None]
    K = device.moire_wavevectors()
    K_norm = jnp.linalg.norm(K, axis=-1)
    weight = raised_cosine_window(jnp.hypot(KX, KY), band_fraction * jnp.min(K_norm), BAND_ROLLOFF)
    for f in range(K.shape[0]):
        for sign in (1.0, -1.0):
            distance = jnp.hypot(KX - sign * K[f, 0], KY - sign * K[f, 1])
            weight = jnp.maximum(weight, raised_cosine_window(distance, band_fraction * K_norm[f], BAND_ROLLOFF))
    return weight


def _scaled_information(
    device: Device,
    wrench,
    contact: Contact,
    noise: HighFidelity,
    exposure,
    mechanics_shape,
    n_parameters: int,
    estimator: Estimator = "pixels",
) -> Float[Array, "p p"]:
    """Fisher information of the first `n_parameters` of `[wrench, x0, y0, radius]`, in scaled units."""
    parameters = jnp.concatenate([wrench, jnp.stack([contact.x0, contact.y0, contact.radius]).astype(wrench.dtype)])

    def frame_of(p):
        latent = Contact(x0=p[6], y0=p[7], radius=p[8])
        return render_frame(device, p[:6], latent, exposure=exposure, mechanics_shape=mechanics_shape)

    frame, jvp = jax.linearize(frame_of, parameters)
    tangents = jnp.diag(_parameter_scale(parameters.dtype))[:n_parameters]
    jacobian = jax.vmap(jvp)(tangents)
    # A saturated (or black) pixel is clipped by the camera and tells nothing about the load.
    unclipped = (frame > 0) & (frame < 1)
    variance = pixel_noise_variance(frame, noise)
    if estimator == "pixels":
        weight = jnp.where(unclipped, 1 / variance, 0.0).reshape(-1)
        flat = jacobian.reshape(n_parameters, -1)
        return (flat * weight[None, :]) @ flat.T
    # Bands: the Fourier coefficients of white noise are independent with equal variance
    # (Parseval: N times the pixel variance), so each bin's information is |dF/dtheta|^2 over
    # that, counted as far as the band windows pass it. The camera's noise is not quite white
    # (shot noise follows the brightness); its mean over the frame stands in for it.
    count = jnp.maximum(jnp.sum(unclipped.astype(frame.dtype)), 1.0)
    mean_variance = jnp.sum(jnp.where(unclipped, variance, 0.0)) / count
    spectra = jnp.fft.fft2(jnp.where(unclipped[None], jacobian, 0.0))
    weight = band_weight(device).astype(frame.dtype)
    cross = sum(jnp.einsum("ihw,jhw->ij", part * weight[None], part) for part in (spectra.real, spectra.imag))
    return cross / (frame.size * mean_variance)


_scaled_information_jit = eqx.filter_jit(_scaled_information)


def fisher_information(
    device: Device,
    wrench: Float[Array, "6"],
    contact: Contact,
    noise: HighFidelity | None = None,
    *,
    exposure: ArrayLike = 1.0,
    mechanics_shape: tuple[int, int] = (64, 64),
    contact_latents: bool = True,
    estimator: Estimator = "pixels",
) -> Float[Array, "p p"]:
    r"""Fisher information about the wrench carried by one `model`-fidelity frame.

    $F = J^\top \Sigma^{-1} J$ with $J = \partial\,\mathrm{frame}/\partial\theta$ from
    `jax.linearize` through [`render_frame`][] and $\Sigma$ the diagonal pixel noise of
    [`pixel_noise_variance`][] at the noise-free frame. Pixels the camera clips (at or
    beyond 0 and 1) carry no information and are left out.

    **Arguments:**

    - `device`, `wrench`, `contact`, `exposure`, `mechanics_shape`: as for [`render_frame`][].
    - `noise`: the camera of a [`HighFidelity`][] model (`full_well`, `read_noise`,
      `bit_depth`); `None` for its defaults.
    - `contact_latents`: also estimate the contact `x0`, `y0` (mm) and `radius` (mm)
      (p = 9); otherwise the contact is taken as known (p = 6).
    - `estimator`: `"pixels"`, the information in every pixel; `"bands"`, only what the
      band inversion reads: each bin of the Jacobian's spectrum weighted by
      [`band_weight`][], under white noise of the frame's mean pixel variance.

    **Returns:** $F$ for $\theta = $ `[fx, fy, fz, tx, ty, tz]` (N, N·m), followed by
    `[x0, y0, radius]` (mm) when `contact_latents` (`PARAMETER_NAMES` order); units are
    the inverse products of theirs.
    """
    wrench = jnp.asarray(wrench)
    if wrench.shape != (6,):
        raise ValueError(f"wrench must have shape (6,), got {wrench.shape}")
    _check_estimator(estimator)
    n = 9 if contact_latents else 6
    scaled = _scaled_information_jit(
        device, wrench, contact, noise_as_arrays(noise, wrench.dtype), exposure, mechanics_shape, n, estimator
    )
    scale = _parameter_scale(wrench.dtype)[:n]
    return scaled / (scale[:, None] * scale[None, :])


def _weakest_axes(vectors: np.ndarray, values: np.ndarray) -> str:
    """Axes spanning the least-seen load directions, e.g. `"fx/fy"` when symmetry makes two equal."""
    nearly_weakest = vectors[:, values <= 1.05 * values[0]]
    loading = np.sum(nearly_weakest**2, axis=1)
    return "/".join(name for name, share in zip(WRENCH_AXES, loading) if share >= 0.25)


def _worst_axes(relative: np.ndarray) -> str:
    """The axis with the largest relative bound, or all within 1% of it (`"fx/fy"` for symmetric grids)."""
    return "/".join(name for name, r in zip(WRENCH_AXES, relative) if r >= 0.99 * np.max(relative))


def _bounds(scaled_information: np.ndarray) -> dict[str, Any]:
    """Cramér–Rao bounds from the 9x9 information in range units (numpy, float64)."""
    F = np.asarray(scaled_information, dtype=np.float64)
    ranges = WRENCH_SCALE
    scale = np.concatenate([ranges, np.ones(3)])
    eigenvalues = np.linalg.eigvalsh(F)
    if not (np.all(np.isfinite(F)) and eigenvalues[0] > 1e-12 * max(eigenvalues[-1], 1e-300)):
        unbounded = dict.fromkeys(WRENCH_AXES, math.inf)
        return dict(
            std=unbounded,
            std_known_contact=dict(unbounded),
            relative=dict(unbounded),
            latent_std=dict.fromkeys(LATENT_NAMES, math.inf),
            condition_number=math.inf,
            weakest_direction=dict.fromkeys(WRENCH_AXES, math.nan),
            weakest_axis="unobservable",
            worst_axis="unobservable",
            worst_relative=math.inf,
        )
    covariance = np.linalg.inv(F)
    marginal = np.sqrt(np.diag(covariance)) * scale
    known_contact = np.sqrt(np.diag(np.linalg.inv(F[:6, :6]))) * ranges
    # Information left about the wrench once the contact is estimated too (Schur complement).
    wrench_information = np.linalg.inv(covariance[:6, :6])
    values, vectors = np.linalg.eigh(0.5 * (wrench_information + wrench_information.T))
    weakest = vectors[:, 0] * np.sign(vectors[np.argmax(np.abs(vectors[:, 0])), 0])
    relative = marginal[:6] / ranges
    return dict(
        std={name: float(v) for name, v in zip(WRENCH_AXES, marginal[:6])},
        std_known_contact={name: float(v) for name, v in zip(WRENCH_AXES, known_contact)},
        relative={name: float(v) for name, v in zip(WRENCH_AXES, relative)},
        latent_std={name: float(v) for name, v in zip(LATENT_NAMES, marginal[6:])},
        condition_number=float(values[-1] / values[0]),
        weakest_direction={name: float(v) for name, v in zip(WRENCH_AXES, weakest)},
        weakest_axis=_weakest_axes(vectors, values),
        worst_axis=_worst_axes(relative),
        worst_relative=float(np.max(relative)),
    )


def cramer_rao(
    device: Device,
    wrench: Float[Array, "6"],
    contact: Contact,
    noise: HighFidelity | None = None,
    *,
    exposure: ArrayLike = 1.0,
    mechanics_shape: tuple[int, int] = (64, 64),
    estimator: Estimator = "pixels",
) -> dict[str, Any]:
    """Cramér–Rao lower bounds on the wrench from one frame, with the contact estimated alongside.

    **Arguments:** as for [`fisher_information`][] (`estimator="bands"`: the bound of an
    estimator that reads the moiré and brightness bands only, as `moirejax invert` does).

    **Returns:** a dict of plain Python values:

    - `std`: per-axis bound on the standard deviation (N, N·m), marginal over the contact
      latents `x0`, `y0`, `radius` (the inversion must estimate them too);
    - `std_known_contact`: the same with the contact known (conditional bound, never larger);
    - `relative`: `std` over the paper's range of each axis;
    - `latent_std`: bounds on `x0`, `y0`, `radius` (mm);
    - `condition_number`: of the wrench information (marginal), axes scaled by the
      paper's ranges (fx, fy 0.2 N; fz 1.2 N; tx, ty 0.012 N·m; tz 0.008 N·m);
    - `weakest_direction`: its eigenvector of smallest eigenvalue, the load combination
      a frame sees least, in range units; `weakest_axis`: the axes that direction loads
      (`"fx/fy"` when a symmetric design sees two equally badly and the direction within
      their plane is arbitrary);
    - `worst_axis`, `worst_relative`: the axis with the largest relative bound (axes
      within 1% of it joined by `/`) and that bound.
    """
    wrench = jnp.asarray(wrench)
    if wrench.shape != (6,):
        raise ValueError(f"wrench must have shape (6,), got {wrench.shape}")
    _check_estimator(estimator)
    scaled = _scaled_information_jit(
        device, wrench, contact, noise_as_arrays(noise, wrench.dtype), exposure, mechanics_shape, 9, estimator
    )
    return _bounds(np.asarray(scaled))


def observability_table(
    device: Device, noise: HighFidelity | None = None, *, mechanics_shape: tuple[int, int] = (64, 64)
) -> dict[str, Any]:
    """Cramér–Rao bounds of `device` at the nominal load, flat and JSON-ready, for the design table.

    The load is a centred press of radius 3.5 mm under Fz = 0.6 N; bounds are marginal
    over the contact latents and use the frame at the device's own size and resolution.
    Keys, for the whole-frame estimator: `crb_<axis>` (N or N·m), `rel_crb_<axis>` (bound
    over the paper's range), `worst_axis`, `worst_rel_crb`, `weakest_direction_axis`,
    `weakest_direction` (unit vector in range units, axis order fx..tz),
    `condition_number`; the same for the band inversion with a `band_` prefix; and a
    `conditions` line.
    """
    wrench, contact = nominal_load(device.p1.dtype)
    noise = HighFidelity() if noise is None else noise
    table: dict[str, Any] = {}
    for estimator, prefix in (("pixels", ""), ("bands", "band_")):
        bounds = cramer_rao(device, wrench, contact, noise, mechanics_shape=mechanics_shape, estimator=estimator)
        for name in WRENCH_AXES:
            unit = "N" if name.startswith("f") else "Nm"
            table[f"{prefix}crb_{name}_{unit}"] = bounds["std"][name]
        for name in WRENCH_AXES:
            table[f"{prefix}rel_crb_{name}"] = bounds["relative"][name]
        table[f"{prefix}worst_axis"] = bounds["worst_axis"]
        table[f"{prefix}worst_rel_crb"] = bounds["worst_relative"]
        table[f"{prefix}weakest_direction_axis"] = bounds["weakest_axis"]
        table[f"{prefix}weakest_direction"] = [round(bounds["weakest_direction"][name], 4) for name in WRENCH_AXES]
        table[f"{prefix}condition_number"] = bounds["condition_number"]
    table["conditions"] = (
        f"one {device.height}x{device.width} model frame at {float(device.px_per_mm):.4g} px/mm, "
        f"full well {float(noise.full_well):.0f} e-, read noise {float(noise.read_noise):.3g} e-, "
        f"{noise.bit_depth} bit; centred contact r = {NOMINAL_RADIUS} mm, Fz = {NOMINAL_WRENCH[2]} N; "
        "contact position and radius estimated too; band_*: only the moire and brightness bands read, "
        "as `moirejax invert` does"
    )
    return table


# ---------------------------------------------------------------------------------------
# Design maps and design optimisation on a reduced frame.

# A press changes the frame only within a few layer thicknesses of the contact, so the
# central 16 mm of the field holds nearly all the information about it: cropping keeps the
# device's own resolution (its carriers stay resolved) at a fraction of the cost.
_REDUCED_FIELD_MM = 16.0


def reduced_device(device: Device, field_mm: float = _REDUCED_FIELD_MM) -> Device:
    """`device` cropped to a central square of about `field_mm` (reference plane), same px/mm."""
    size = min(device.height, device.width, 8 * max(2, round(field_mm * float(device.px_per_mm) / 8)))
    return dataclasses.replace(device, height=size, width=size)


def _relative_bounds(device: Device, noise: HighFidelity, mechanics_shape, estimator: Estimator) -> np.ndarray:
    wrench, contact = nominal_load(device.p1.dtype)
    scaled = _scaled_information_jit(device, wrench, contact, noise, 1.0, mechanics_shape, 9, estimator)
    relative = _bounds(np.asarray(scaled))["relative"]
    return np.array([relative[name] for name in WRENCH_AXES])


def plot_observability(
    path,
    device: Device,
    noise: HighFidelity | None = None,
    *,
    pitches: tuple[float, float, int] = (0.15, 0.45, 11),
    angles_deg: tuple[float, float, int] = (-5.0, 5.0, 21),
    field_mm: float = _REDUCED_FIELD_MM,
    mechanics_shape: tuple[int, int] = (64, 64),
    estimator: Estimator = "bands",
) -> None:
    """Per-axis relative Cramér–Rao bound over a p1 x p2 grid and over Δα, as a PNG.

    Everything else is `device`'s; the frame is its central crop of about `field_mm`
    (see [`reduced_device`][]) at its own resolution, which the plot states. Pitches the
    camera cannot resolve (under 2.5 px in the image) are outlined.

    **Arguments:**

    - `path`: PNG file to write.
    - `device`: the design whose other parameters (layout, a, Z, duty, optics) are kept.
    - `noise`: camera noise ([`HighFidelity`][] defaults for `None`).
    - `pitches`: `(first, last, count)` of the p1 and p2 axes (mm).
    - `angles_deg`: `(first, last, count)` of Δα = α1 − α2 (degrees) at the device's pitches.
    - `field_mm`, `mechanics_shape`: reduced frame and mechanics grid.
    - `estimator`: whose bound to map (see [`fisher_information`][]); by default the band
      inversion's, which `moirejax invert` runs.
    """
    from .._plotting import pyplot, save_figure

    _check_estimator(estimator)
    small = reduced_device(device, field_mm)
    noise = noise_as_arrays(noise, small.p1.dtype)
    dtype = small.p1.dtype
    grid = np.linspace(*pitches)
    maps = np.full((len(grid), len(grid), 6), np.nan)
    for i, p2 in enumerate(grid):
        for j, p1 in enumerate(grid):
            design = dataclasses.replace(small, p1=jnp.asarray(p1, dtype), p2=jnp.asarray(p2, dtype))
            maps[i, j] = _relative_bounds(design, noise, mechanics_shape, estimator)
    angles = np.linspace(*angles_deg)
    curves = np.stack(
        [
            _relative_bounds(
                dataclasses.replace(small, alpha1=small.alpha2 + jnp.asarray(math.radians(a), dtype)),
                noise,
                mechanics_shape,
                estimator,
            )
            for a in angles
        ]
    )
    plt = pyplot()
    fig, axes = plt.subplots(2, 4, figsize=(19, 8.5))
    P1, P2 = np.meshgrid(grid, grid, indexing="xy")
    px = float(small.px_per_mm)
    a, Z = float(small.a), float(small.Z)
    # Carriers under 2.5 px in the image cannot be resolved by the camera.
    resolvable = np.minimum(P1 * Z / (Z + a), P2) * px
    panels = [(maps[..., k], f"{name}: log10 CRB / range") for k, name in enumerate(WRENCH_AXES)]
    panels.append((np.max(maps, axis=-1), "worst axis: log10 CRB / range"))
    for ax, (field, title) in zip(axes.flat, panels):
        with np.errstate(divide="ignore", invalid="ignore"):
            im = ax.pcolormesh(P1, P2, np.log10(field), shading="auto", cmap="viridis")
        fig.colorbar(im, ax=ax)
        ax.contour(P1, P2, resolvable, levels=[2.5], colors="r", linewidths=1)
        ax.plot(grid, grid * Z / (Z + a), "w--", lw=1)
        for name, (q1, q2) in PRESET_PITCHES.items():
            ax.plot(q1, q2, "r*", ms=9)
            ax.annotate(name, (q1, q2), color="w", xytext=(3, 3), textcoords="offset points", fontsize=8)
        ax.plot(float(small.p1), float(small.p2), "c+", ms=12, mew=2)
        ax.set_xlabel("p1 (mm)")
        ax.set_ylabel("p2 (mm)")
        ax.set_title(title, fontsize=9)
        ax.set_xlim(grid[0] - 0.5 * (grid[1] - grid[0]), grid[-1] + 0.5 * (grid[1] - grid[0]))
        ax.set_ylim(grid[0] - 0.5 * (grid[1] - grid[0]), grid[-1] + 0.5 * (grid[1] - grid[0]))
    ax = axes.flat[7]
    for k, name in enumerate(WRENCH_AXES):
        # fx/fy and tx/ty coincide for symmetric crossed grids: dashes keep both visible.
        ax.semilogy(angles, curves[:, k], "-" if k % 3 == 0 or k == 2 else "--", label=name)
    ax.set_xlabel("delta alpha (deg)")
    ax.set_ylabel("CRB / range")
    ax.set_title(f"against angle at p1={float(small.p1):.3g}, p2={float(small.p2):.3g} mm", fontsize=9)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.suptitle(
        f"Single-frame Cramer-Rao bounds of the {'band' if estimator == 'bands' else 'whole-frame'} estimator "
        f"(marginal over contact x0, y0, r), {small.layout} gratings, "
        f"a={a:.3g} mm, Z={Z:.3g} mm; nominal load Fz={NOMINAL_WRENCH[2]} N, r={NOMINAL_RADIUS} mm, centred.\n"
        f"Reduced frame: central {small.height}x{small.width} px crop ({small.height / px:.1f} mm) "
        f"of the {device.height}x{device.width} frame at {px:.3g} px/mm. "
        "Red: carriers at 2.5 px; white dashed: p1' = p2 (no fringes); cyan +: this device.",
        fontsize=10,
    )
    fig.tight_layout()
    save_figure(fig, path)
