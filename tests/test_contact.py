import jax
import jax.numpy as jnp
import jaxtyping
import numpy as np
import pytest
import scipy.linalg

import moirejax as mj
from moirejax.physics import layer_response
from moirejax.physics._contact import (
    _hertz_transform,
    _punch_transform,
    Contact,
    surface_grid,
    surface_tractions,
    traction_resultant,
    traction_spectrum,
)

from .helpers import check_grad_against_fd


GRID = surface_grid((96, 96), 16.0, (512, 512), 3.0, 12.0)


@pytest.mark.parametrize(
    "wrench, contact",
    [
        ([0.0, 0.0, 1.0, 0.0, 0.0, 0.0], Contact(0.0, 0.0, 3.0)),
        ([0.1, -0.2, 0.8, 0.004, -0.006, 0.007], Contact(2.3, -1.7, 3.5)),
        ([-0.2, 0.15, 1.2, -0.012, 0.011, -0.008], Contact(-6.1, 4.4, 2.2)),
        ([0.0, 0.0, 0.0, 0.0, 0.0, 0.003], Contact(0.0, 0.0, 4.0)),
    ],
)
def test_resultant_equals_requested_wrench(wrench, contact):
    wrench = jnp.asarray(wrench)
    tractions = surface_tractions(wrench, contact, GRID)
    assert jnp.allclose(traction_resultant(tractions, GRID), wrench, rtol=0, atol=1e-9)


def test_centred_press_is_a_hertz_like_pressure():
    tractions = surface_tractions(jnp.array([0.0, 0, 1.0, 0, 0, 0]), Contact(0.0, 0.0, 3.0), GRID)
    tx, ty, p = tractions
    assert jnp.allclose(tx, 0) and jnp.allclose(ty, 0)
    # Peak at the centre, positive inside, tiny outside the patch, mean pressure = F / (pi r^2).
    rho = jnp.hypot(GRID.X, GRID.Y)
    assert p.max() == p[rho == rho.min()].max()
    assert jnp.all(p[rho < 2.5] > 0) and jnp.all(jnp.abs(p[rho > 4.0]) < 1e-3 * p.max())
    hertz_peak = 1.5 * 1.0 / (jnp.pi * 3.0**2)
    assert abs(float(p.max()) / float(hertz_peak) - 1) < 0.1


def test_off_centre_press_moments_follow_convention():
    # Pressing at +x gives Ty = -x Fz (z into the sensor); at +y gives Tx = +y Fz.
    contact = Contact(5.0, 2.0, 3.0)
    fz = 1.0
    wrench = jnp.array([0.0, 0.0, fz, 2.0 * fz / 1000, -5.0 * fz / 1000, 0.0])
    p = surface_tractions(wrench, contact, GRID)[2]
    # A pressure centred on the contact: no tilt needed, profile symmetric about it.
    symmetric = surface_tractions(jnp.array([0.0, 0, fz, 0, 0, 0]), Contact(0.0, 0.0, 3.0), GRID)[2]
    assert float(p.max()) == pytest.approx(float(symmetric.max()), rel=0.05)


def test_gradients_with_respect_to_wrench_and_contact():
    def f(args):
        wrench, contact = args
        return surface_tractions(wrench, contact, GRID)

    args = (jnp.array([0.1, -0.05, 0.9, 0.003, -0.002, 0.004]), Contact(1.0, -0.5, 3.0))
    check_grad_against_fd(f, args)
    jac = jax.jacfwd(lambda w: surface_tractions(w, args[1], GRID))(args[0])
    assert jac.shape == (3, 96, 96, 6)


def test_bad_wrench_shape_is_a_trace_time_error():
    # Under pytest jaxtyping's runtime check fires first; without it, our ValueError.
    with pytest.raises((ValueError, jaxtyping.TypeCheckError)):
        surface_tractions(jnp.zeros(5), Contact(), GRID)


def test_resultant_under_vmap():
    wrenches = jnp.asarray(np.random.default_rng(0).normal(size=(4, 6)) * np.array([0.1, 0.1, 1, 0.005, 0.005, 0.004]))
    tractions = jax.vmap(lambda w: surface_tractions(w, Contact(1.0, 2.0, 3.0), GRID))(wrenches)
    resultants = jax.vmap(lambda t: traction_resultant(t, GRID))(tractions)
    assert jnp.allclose(resultants, wrenches, atol=1e-9)


def _hard_edge_fields(wrench, contact, X, Y):
    """The fields of `traction_spectrum` with the hard edges, sampled at (X, Y), from the
    continuum moments (an independent evaluation in numpy): the sphere's profile and the flat
    punch's, each over its resultant, blended by the flatness."""
    fx, fy, fz = wrench[:3]
    tx, ty, tz = np.asarray(wrench[3:]) * 1000.0
    r, x0, y0, f = float(contact.radius), float(contact.x0), float(contact.y0), float(contact.flatness)
    # An elongated patch is the round one seen through the stretch S = expm(A): its
    # profile at d is the round one's at S^-1 d, and its second moments are m2 S^2.
    a, b = float(contact.stretch_x), float(contact.stretch_xy)
    stretch = scipy.linalg.expm(np.array([[a, b], [b, -a]]))
    inverse = np.linalg.inv(stretch)
    dX, dY = X - x0, Y - y0
    u, v = inverse[0, 0] * dX + inverse[0, 1] * dY, inverse[1, 0] * dX + inverse[1, 1] * dY
    gap = np.clip(1 - (u**2 + v**2) / r**2, 0, None)
    punch = np.where(gap > 0, 1 / np.sqrt(np.where(gap > 0, gap, 1.0)), 0.0)
    H = (1 - f) * np.sqrt(gap) / (2 * np.pi * r**2 / 3) + f * punch / (2 * np.pi * r**2)
    m0, m2 = 1.0, (1 - f) * r**2 / 5 + f * r**2 / 3
    moments = m2 * stretch @ stretch
    cx, cy = np.linalg.solve(moments, [-(ty + x0 * fz), tx - y0 * fz])
    p = H * (fz / m0 + cx * dX + cy * dY)
    twist = (tz - x0 * fy + y0 * fx) / np.trace(moments)
    return np.stack([H * (fx / m0 - twist * dY), H * (fy / m0 + twist * dX), p])


SPECTRUM_CASES = [
    ([0.1, -0.2, 0.8, 0.004, -0.006, 0.007], Contact(2.3, -1.7, 3.5)),
    ([-0.2, 0.15, 1.2, -0.012, 0.011, -0.008], Contact(-6.1, 4.4, 2.2)),
    # An edge pressed along a direction 35 degrees from x, five times as long as wide.
    ([0.05, 0.1, 1.0, 0.006, 0.004, -0.005], Contact.elongated(1.5, 0.5, 3.0, 5.0, 0.61)),
]
# Flat and part-flat patches: their edge is singular, which sampling on a fine grid does not
# resolve (it misses a fifth of a flat punch's load), so their transform is checked against
# a quadrature (`test_punch_transform_is_the_hankel_transform_of_the_punch`) and here
# through the resultant.
FLAT_CASES = [
    ([0.15, 0.1, 1.0, -0.006, 0.009, 0.005], Contact(1.2, 0.8, 3.0, 1.0)),
    ([-0.05, 0.2, 0.6, 0.003, 0.002, -0.004], Contact(-2.0, 3.1, 2.6, 0.4)),
    ([0.1, -0.1, 0.9, -0.002, 0.005, 0.003], Contact(0.8, -1.1, 2.8, 0.7, -0.6, 0.3)),
]


@pytest.mark.parametrize("wrench, contact", SPECTRUM_CASES)
def test_traction_spectrum_is_the_transform_of_the_hard_edge_fields(wrench, contact):
    # The same fields sampled 16 times finer and cell-averaged onto the coarse grid have,
    # at the coarse grid's low wavenumbers, the coarse cells' transform times the box
    # average's sinc: compare there, where the sinc is known.
    wrench = jnp.asarray(wrench)
    grid = surface_grid((64, 64), 16.0, (512, 512), 3.0, 12.0)
    fine = 16
    h = float(grid.spacing) / fine
    n = 64 * fine
    axis = (np.arange(n) - (n - 1) / 2) * h
    X, Y = np.meshgrid(axis, -axis, indexing="xy")
    fields = _hard_edge_fields(np.asarray(wrench), contact, X, Y)
    cells = fields.reshape(3, 64, fine, 64, fine).mean(axis=(2, 4))
    expected = np.fft.rfft2(cells)
    spectrum = np.asarray(traction_spectrum(wrench, contact, grid))
    kx = 2 * np.pi * np.fft.rfftfreq(64, float(grid.spacing))
    ky = 2 * np.pi * np.fft.fftfreq(64, float(grid.spacing))
    box = np.sinc(kx[None, :] * float(grid.spacing) / (2 * np.pi)) * np.sinc(
        ky[:, None] * float(grid.spacing) / (2 * np.pi)
    )
    low = np.hypot(kx[None, :], ky[:, None]) < 2.0  # rad/mm: the scale of the fringe band
    scale = np.abs(expected[:, low]).max()
    # The fine sampling of the square-root edge is itself good to a few 1e-3; the grid's own
    # smoothed-edge fields are several times further off.
    assert np.abs(spectrum[:, low] * box[low] - expected[:, low]).max() < 5e-3 * scale
    smoothed = np.fft.rfft2(np.asarray(surface_tractions(wrench, contact, grid)))
    assert np.abs(smoothed[:, low] - expected[:, low]).max() > 2e-2 * scale


@pytest.mark.parametrize("wrench, contact", SPECTRUM_CASES + FLAT_CASES)
def test_traction_spectrum_resultant_is_the_wrench(wrench, contact):
    # The band-limited field it describes has the requested wrench as its resultant.
    wrench = jnp.asarray(wrench)
    grid = surface_grid((256, 256), 16.0, (512, 512), 3.0, 12.0)
    fields = jnp.fft.irfft2(traction_spectrum(wrench, contact, grid), s=(256, 256))
    scale = jnp.asarray([0.2, 0.2, 1.2, 0.012, 0.012, 0.008])
    assert jnp.all(jnp.abs(traction_resultant(fields, grid) - wrench) < 2e-3 * scale)
    # The zero-wavenumber bin carries the forces exactly.
    area = grid.spacing**2
    zero_bin = jnp.real(traction_spectrum(wrench, contact, grid)[:, 0, 0]) * area
    assert jnp.allclose(zero_bin, wrench[:3], rtol=1e-12, atol=1e-12)


def test_traction_spectrum_displacement_agrees_with_a_fine_hard_edge_solve():
    # The layer under the spectrum on a coarse grid against the layer under the hard-edge
    # fields sampled on a grid four times finer: the coarse grid's smoothed-edge fields would
    # be several per cent off, the exact transform is not.
    wrench, contact = jnp.asarray(SPECTRUM_CASES[0][0]), SPECTRUM_CASES[0][1]
    coarse = surface_grid((96, 96), 16.0, (512, 512), 3.0, 12.0)
    fine = surface_grid((384, 384), 16.0, (512, 512), 3.0, 12.0)
    from_spectrum = layer_response((96, 96), coarse.spacing, 1.0, 0.49, 3.0).displacement_of_spectrum(
        traction_spectrum(wrench, contact, coarse)
    )
    fields = _hard_edge_fields(np.asarray(wrench), contact, np.asarray(fine.X), np.asarray(fine.Y))
    reference = layer_response((384, 384), fine.spacing, 1.0, 0.49, 3.0)(jnp.asarray(fields))
    reference = reference.reshape(3, 96, 4, 96, 4).mean(axis=(2, 4))
    error = jnp.linalg.norm(from_spectrum - reference) / jnp.linalg.norm(reference)
    smoothed = layer_response((96, 96), coarse.spacing, 1.0, 0.49, 3.0)(surface_tractions(wrench, contact, coarse))
    assert error < 0.01 < jnp.linalg.norm(smoothed - reference) / jnp.linalg.norm(reference)


def test_hertz_transform_series_meets_the_closed_form():
    g, dg = _hertz_transform(jnp.asarray([1.0 - 2e-12, 1.0 + 2e-12]))
    # Both sides agree to rounding (the functions themselves move by ~1e-13 over the gap).
    assert abs(float(g[0] - g[1])) < 1e-12 and abs(float(dg[0] - dg[1])) < 1e-12
    # g(0) = 1/3: the transform of the unit profile at zero is its integral 2 pi r^2 / 3.
    assert float(_hertz_transform(jnp.asarray(0.0))[0]) == pytest.approx(1 / 3, rel=1e-14)


def test_punch_transform_is_the_hankel_transform_of_the_punch():
    # The punch's transform over its resultant, 2 pi r^2 sin(qr)/(qr) / (2 pi r^2), is the
    # Hankel transform of 1/sqrt(1 - t^2) on the unit disc over 2 pi; with t = sin(theta) the
    # integrand int_0^1 J0(x t) t/sqrt(1 - t^2) dt = int_0^{pi/2} J0(x sin theta) sin theta
    # dtheta is smooth, and a Gauss-Legendre rule gets it to rounding.
    from scipy.special import j0

    x = np.asarray([0.0, 0.3, 0.99, 1.01, 2.5, 7.0, 19.0])
    nodes, weights = np.polynomial.legendre.leggauss(200)
    theta = (nodes + 1) * np.pi / 4
    expected = (j0(x[:, None] * np.sin(theta)[None]) * np.sin(theta)[None]) @ weights * np.pi / 4
    sinc, dsinc = _punch_transform(jnp.asarray(x**2), _hertz_transform(jnp.asarray(x**2))[0])
    assert np.allclose(np.asarray(sinc), expected, rtol=0, atol=1e-12)
    # Its derivative over x, which gives the first moments' transforms, against autodiff of
    # the transform itself (through x^2, as the spectrum takes it).
    derivative = jax.vmap(jax.grad(lambda z: _punch_transform(z, _hertz_transform(z)[0])[0]))(jnp.asarray(x**2))
    assert np.allclose(2 * np.asarray(derivative), np.asarray(dsinc), rtol=0, atol=1e-12)


def test_a_flat_contact_loads_its_edge():
    # The punch's pressure rises towards its edge, the sphere's falls to zero there; both carry
    # the requested normal force.
    grid = surface_grid((256, 256), 16.0, (512, 512), 3.0, 12.0)
    wrench = jnp.asarray([0.0, 0.0, 1.0, 0.0, 0.0, 0.0])
    centre = grid.X.shape[0] // 2
    for flatness, rising in ((0.0, False), (1.0, True)):
        p = jnp.fft.irfft2(traction_spectrum(wrench, Contact(0.0, 0.0, 3.0, flatness), grid), s=(256, 256))[2]
        row = np.asarray(p[centre])
        rho = np.abs(np.asarray(grid.X[centre]))
        inner, edge = row[rho < 0.5].mean(), row[(rho > 2.4) & (rho < 2.8)].mean()
        assert (edge > inner) == rising
        assert float(jnp.sum(p) * grid.spacing**2) == pytest.approx(1.0, rel=1e-9)


def test_traction_spectrum_gradients():
    grid = surface_grid((32, 32), 16.0, (512, 512), 3.0, 12.0)

    def f(args):
        wrench, contact = args
        spectrum = traction_spectrum(wrench, contact, grid)
        return jnp.stack([spectrum.real, spectrum.imag])

    wrench = jnp.array([0.1, -0.05, 0.9, 0.003, -0.002, 0.004])
    check_grad_against_fd(f, (wrench, Contact(1.0, -0.5, 3.0, 0.3)))
    # Elongated, and through the round patch, where the stretch's direction means nothing
    # and its shape tensor comes from a series.
    check_grad_against_fd(f, (wrench, Contact(1.0, -0.5, 3.0, 0.3, 0.4, -0.2)))
    check_grad_against_fd(f, (wrench, Contact(1.0, -0.5, 3.0, 0.3, 0.0, 0.0)))


def test_elongated_patch_reads_its_shape():
    contact = Contact.elongated(0.0, 0.0, 3.0, 4.0, 0.3)
    assert float(contact.aspect_ratio) == pytest.approx(4.0, rel=1e-12)
    assert float(contact.long_axis_angle) == pytest.approx(0.3, rel=1e-12)
    pxx, pxy, pyy = contact.shape_tensor()
    assert float(pxx * pyy - pxy**2) == pytest.approx(1.0, rel=1e-12)
    # Its pressure spreads twice the radius along the long axis and half of it across: the
    # round patch's second moment (r^2/5 per unit force, with the smoothed edge's share),
    # times 4 along and over 4 across.
    grid = surface_grid((256, 256), 16.0, (512, 512), 3.0, 12.0)

    def pressure(contact):
        return (
            np.asarray(surface_tractions(jnp.array([0.0, 0, 1.0, 0, 0, 0]), contact, grid)[2])
            * float(grid.spacing) ** 2
        )

    p, round_p = pressure(contact), pressure(Contact(0.0, 0.0, 3.0))
    along = np.cos(0.3) * np.asarray(grid.X) + np.sin(0.3) * np.asarray(grid.Y)
    across = -np.sin(0.3) * np.asarray(grid.X) + np.cos(0.3) * np.asarray(grid.Y)
    round_moment = np.sum(round_p * along**2)
    assert round_moment == pytest.approx(9 / 5, rel=0.1)
    assert np.sum(p * along**2) == pytest.approx(4 * round_moment, rel=1e-5)
    assert np.sum(p * across**2) == pytest.approx(round_moment / 4, rel=1e-5)
    assert abs(np.sum(p * along * across)) < 1e-5
    # The series near the round patch meets the closed form.
    for k in (np.sqrt(0.99e-4), np.sqrt(1.01e-4)):
        near = Contact(0.0, 0.0, 3.0, 0.0, k * 0.6, k * 0.8).shape_tensor()
        exact = scipy.linalg.expm(2 * np.array([[0.6 * k, 0.8 * k], [0.8 * k, -0.6 * k]]))
        assert np.allclose([float(v) for v in near], [exact[0, 0], exact[0, 1], exact[1, 1]], rtol=0, atol=1e-13)


@pytest.mark.parametrize(
    "image, cells, grid",
    [
        ((512, 512), 96, (96, 96)),
        ((480, 640), 128, (96, 128)),
        ((640, 480), 100, (100, 75)),
        ((250, 300), 64, (55, 66)),
    ],
)
def test_grid_shape_keeps_the_image_aspect_with_square_cells(image, cells, grid):
    assert mj.grid_shape(image, cells) == grid
    # Square cells: the grid's aspect ratio is the image's exactly, which surface_grid needs.
    assert grid[0] * image[1] == grid[1] * image[0] and max(grid) >= cells
    mj.surface_grid(grid, 16.0, image, 3.0, 12.0)
    with pytest.raises(ValueError, match="grid_shape"):
        mj.surface_grid((grid[0] + 1, grid[1]), 16.0, image, 3.0, 12.0)
