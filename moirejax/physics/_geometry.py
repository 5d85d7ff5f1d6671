r"""Moiré geometry of two stacked gratings seen by a pinhole camera (paper Eq. 1, 2, 5–7).

Every function is pure and differentiable; pitches and lengths are in mm, angles in
radians, wavevectors in rad/mm in the x-right / y-up frame of the rectified image
(the reference-grating plane).

The paper mixes two approximations. Its δ_eff (Eq. 7) is first order in a/Z and
uses the object-space mismatch $\delta_\text{obj} = (p_1 - p_2)/p$. Its amplification
$A$ uses the exact projection: the far grating (pitch $p_1$ at $Z + a$) is seen in the
reference plane with apparent pitch $p_1' = p_1 Z/(Z + a)$. Both are provided, and the
exact parallax model is the one the forward model renders.
"""

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float


def grating_wavevector(pitch: ArrayLike, angle: ArrayLike) -> Float[Array, "*batch 2"]:
    r"""Wavevector $k = \frac{2\pi}{p}(\cos\alpha, \sin\alpha)$ of a line grating (Eq. 1).

    **Arguments:**

    - `pitch`: grating period $p$ (mm).
    - `angle`: direction $\alpha$ of the wavevector (rad), i.e. the normal to the lines.

    **Returns:** the wavevector (rad/mm), last axis `(kx, ky)`.
    """
    pitch, angle = jnp.broadcast_arrays(jnp.asarray(pitch), jnp.asarray(angle))
    magnitude = 2 * jnp.pi / pitch
    return jnp.stack([magnitude * jnp.cos(angle), magnitude * jnp.sin(angle)], axis=-1)


def moire_wavevector(k1: Float[Array, "*batch 2"], k2: Float[Array, "*batch 2"]) -> Float[Array, "*batch 2"]:
    r"""Moiré (beat) wavevector $K = k_1 - k_2$ (Eq. 2)."""
    return k1 - k2


def moire_period(K: Float[Array, "*batch 2"]) -> Float[Array, "*batch"]:
    r"""Moiré period $\Lambda = 2\pi / \lVert K \rVert$ (Eq. 2)."""
    return 2 * jnp.pi / jnp.linalg.norm(K, axis=-1)


def moire_orientation(K: Float[Array, "*batch 2"]) -> Float[Array, "*batch"]:
    r"""Moiré orientation $\theta = \operatorname{atan2}(K_y, K_x)$ (Eq. 2)."""
    return jnp.arctan2(K[..., 1], K[..., 0])


def moire_period_general(p1: ArrayLike, p2: ArrayLike, delta_alpha: ArrayLike) -> Array:
    r"""Closed-form moiré period of two line gratings (Eq. 5):

    $$\Lambda = \frac{p_1 p_2}{\sqrt{p_1^2 + p_2^2 - 2 p_1 p_2 \cos\Delta\alpha}}.$$

    Infinite for identical, aligned gratings.
    """
    p1, p2, delta_alpha = jnp.asarray(p1), jnp.asarray(p2), jnp.asarray(delta_alpha)
    # (p1 - p2)^2 + 2 p1 p2 (1 - cos Δα) avoids cancellation for nearly equal pitches.
    squared = (p1 - p2) ** 2 + 4 * p1 * p2 * jnp.sin(delta_alpha / 2) ** 2
    return p1 * p2 / jnp.sqrt(squared)


def moire_period_angle_dominated(p1: ArrayLike, p2: ArrayLike, delta_alpha: ArrayLike) -> Array:
    r"""Angle-dominated limit of Eq. 5 (Eq. 6): $\Lambda \approx p/\Delta\alpha$, $p = (p_1+p_2)/2$."""
    return (jnp.asarray(p1) + jnp.asarray(p2)) / 2 / jnp.abs(jnp.asarray(delta_alpha))


def moire_period_pitch_dominated(p1: ArrayLike, p2: ArrayLike) -> Array:
    r"""Pitch-dominated limit of Eq. 5 (Eq. 6): $\Lambda = p/\delta$, $\delta = |p_2 - p_1|/p$."""
    p = (jnp.asarray(p1) + jnp.asarray(p2)) / 2
    return p / relative_mismatch(p1, p2)


def relative_mismatch(p1: ArrayLike, p2: ArrayLike) -> Array:
    r"""Unsigned relative pitch mismatch $\delta = |p_2 - p_1| / p$ with $p = (p_1 + p_2)/2$."""
    p1, p2 = jnp.asarray(p1), jnp.asarray(p2)
    return jnp.abs(p2 - p1) / ((p1 + p2) / 2)


def object_mismatch(p1: ArrayLike, p2: ArrayLike) -> Array:
    r"""Signed object-space mismatch $\delta_\text{obj} = (p_1 - p_2)/p$ used by Eq. 7."""
    p1, p2 = jnp.asarray(p1), jnp.asarray(p2)
    return (p1 - p2) / ((p1 + p2) / 2)


def effective_mismatch_first_order(p1: ArrayLike, p2: ArrayLike, a: ArrayLike, Z: ArrayLike) -> Array:
    r"""The paper's first-order effective mismatch (Eq. 7): $\delta_\text{eff} \approx |\delta_\text{obj} - a/Z|$."""
    return jnp.abs(object_mismatch(p1, p2) - jnp.asarray(a) / jnp.asarray(Z))


def apparent_pitch(pitch: ArrayLike, depth_offset: ArrayLike, Z: ArrayLike) -> Array:
    r"""Pitch of a grating at distance $Z + a$ as seen in the reference plane at $Z$: $p Z/(Z + a)$."""
    Z = jnp.asarray(Z)
    return jnp.asarray(pitch) * Z / (Z + jnp.asarray(depth_offset))


def effective_mismatch_exact(p1: ArrayLike, p2: ArrayLike, a: ArrayLike, Z: ArrayLike) -> Array:
    r"""Exact-parallax effective mismatch: $\delta$ between $p_1' = p_1 Z/(Z+a)$ and $p_2$.

    This is the mismatch that sets the rendered moiré period, $\Lambda = p'/\delta$ with
    $p' = (p_1' + p_2)/2$ for aligned gratings.
    """
    return relative_mismatch(apparent_pitch(p1, a, Z), p2)


def moire_period_exact(p1: ArrayLike, p2: ArrayLike, delta_alpha: ArrayLike, a: ArrayLike, Z: ArrayLike) -> Array:
    r"""Moiré period in the reference plane with exact parallax: Eq. 5 with $p_1 \to p_1 Z/(Z+a)$."""
    return moire_period_general(apparent_pitch(p1, a, Z), p2, delta_alpha)


def geometric_amplification(p1: ArrayLike, p2: ArrayLike, delta_alpha: ArrayLike, a: ArrayLike, Z: ArrayLike) -> Array:
    r"""The paper's geometric amplification $A = \Lambda / p_2$.

    For aligned gratings this is $A = p_1'/|p_2 - p_1'|$, the fringe displacement per unit
    displacement of the reference grating; the paper's 4.00 / 14.00 / 24.00 table.
    """
    return moire_period_exact(p1, p2, delta_alpha, a, Z) / jnp.asarray(p2)


def shear_amplification(p1: ArrayLike, p2: ArrayLike, delta_alpha: ArrayLike, a: ArrayLike, Z: ArrayLike) -> Array:
    r"""Fringe displacement in the image per unit in-plane displacement of the contact surface.

    A surface displacement $u$ along $k_1$ shifts the fringe phase by $|k_1| u$, which
    moves the fringes by $|k_1| u / |K| = u \Lambda / p_1$ in the reference plane. This is
    the amplification that matters for shear sensing.
    """
    return moire_period_exact(p1, p2, delta_alpha, a, Z) / jnp.asarray(p1)
