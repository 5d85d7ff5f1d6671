"""Elastomer mechanics: the bonded layer's Fourier-space compliance and the FFT surface solver.

Independent routes: a Chebyshev collocation solve of Navier's equation across the layer,
the closed-form Boussinesq/Cerruti solutions, uniform-traction strain states, and
Maxwell-Betti reciprocity.
"""

import jax
import jax.numpy as jnp
import jaxtyping
import numpy as np
import pytest

from moirejax.physics._elastomer import half_space_compliance, layer_compliance, surface_displacement

from .helpers import FD_ATOL, FD_RTOL, finite_difference_jvp, tree_allclose


E = 1.3
NU_GRID = (0.0, 0.3, 0.49, 0.499)


def _random(seed, shape):
    # numpy rather than jax.random: each new shape of jax.random.normal costs seconds of compile.
    return jnp.asarray(np.random.default_rng(seed).normal(size=shape))


def _shear_modulus(E, nu):
    return E / (2 * (1 + nu))


def _confined_modulus(E, nu):
    return E * (1 - nu) / ((1 + nu) * (1 - 2 * nu))


def _chebyshev(n):
    """Chebyshev points on [-1, 1] and the differentiation matrix (Trefethen, Spectral Methods)."""
    x = np.cos(np.pi * np.arange(n + 1) / n)
    c = np.r_[2.0, np.ones(n - 1), 2.0] * (-1.0) ** np.arange(n + 1)
    D = np.outer(c, 1 / c) / (x[:, None] - x[None, :] + np.eye(n + 1))
    return x, D - np.diag(D.sum(axis=1))


def _collocation_compliance(q, h, E, nu, n=48):
    """Layer compliance in the frame of q from a numerical solve of Navier's equation in z.

    Unknowns are u_L(z), w(z) ~ exp(i q x) on Chebyshev nodes, z = h(1 - x)/2 (node 0 is the
    free surface, node n the bonded base). Returns the 2x2 P-SV block and the SH value.
    """
    mu = _shear_modulus(E, nu)
    lam = 2 * mu * nu / (1 - 2 * nu)
    _, Dx = _chebyshev(n)
    D = -2 / h * Dx
    D2 = D @ D
    eye = np.eye(n + 1)
    m = n + 1
    # mu (u'' - q^2 u) + (lam + mu) i q (i q u + w') = 0 and the same for w.
    A = np.block(
        [
            [mu * D2 - (lam + 2 * mu) * q**2 * eye, 1j * q * (lam + mu) * D],
            [1j * q * (lam + mu) * D, (lam + 2 * mu) * D2 - mu * q**2 * eye],
        ]
    )
    # z = 0: sigma_xz = -t_L, sigma_zz = -p. z = h: u = w = 0.
    A[0] = np.r_[mu * D[0], 1j * q * mu * eye[0]]
    A[m] = np.r_[1j * q * lam * eye[0], (lam + 2 * mu) * D[0]]
    A[n] = np.r_[eye[n], 0 * eye[n]]
    A[m + n] = np.r_[0 * eye[n], eye[n]]
    psv = np.zeros((2, 2), complex)
    for j in range(2):
        rhs = np.zeros(2 * m, complex)
        rhs[[0, m][j]] = -1
        solution = np.linalg.solve(A, rhs)
        psv[:, j] = solution[0], solution[m]
    A_sh = mu * (D2 - q**2 * eye)
    A_sh[0], A_sh[n] = mu * D[0], eye[n]
    rhs = np.zeros(m)
    rhs[0] = -1
    return psv, np.linalg.solve(A_sh, rhs)[0]


@pytest.mark.parametrize("nu", NU_GRID)
@pytest.mark.parametrize("s", [0.02, 0.7, 3.0])
def test_layer_compliance_matches_collocation(s, nu):
    h, theta = 2.5, 0.6
    q = s / h
    psv, sh = _collocation_compliance(q, h, E, nu)
    # Rotate the modal result into (x, y, z) with q along angle theta.
    c, si = np.cos(theta), np.sin(theta)
    R = np.array([[c, -si, 0], [si, c, 0], [0, 0, 1]])
    modal = np.array([[psv[0, 0], 0, psv[0, 1]], [0, sh, 0], [psv[1, 0], 0, psv[1, 1]]])
    expected = R @ modal @ R.T
    C = np.asarray(layer_compliance(q * c, q * si, E, nu, h))
    assert np.allclose(C, expected, rtol=0, atol=1e-9 * np.abs(expected).max())


def test_layer_compliance_is_hermitian_positive_definite():
    q = np.linspace(-3.0, 3.0, 13)
    for nu in NU_GRID + (0.5,):
        C = np.asarray(layer_compliance(q[:, None], q[None, :], E, nu, 2.0))
        assert C.shape == (13, 13, 3, 3)
        assert np.allclose(C, np.conj(np.swapaxes(C, -1, -2)), rtol=0, atol=1e-15)
        # Positive definite: a traction always does positive work (semi-definite only for the
        # incompressible layer, which a uniform pressure cannot compress).
        eigenvalues = np.linalg.eigvalsh(C)
        assert np.all(eigenvalues > 0) if nu < 0.5 else np.all(eigenvalues >= 0)


@pytest.mark.parametrize("nu", NU_GRID + (0.5,))
def test_uniform_traction_gives_simple_shear_and_confined_compression(nu):
    h, tx, ty, p = 3.0, 0.02, -0.01, 0.05
    mu = _shear_modulus(E, nu)
    traction = jnp.broadcast_to(jnp.array([tx, ty, p])[:, None, None], (3, 12, 10))
    u = surface_displacement(traction, 0.25, E, nu, h)
    assert u.shape == (3, 12, 10)
    # A perfectly incompressible layer cannot be compressed uniformly.
    w = 0.0 if nu == 0.5 else p * h / _confined_modulus(E, nu)
    expected = np.broadcast_to(np.array([tx * h / mu, ty * h / mu, w])[:, None, None], u.shape)
    assert np.allclose(u, expected, rtol=1e-12, atol=1e-15)
    C0 = np.asarray(layer_compliance(0.0, 0.0, E, nu, h))
    assert np.allclose(C0, np.diag([h / mu, h / mu, w / p]), rtol=1e-12, atol=1e-15)


def test_compliance_is_continuous_with_finite_gradients_at_zero_wavevector():
    nu, h = 0.49, 2.0
    mu = _shear_modulus(E, nu)
    C0 = layer_compliance(0.0, 0.0, E, nu, h)
    # The coupling entries grow linearly in q, the others quadratically.
    C_small = layer_compliance(1e-9, -2e-9, E, nu, h)
    assert np.allclose(C_small, C0, rtol=0, atol=1e-8 * np.abs(C0).max())

    def flat(qx, E, nu, h):
        C = layer_compliance(qx, 0.0, E, nu, h)
        return jnp.stack([C.real, C.imag])

    jacobians = jax.jacfwd(flat, argnums=(0, 1, 2, 3))(0.0, E, nu, h)
    assert all(np.all(np.isfinite(jac)) for jac in jacobians)
    slope, d_dh = jacobians[0][1, 0, 2], jacobians[3][0]
    assert np.allclose(np.diag(d_dh), [1 / mu, 1 / mu, 1 / _confined_modulus(E, nu)])
    # C_xz = i q_x Y is linear through q = 0; its slope there matches a finite difference.
    eps = 1e-6
    fd = (flat(eps, E, nu, h) - flat(-eps, E, nu, h))[1, 0, 2] / (2 * eps)
    assert np.isclose(slope, fd, rtol=1e-8)


def test_layer_approaches_half_space_and_is_stable_in_float32():
    h = 3.0
    theta = 0.3
    direction = np.array([np.cos(theta), np.sin(theta)])
    previous = np.inf
    for s in [2.0, 5.0, 10.0]:
        q = s / h * direction
        layer = np.asarray(layer_compliance(q[0], q[1], E, 0.3, h))
        half = np.asarray(half_space_compliance(q[0], q[1], E, 0.3))
        gap = np.abs(layer - half).max() / np.abs(half).max()
        assert gap < previous
        previous = gap
    s = np.array([15.0, 30.0, 100.0, 1e4, 1e6])
    for nu in NU_GRID + (0.5,):
        qx, qy = s / h * direction[0], s / h * direction[1]
        half = np.asarray(half_space_compliance(qx, qy, E, nu))
        layer = np.asarray(layer_compliance(qx, qy, E, nu, h))
        assert np.allclose(layer, half, rtol=0, atol=1e-9 * np.abs(half).max())
        layer32 = layer_compliance(qx.astype(np.float32), qy.astype(np.float32), E, nu, h)
        assert layer32.dtype == jnp.complex64
        assert np.all(np.isfinite(layer32))
        # float32 keeps its digits (up to the rounding of nu itself in 1 - 2 nu).
        assert np.allclose(layer32, half, rtol=0, atol=2e-5 * np.abs(half).max())


@pytest.mark.parametrize("nu", NU_GRID + (0.5,))
def test_float32_matches_float64_over_all_wavevectors(nu):
    s = np.concatenate([[0.0], np.logspace(-6, 4, 101)])
    C64 = np.asarray(layer_compliance(s, 0.0, E, nu, 1.0))
    C32 = np.asarray(layer_compliance(s.astype(np.float32), np.float32(0), E, nu, 1.0))
    scale = np.abs(C64).max(axis=(-1, -2), keepdims=True)
    assert np.all(np.abs(C32 - C64) < 2e-5 * scale)


def test_half_space_at_incompressibility_has_no_normal_tangential_coupling():
    q = np.linspace(-2.0, 2.0, 9)
    C = np.asarray(half_space_compliance(q[:, None], q[None, :], E, 0.5))
    assert np.all(C[..., :2, 2] == 0) and np.all(C[..., 2, :2] == 0)
    assert np.all(C[4, 4] == 0)  # the divergent q = 0 mode is gauged to zero


def _grid(n, dx):
    """Rectified-plane coordinates of an n x n grid (docs/conventions.md: y up, row 0 on top)."""
    coords = (np.arange(n) - (n - 1) / 2) * dx
    x, y = np.meshgrid(coords, -coords)
    return x, y, np.hypot(x, y)


def _gaussian(r, sigma, total):
    return total * np.exp(-(r**2) / (2 * sigma**2)) / (2 * np.pi * sigma**2)


# A layer far thicker than the grid's period behaves as a half-space at every q != 0.
THICK = 1e4


def test_thick_layer_reproduces_boussinesq():
    n, dx, sigma, P, nu = 512, 1.0, 2.0, 1.0, 0.3
    x, y, r = _grid(n, dx)
    traction = np.zeros((3, n, n))
    traction[2] = _gaussian(r, sigma, P)
    u = np.asarray(surface_displacement(jnp.asarray(traction), dx, E, nu, THICK))
    mu = _shear_modulus(E, nu)

    # Boussinesq convolved with the Gaussian (Hankel transforms of exp(-k^2 sigma^2/2) J0, J1):
    # w = (1-nu) P / (2 pi mu) sqrt(pi/2)/sigma e^{-a} I0(a), a = r^2 / (4 sigma^2),
    # u_r = -(1-2nu) P / (4 pi mu r) (1 - e^{-r^2 / (2 sigma^2)}).
    a = r**2 / (4 * sigma**2)
    ring = (r > 3 * sigma) & (r < 12 * sigma)
    w_exact = (1 - nu) * P / (2 * np.pi * mu) * np.sqrt(np.pi / 2) / sigma
    w_exact = w_exact * np.exp(-np.minimum(a, 500)) * np.i0(np.minimum(a, 500))
    u_r_exact = -(1 - 2 * nu) * P / (4 * np.pi * mu * r) * -np.expm1(-(r**2) / (2 * sigma**2))
    # The periodic images of the u_r field add the field of a uniform neutralising background,
    # which on a square lattice is -pi r / L^2 times the same prefactor.
    u_r_exact += (1 - 2 * nu) * P / (4 * np.pi * mu) * np.pi * r / (n * dx) ** 2
    u_r = (u[0] * x + u[1] * y) / r
    assert np.allclose(u_r[ring], u_r_exact[ring], rtol=1e-4)
    # w carries a uniform offset (the q = 0 mode, and the images' mean): compare differences.
    w_ref, w_exact_ref = u[2][ring][0], w_exact[ring][0]
    w_exact_diff = w_exact[ring] - w_exact_ref
    assert np.allclose(u[2][ring] - w_ref, w_exact_diff, atol=3e-4 * np.abs(w_exact_diff).max())

    # Far from the load the point-force formulas hold to a few per cent.
    far = (r > 8 * sigma) & (r < 14 * sigma)
    w_point = (1 - nu**2) * P / (np.pi * E * r)
    u_r_point = -(1 - 2 * nu) * (1 + nu) * P / (2 * np.pi * E * r)
    assert np.all(u_r[far] < 0)  # pulled inward
    assert np.allclose(u_r[far], u_r_point[far], rtol=0.03)
    w_diff = u[2][far] - u[2][far][0]
    w_point_diff = w_point[far] - w_point[far][0]
    assert np.allclose(w_diff, w_point_diff, atol=0.03 * np.abs(w_point_diff).max())
    # y points up: a pixel above the load (row index smaller) is pulled down, towards it.
    above = (n // 2 - 20, n // 2)
    assert y[above] > 0 and u[1][above] < 0


def test_thick_layer_reproduces_cerruti():
    n, dx, sigma, Q, nu = 512, 1.0, 1.5, 1.0, 0.3
    x, y, r = _grid(n, dx)
    traction = np.zeros((3, n, n))
    traction[0] = _gaussian(r, sigma, Q)
    u = np.asarray(surface_displacement(jnp.asarray(traction), dx, E, nu, THICK))
    far = (r > 8 * sigma) & (r < 14 * sigma)
    prefactor = (1 + nu) * Q / (np.pi * E * r)
    # u_x = (1+nu) Q / (pi E r) [(1 - nu) + nu x^2/r^2], u_y = (1+nu) Q nu x y / (pi E r^3).
    u_x_point = prefactor * ((1 - nu) + nu * x**2 / r**2)
    u_y_point = prefactor * nu * x * y / r**2
    # By Betti from Boussinesq's inward u_r: the surface ahead of the load moves in.
    w_point = (1 - 2 * nu) * (1 + nu) * Q * x / (2 * np.pi * E * r**2)
    scale = np.abs(u_x_point[far]).max()
    assert np.allclose(u[1][far], u_y_point[far], atol=0.03 * scale)
    assert np.allclose(u[2][far], w_point[far], atol=0.03 * scale)
    # u_x has a uniform offset from the q = 0 mode: compare its variation over the ring,
    # which holds both the 1/r decay and the nu x^2/r^2 anisotropy.
    u_x_diff = u[0][far] - u[0][far].mean()
    u_x_point_diff = u_x_point[far] - u_x_point[far].mean()
    assert np.allclose(u_x_diff, u_x_point_diff, atol=0.03 * np.abs(u_x_point_diff).max())


def test_bonded_layer_squeezes_material_outward_but_half_space_does_not():
    n, dx, h = 128, 0.1, 1.0
    x, y, r = _grid(n, dx)
    traction = np.zeros((3, n, n))
    traction[2] = _gaussian(r, 0.5, 1.0)
    near = (r > 0.3) & (r < 2.0)
    for nu in (0.49, 0.499, 0.5):
        u = np.asarray(surface_displacement(jnp.asarray(traction), dx, E, nu, h))
        u_r = (u[0] * x + u[1] * y) / r
        assert np.all(u_r[near] > 0.05 * u[2].max())
        # Straight above the load (y up) the surface moves up, away from it.
        assert u[1][n // 2 - 8, n // 2] > 0
    # The same load on an incompressible half-space (thick layer) moves nothing in-plane.
    u = np.asarray(surface_displacement(jnp.asarray(traction), dx, E, 0.5, THICK))
    assert np.abs(u[:2]).max() < 1e-12 * np.abs(u[2]).max()


@pytest.mark.parametrize("shape", [(24, 32), (23, 17)])
def test_reciprocity(shape):
    t1, t2 = _random(1, (3,) + shape), _random(2, (3,) + shape)
    for thickness in (0.5, 5.0):
        u1 = surface_displacement(t1, 0.2, E, 0.45, thickness)
        u2 = surface_displacement(t2, 0.2, E, 0.45, thickness)
        assert np.isclose(jnp.sum(t1 * u2), jnp.sum(t2 * u1), rtol=1e-12)


def test_fft_solver_applies_the_compliance_matrix():
    # Odd sizes have no Nyquist bins, so the full complex FFT is an exact second route.
    rows, cols, dx, nu, h = 15, 21, 0.3, 0.45, 1.2
    traction = _random(3, (3, rows, cols))
    kx = 2 * np.pi * np.fft.fftfreq(cols, dx)
    ky = -2 * np.pi * np.fft.fftfreq(rows, dx)
    C = np.asarray(layer_compliance(kx[None, :], ky[:, None], E, nu, h))
    expected = np.fft.ifft2(np.einsum("abij,jab->iab", C, np.fft.fft2(np.asarray(traction))))
    assert np.abs(expected.imag).max() < 1e-14
    assert np.allclose(surface_displacement(traction, dx, E, nu, h), expected.real, atol=1e-14)


@pytest.mark.parametrize("shape", [(24, 32), (23, 17)])
def test_mirror_symmetry(shape):
    # Reflecting the grid (rows reverse y, columns reverse x) and the matching traction
    # components must reflect the displacement, Nyquist bins of even grids included.
    traction = _random(9, (3,) + shape)
    u = surface_displacement(traction, 0.2, E, 0.45, 0.8)
    flip_y, flip_x = jnp.array([1.0, -1.0, 1.0]), jnp.array([-1.0, 1.0, 1.0])
    mirrored_y = surface_displacement(flip_y[:, None, None] * traction[:, ::-1], 0.2, E, 0.45, 0.8)
    mirrored_x = surface_displacement(flip_x[:, None, None] * traction[:, :, ::-1], 0.2, E, 0.45, 0.8)
    assert tree_allclose(mirrored_y, flip_y[:, None, None] * u[:, ::-1], atol=1e-14)
    assert tree_allclose(mirrored_x, flip_x[:, None, None] * u[:, :, ::-1], atol=1e-14)


def test_float32_surface_displacement():
    traction = _random(4, (3, 16, 20))
    for nu in (0.3, 0.499):
        u64 = surface_displacement(traction, 0.2, E, nu, 1.5)
        u32 = surface_displacement(traction.astype(jnp.float32), 0.2, E, nu, 1.5)
        assert u32.dtype == jnp.float32
        assert np.allclose(u32, u64, rtol=0, atol=1e-5 * np.abs(u64).max())


def test_gradients_match_finite_differences():
    traction = _random(5, (3, 12, 16))
    scalars = jnp.array([0.2, E, 0.49, 1.5])  # spacing, E, nu, thickness
    solve = lambda t, v: surface_displacement(t, *v)
    # All inputs at once along a random direction...
    tangents = (_random(6, traction.shape), _random(7, (4,)) * scalars)
    jvp = jax.jvp(solve, (traction, scalars), tangents)[1]
    fd = finite_difference_jvp(solve, (traction, scalars), tangents)[1]
    assert tree_allclose(jvp, fd, rtol=FD_RTOL, atol=FD_ATOL)
    # Each scalar on its own, so a wrong derivative cannot hide behind a larger one.
    # ...and each scalar on its own, so a wrong derivative cannot hide behind a larger one.
    jacobian = jax.jacfwd(solve, argnums=1)(traction, scalars)
    for i in range(4):
        tangent = scalars[i] * jnp.eye(4)[i]
        fd = finite_difference_jvp(solve, (traction, scalars), (0 * traction, tangent))[1]
        assert np.allclose(scalars[i] * jacobian[..., i], fd, rtol=FD_RTOL, atol=FD_ATOL)


def test_jit_vmap_and_grad_compose():
    tractions = _random(8, (4, 3, 8, 10))
    nus = jnp.array([0.0, 0.3, 0.49, 0.499])
    solve = jax.jit(surface_displacement)
    batched = jax.vmap(solve, in_axes=(0, None, None, 0, None))(tractions, 0.2, E, nus, 1.0)
    looped = jnp.stack([solve(t, 0.2, E, nu, 1.0) for t, nu in zip(tractions, nus)])
    assert tree_allclose(batched, looped)

    def energy(nu, t):
        return jnp.sum(t * surface_displacement(t, 0.2, E, nu, 1.0))

    grad_of_vmap = jax.jit(jax.grad(lambda n: jnp.sum(jax.vmap(energy)(n, tractions))))(nus)
    vmap_of_grad = jax.jit(jax.vmap(jax.grad(energy)))(nus, tractions)
    assert tree_allclose(grad_of_vmap, vmap_of_grad)
    assert np.all(np.isfinite(vmap_of_grad))


def test_rejects_traction_without_three_components():
    with pytest.raises((ValueError, jaxtyping.TypeCheckError)):
        surface_displacement(jnp.zeros((2, 4, 4)), 0.1, E, 0.3, 1.0)
