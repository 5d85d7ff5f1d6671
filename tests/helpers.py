"""Shared tolerances and numerical references for the test suite."""

import time

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np


# float64 tolerances used by every gradient and identity check.
RTOL = 1e-6
ATOL = 1e-9
# Finite-difference gradients lose about half the digits.
FD_RTOL = 1e-5
FD_ATOL = 1e-7


def tree_allclose(x, y, *, rtol=RTOL, atol=ATOL):
    """`True` when two PyTrees have the same structure and all leaves are close."""
    if jtu.tree_structure(x) != jtu.tree_structure(y):
        return False
    xs, ys = jtu.tree_leaves(x), jtu.tree_leaves(y)
    return all(np.shape(a) == np.shape(b) and np.allclose(a, b, rtol=rtol, atol=atol) for a, b in zip(xs, ys))


def finite_difference_jvp(fn, primals, tangents, eps=1e-6):
    """Central-difference Jacobian-vector product of `fn` at `primals` along `tangents`.

    Works on PyTrees of arrays; use in float64 only.
    """
    plus = jtu.tree_map(lambda p, t: p + eps * t, primals, tangents)
    minus = jtu.tree_map(lambda p, t: p - eps * t, primals, tangents)
    f_plus = fn(*plus)
    f_minus = fn(*minus)
    out = fn(*primals)
    tangent_out = jtu.tree_map(lambda a, b: (a - b) / (2 * eps), f_plus, f_minus)
    return out, tangent_out


def finite_difference_jacobian(fn, x, steps) -> np.ndarray:
    """Rows: central differences of the flattened output of `fn` along each coordinate of
    the vector `x`, coordinate `i` stepped by `steps[i]`. Use in float64 only."""
    x = np.asarray(x, np.float64)
    rows = []
    for i, h in enumerate(steps):
        e = np.zeros_like(x)
        e[i] = h
        rows.append(((np.asarray(fn(x + e)) - np.asarray(fn(x - e))) / (2 * h)).ravel())
    return np.stack(rows)


def camera_variance(frame, full_well: float, read_noise: float, bits: int = 8) -> np.ndarray:
    """The camera's pixel variance written out by hand (frame units): Poisson plus read
    variance in electrons, and the uniform rounding error of `bits`-bit quantisation."""
    v = np.clip(np.asarray(frame), 0, 1)
    return (v * full_well + read_noise**2) / full_well**2 + 1 / (12 * (2**bits - 1) ** 2)


def check_grad_against_fd(fn, x, *, eps=1e-6, rtol=FD_RTOL, atol=FD_ATOL, key=None):
    """Compare `jax.jvp` of a scalar- or array-valued `fn` with central differences.

    Uses a random tangent over the inexact leaves of `x` (so every parameter contributes).
    """
    key = jax.random.PRNGKey(0) if key is None else key
    dynamic, static = eqx.partition(x, eqx.is_inexact_array)
    leaves, treedef = jtu.tree_flatten(dynamic)
    keys = jax.random.split(key, len(leaves))
    tangent_leaves = [jax.random.normal(k, jnp.shape(l), jnp.result_type(l)) for k, l in zip(keys, leaves)]
    tangents = jtu.tree_unflatten(treedef, tangent_leaves)

    def f(d):
        return fn(eqx.combine(d, static))

    _, jvp_out = jax.jvp(f, (dynamic,), (tangents,))
    _, fd_out = finite_difference_jvp(f, (dynamic,), (tangents,), eps=eps)
    # Compare in the max norm, relative to the largest derivative: finite differences have
    # an absolute error set by the function's scale, not by each element's.
    for a, b in zip(jtu.tree_leaves(jvp_out), jtu.tree_leaves(fd_out)):
        a, b = np.asarray(a), np.asarray(b)
        error = np.max(np.abs(a - b)) if a.size else 0.0
        scale = np.max(np.abs(b)) if b.size else 0.0
        assert np.all(np.isfinite(a)), "non-finite derivative"
        assert error <= atol + rtol * scale, (error, scale)


def spectral_peak(image, px_per_mm, k_guess, radius):
    """Numpy reference: the spectral peak of `image` nearest `k_guess` (rad/mm, x right, y up).

    A Gaussian window makes the log-magnitude peak a parabola, refined to sub-bin
    precision. Returns the peak wavevector and the phase psi of `cos(K.x + psi)` at the
    image centre, from a direct DFT at the refined wavevector.
    """
    image = np.asarray(image, dtype=np.float64)
    h, w = image.shape
    dx = 1.0 / px_per_mm
    x = (np.arange(w) - (w - 1) / 2) * dx
    y = ((h - 1) / 2 - np.arange(h)) * dx
    X, Y = np.meshgrid(x, y)
    window = np.exp(-0.5 * ((X / (w * dx / 6)) ** 2 + (Y / (h * dx / 6)) ** 2))
    centred = (image - image.mean()) * window
    spectrum = np.abs(np.fft.fftshift(np.fft.fft2(centred)))
    kx = np.fft.fftshift(np.fft.fftfreq(w, dx)) * 2 * np.pi
    ky = -np.fft.fftshift(np.fft.fftfreq(h, dx)) * 2 * np.pi
    KX, KY = np.meshgrid(kx, ky)
    mask = np.hypot(KX - k_guess[0], KY - k_guess[1]) < radius
    i, j = np.unravel_index(np.argmax(np.where(mask, spectrum, 0)), spectrum.shape)
    logs = np.log(spectrum + 1e-300)

    def refine(lm, l0, lp):
        return 0.5 * (lm - lp) / (lm - 2 * l0 + lp)

    dj = refine(logs[i, j - 1], logs[i, j], logs[i, j + 1])
    di = refine(logs[i - 1, j], logs[i, j], logs[i + 1, j])
    K = np.array([kx[j] + dj * (kx[1] - kx[0]), ky[i] + di * (ky[1] - ky[0])])
    psi = np.angle(np.sum(centred * np.exp(-1j * (K[0] * X + K[1] * Y))))
    return K, psi


def wrap(angle):
    """Wrap angles to (-pi, pi]."""
    return (np.asarray(angle) + np.pi) % (2 * np.pi) - np.pi


def wait_until(predicate, timeout: float, poll: float = 0.005) -> bool:
    """Whether `predicate()` becomes true within `timeout` seconds, polled every `poll`."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(poll)
    return False
