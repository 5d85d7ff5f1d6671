# ---
# jupyter:
#   jupytext:
#     cell_metadata_filter: -all
#     formats: ipynb,py:percent
#     text_representation:
#       extension: .py
#       format_name: percent
#       format_version: '1.3'
#       jupytext_version: 1.19.6
#   kernelspec:
#     display_name: Python 3 (ipykernel)
#     language: python
#     name: python3
# ---

# %% [markdown]
# # 01 · The design space of a moiré sensor
#
# A MoiréTac sensor stacks two line gratings: a fixed **reference grating** (pitch $p_2$) at
# distance $Z$ from the camera, and an **upper grating** (pitch $p_1$) on the soft contact surface
# at $Z + a$. Their beat is a moiré fringe pattern of period $\Lambda$ and orientation $\theta$ that
# moves far more than the surface does. This notebook maps what the design parameters
# ($p_1$, $p_2$, the angle $\Delta\alpha = \alpha_1 - \alpha_2$, and the stack $a/Z$) give:
#
# 1. the paper's Dense / Mid / Sparse table, reproduced with `mj.design_table`;
# 2. the two parallax models the paper mixes, first order and exact;
# 3. $\Lambda$, $\theta$ and the amplification $A$ over $p_1$, $p_2$ and $\Delta\alpha$;
# 4. how much the fringes respond to a load (`mj.force_sensitivity`), and what the model says
#    about the paper's "about threefold" sensitivity range across the three designs.
#
# Set `MOIREJAX_SMOKE=1` for a quick pass at reduced sizes (the test suite does).

# %%
import dataclasses
import math
import os

import matplotlib.pyplot as plt
import numpy as np
from IPython.display import display, Markdown

import moirejax as mj


SMOKE = os.environ.get("MOIREJAX_SMOKE") == "1"
MAP_POINTS = 61 if SMOKE else 301  # samples per axis of the closed-form maps
SWEEP_POINTS = 7 if SMOKE else 37  # designs per force-sensitivity sweep
MECHANICS = (32, 32) if SMOKE else (128, 128)  # elastomer grid of force_sensitivity
PRESETS = ("dense", "mid", "sparse")
COLOURS = {"dense": "tab:blue", "mid": "tab:orange", "sparse": "tab:green"}

devices = {name: mj.preset(name) for name in PRESETS}
a, Z = float(devices["mid"].a), float(devices["mid"].Z)
print(f"all presets: a = {a} mm, Z = {Z} mm, a/Z = {a / Z}")


def geometric_gain(device):
    """Λ/p1': fringe motion in the image per unit motion of the far grating's image (aligned: A p2/p1')."""
    delta_alpha = device.alpha1 - device.alpha2
    period = mj.moire_period_exact(device.p1, device.p2, delta_alpha, device.a, device.Z)
    return float(period / mj.apparent_pitch(device.p1, device.a, device.Z))


# %% [markdown]
# ## 1. The paper's table
#
# `mj.design_table(device)` returns plain numbers: the object mismatch
# $\delta_\text{obj} = (p_1 - p_2)/p$, the effective mismatch in both parallax models, the moiré
# period, the amplification $A = \Lambda/p_2$, the shear amplification $\Lambda/p_1$ (fringe motion
# per unit surface motion), and `jax.jacfwd` derivatives of $\Lambda$ and $A$ with respect to
# every design parameter.

# %%
tables = {name: mj.design_table(device) for name, device in devices.items()}
header = (
    "| design | p1, p2 (mm) | A | δ_eff first order | δ_eff exact | Λ exact (mm) | Λ first order (mm) "
    "| shear amplification Λ/p1 |\n|---|---|---|---|---|---|---|---|"
)
rows = [
    f"| {name.capitalize()} | {t['p1_mm']:.2f}, {t['p2_mm']:.2f} | {t['amplification_A']:.2f} "
    f"| {t['delta_eff_first_order']:.2f} | {t['delta_eff_exact']:.3f} | {t['period_mm_exact']:.2f} "
    f"| {t['period_mm_first_order']:.2f} | {t['shear_amplification']:.1f} |"
    for name, t in tables.items()
]
display(Markdown("\n".join([header, *rows])))

# The paper: A = 4.00 / 14.00 / 24.00 and delta_eff = 0.25 / 0.10 / 0.07.
paper = {"dense": (4.00, 0.25), "mid": (14.00, 0.10), "sparse": (24.00, 0.07)}
for name, (A, delta_eff) in paper.items():
    assert round(tables[name]["amplification_A"], 2) == A, name
    assert round(tables[name]["delta_eff_first_order"], 2) == delta_eff, name
print("paper's A and delta_eff reproduced to the digits it gives")

# %% [markdown]
# The full table of one design, as `moirejax design --preset mid` prints it, including the
# derivatives. Near $p_1' = p_2$ the period is steep in both pitches, which is why a fabricated
# unit must be calibrated rather than trusted to its drawing.

# %%
print(mj.format_design_table(tables["mid"]))
dperiod_dp1 = tables["mid"]["dperiod"]["p1"]
print(
    f"\nMid: a 1 µm error in p1 moves the period by {dperiod_dp1 * 1e-3:.3f} mm "
    f"({100 * dperiod_dp1 * 1e-3 / tables['mid']['period_mm_exact']:.1f}%)"
)

# %% [markdown]
# ## 2. First-order versus exact parallax
#
# The camera sees the far grating (pitch $p_1$ at distance $Z + a$) projected onto the reference
# plane with magnification $Z/(Z + a)$, i.e. with the **apparent pitch** $p_1' = p_1 Z/(Z + a)$.
# The moiré period is the beat of $p_1'$ and $p_2$:
#
# $$\Lambda = \frac{p_1' p_2}{\sqrt{p_1'^2 + p_2^2 - 2 p_1' p_2 \cos\Delta\alpha}}
# \quad\xrightarrow{\Delta\alpha = 0}\quad \frac{p_1' p_2}{|p_1' - p_2|}.$$
#
# The paper's Eq. 7 expands this to first order in $a/Z$: $p_1' \approx p_1 (1 - a/Z)$, so
# $\delta_\text{eff} \approx |\delta_\text{obj} - a/Z|$. With $a/Z = 0.25$ the expansion is not
# small ($1/(1 + 0.25) = 0.80$ against $1 - 0.25 = 0.75$): the first-order $\delta_\text{eff}$
# (0.25 / 0.10 / 0.07) overstates the exact one (0.22 / 0.07 / 0.04). The paper's $\delta_\text{eff}$
# column is first order while its $A$ column ($A = \Lambda/p_2 = p_1'/|p_2 - p_1'|$ for aligned
# gratings) is exact; `design_table` gives both and labels them. The forward model renders the
# exact geometry.
#
# Below, both models against $a/Z$. They agree only for a thin stack, and they put the
# singularity ($p_1' = p_2$, infinite period) at different separations.

# %%
a_over_Z = np.linspace(0.0, 0.4, MAP_POINTS)
fig, axes = plt.subplots(1, 2, figsize=(12, 4))
for name, device in devices.items():
    p1, p2 = float(device.p1), float(device.p2)
    first = np.asarray(mj.effective_mismatch_first_order(p1, p2, a_over_Z * Z, Z))
    exact = np.asarray(mj.effective_mismatch_exact(p1, p2, a_over_Z * Z, Z))
    c = COLOURS[name]
    axes[0].plot(a_over_Z, first, "--", color=c, label=f"{name}, first order")
    axes[0].plot(a_over_Z, exact, "-", color=c, label=f"{name}, exact")
    with np.errstate(divide="ignore"):  # the first-order period is infinite where delta_eff = 0
        axes[1].semilogy(a_over_Z, (p1 + p2) / 2 / first, "--", color=c)
    axes[1].semilogy(a_over_Z, np.asarray(mj.moire_period_exact(p1, p2, 0.0, a_over_Z * Z, Z)), "-", color=c)
for ax in axes:
    ax.axvline(a / Z, color="k", lw=0.8)
    ax.set_xlabel("a / Z")
    ax.grid(alpha=0.3)
axes[0].set_ylabel("effective mismatch δ_eff")
axes[0].legend(fontsize=8, ncol=2)
axes[1].set_ylabel("moiré period Λ (mm), aligned gratings")
axes[1].set_title("dashed: p/δ_eff (first order); solid: exact", fontsize=10)
axes[1].set_ylim(0.1, 1e3)
fig.tight_layout()
plt.show()

# %% [markdown]
# ## 3. Period, orientation and amplification over $p_1$, $p_2$ and $\Delta\alpha$
#
# Every moiré geometry function (`mj.moire_period`, `mj.geometric_amplification`, ...) is a pure
# JAX function, so whole maps are one call. The white dashed line is $p_1' = p_2$: aligned
# gratings with equal apparent pitch give no fringes at all. On either side the amplification
# grows without bound, and the fringe period with it, until a single fringe no longer fits in the
# field of view.

# %%
pitches = np.linspace(0.15, 0.45, MAP_POINTS)
P1, P2 = np.meshgrid(pitches, pitches, indexing="xy")
period = np.asarray(mj.moire_period_exact(P1, P2, 0.0, a, Z))
amplification = np.asarray(mj.geometric_amplification(P1, P2, 0.0, a, Z))
fig, axes = plt.subplots(1, 2, figsize=(12, 4.8))
for ax, field, levels, title in (
    (axes[0], period, [1, 4, 10], "log10 moiré period Λ (mm), aligned; contours at 1, 4, 10 mm"),
    (axes[1], amplification, [4, 14, 24], "log10 amplification A = Λ / p2; contours at 4, 14, 24"),
):
    im = ax.pcolormesh(P1, P2, np.log10(np.clip(field, 1e-3, 1e4)), shading="auto", cmap="viridis", vmax=3)
    fig.colorbar(im, ax=ax)
    ax.contour(P1, P2, field, levels=levels, colors="w", linewidths=0.6)
    ax.plot(pitches, pitches * Z / (Z + a), "w--", lw=1)
    for name, device in devices.items():
        ax.plot(float(device.p1), float(device.p2), "r*", ms=12)
        ax.annotate(name, (float(device.p1), float(device.p2)), color="w", xytext=(5, 5), textcoords="offset points")
    ax.set_xlim(pitches[0], pitches[-1])
    ax.set_ylim(pitches[0], pitches[-1])
    ax.set_xlabel("p1, upper grating (mm)")
    ax.set_ylabel("p2, reference grating (mm)")
    ax.set_title(title, fontsize=10)
fig.tight_layout()
plt.show()

# %% [markdown]
# Rotating one grating moves the design from the pitch-dominated regime ($\Lambda \approx p/\delta$,
# fringes parallel to the grating lines) to the angle-dominated one ($\Lambda \approx p/\Delta\alpha$,
# fringes nearly perpendicular to them). Near $\Delta\alpha = 0$ the fringes turn
# $d\theta/d\Delta\alpha = \Lambda/p_1'$ times faster than the grating: 5, 15 and 25 for the three
# presets. That is the gain a twist of the contact surface enjoys.

# %%
angles = np.radians(np.linspace(-6, 6, MAP_POINTS))
fig, axes = plt.subplots(1, 3, figsize=(15, 4))
for name, device in devices.items():
    p1, p2 = float(device.p1), float(device.p2)
    k1 = mj.grating_wavevector(mj.apparent_pitch(p1, a, Z), angles)
    k2 = mj.grating_wavevector(p2, np.zeros_like(angles))
    K = mj.moire_wavevector(k1, k2)
    theta = np.degrees(np.asarray(mj.moire_orientation(K)))
    lam = np.asarray(mj.moire_period(K))
    c = COLOURS[name]
    axes[0].semilogy(np.degrees(angles), lam, color=c, label=name)
    axes[0].semilogy(
        np.degrees(angles),
        np.asarray(mj.moire_period_angle_dominated(p1, p2, angles)),
        ":",
        color=c,
        lw=1,
    )
    axes[1].plot(np.degrees(angles), theta, color=c, label=name)
    axes[2].semilogy(np.degrees(angles), lam / p2, color=c, label=name)
axes[0].set_ylabel("Λ (mm); dotted: angle-dominated limit p/Δα")
axes[1].set_ylabel("fringe orientation θ (deg)")
axes[2].set_ylabel("amplification A = Λ / p2")
for ax in axes:
    ax.set_xlabel("Δα = α1 − α2 (deg)")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
fig.tight_layout()
plt.show()

for name, device in devices.items():
    print(f"{name:6s}  Λ/p1' = {geometric_gain(device):5.1f}  (dθ/dΔα at Δα = 0)")

# %% [markdown]
# ## 4. Force sensitivity
#
# `mj.force_sensitivity(device)` differentiates the mechanics (a 3 mm PDMS layer bonded to a rigid
# carrier, E = 1 MPa) and the phase relation of the renderer with `jax.jacfwd`, at a centred
# 3.5 mm contact under 0.6 N preload. A surface displacement $u$ and compression $w$ at surface
# point $X$ change the phase of a fringe family by $\Delta\psi = -k_1\cdot(u + X w/(Z + a))$:
#
# - **phase** (rad per N): set by $|k_1| = 2\pi/p_1$ alone, *not* by the amplification;
# - **fringe shift** (mm per N in the image), **fringe rotation** (rad per N·m of twist) and the
#   **relative period change** (per N of press) all carry the amplification $\Lambda/p_1'$.

# %%
sensitivity = {name: mj.force_sensitivity(device, mechanics_shape=MECHANICS) for name, device in devices.items()}
keys = {
    "fx_phase_peak_rad_per_N": "Fx phase, peak (rad/N)",
    "fx_fringe_shift_mm_per_N": "Fx fringe shift (mm/N)",
    "tz_fringe_rotation_rad_per_Nm": "Tz fringe rotation (rad/(N·m))",
    "fz_compression_mm_per_N": "Fz compression (mm/N)",
    "fz_period_change_rel_per_N": "Fz relative period change (1/N)",
    "fz_parallax_share": "share of it from parallax",
    "period_mm": "local period under preload (mm)",
}
lines = ["| quantity | " + " | ".join(n.capitalize() for n in PRESETS) + " |", "|---|---|---|---|"]
for key, label in keys.items():
    lines.append(f"| {label} | " + " | ".join(f"{sensitivity[n][key]:.3g}" for n in PRESETS) + " |")
display(Markdown("\n".join(lines)))

# %% [markdown]
# ### The "about threefold" range
#
# The paper reports about a threefold sensitivity range across its three designs. The ratios the
# model finds, relative to Dense:

# %%
ratio_keys = (
    "fx_phase_peak_rad_per_N",
    "fx_fringe_shift_mm_per_N",
    "tz_fringe_rotation_rad_per_Nm",
    "fz_period_change_rel_per_N",
)

amplification_ratio = {n: geometric_gain(devices[n]) for n in PRESETS}
lines = ["| quantity | Mid / Dense | Sparse / Dense |", "|---|---|---|"]
lines.append(
    f"| geometric gain Λ/p1' (unloaded) | {amplification_ratio['mid'] / amplification_ratio['dense']:.2f} "
    f"| {amplification_ratio['sparse'] / amplification_ratio['dense']:.2f} |"
)
for key in ratio_keys:
    dense, mid, sparse = (sensitivity[n][key] for n in PRESETS)
    lines.append(f"| {keys[key]} | {mid / dense:.2f} | {sparse / dense:.2f} |")
display(Markdown("\n".join(lines)))
shift = [sensitivity[n]["fx_fringe_shift_mm_per_N"] for n in PRESETS]
assert shift[0] < shift[1] < shift[2], "fringe motion should grow Dense < Mid < Sparse"

# %% [markdown]
# What the model finds, stated plainly:
#
# - Everything measured **in the image** (fringe shift, fringe rotation, relative period change)
#   follows the geometric gain $\Lambda/p_1'$ (5 / 15 / 25), slightly more under preload because the
#   press makes the local fringes sparser. Mid is about **3×** Dense, as the paper says, but Sparse
#   is nearer **6×** Dense, not 3×: "threefold" describes the Dense → Mid step only.
# - The fringe **phase** per newton does not follow the amplification at all: it is
#   $2\pi/p_1$ times the surface displacement, so Dense (the smallest $p_1$) has the largest phase
#   response and Mid the smallest. A sparser moiré moves its fringes farther, but there are fewer
#   of them across the contact. Whether the larger fringe motion is worth the fewer fringes is a
#   question of noise and pixels, answered by the Cramér–Rao bounds of notebook 06.
# - The press sensitivity has two sources: the layer squeezed outward (in-plane strain) and the
#   compression $w$ changing the parallax locally; the parallax share is the same for all three
#   designs because both scale with the geometric gain.
#
# ### Sensitivity across the design space
#
# The same quantities along three cuts through the design space, each relative to Mid: $p_1$ at
# Mid's $p_2$, $p_2$ at Mid's $p_1$, and $\Delta\alpha$ at Mid's pitches. Designs within 3% of
# $p_1' = p_2$ (no fringes) are skipped.

# %%
mid = devices["mid"]


def sweep(designs):
    """force_sensitivity of each design, as arrays keyed like its dict."""
    results = [mj.force_sensitivity(d, mechanics_shape=MECHANICS) for d in designs]
    return {key: np.array([r[key] for r in results]) for key in results[0]}


def usable(p1, p2):
    return abs(p1 * Z / (Z + a) / p2 - 1) > 0.03


p1_values = [p for p in np.linspace(0.20, 0.50, SWEEP_POINTS) if usable(p, float(mid.p2))]
p2_values = [p for p in np.linspace(0.18, 0.45, SWEEP_POINTS) if usable(float(mid.p1), p)]
angle_values = np.linspace(0.0, 6.0, SWEEP_POINTS)
cuts = {
    "p1 (mm), p2 = 0.30 mm": (p1_values, [dataclasses.replace(mid, p1=p) for p in p1_values]),
    "p2 (mm), p1 = 0.35 mm": (p2_values, [dataclasses.replace(mid, p2=p) for p in p2_values]),
    "Δα (deg), Mid pitches": (angle_values, [dataclasses.replace(mid, alpha1=math.radians(d)) for d in angle_values]),
}
reference = sensitivity["mid"]
fig, axes = plt.subplots(1, 3, figsize=(15, 4.2), sharey=True)
for ax, (label, (x, designs)) in zip(axes, cuts.items()):
    s = sweep(designs)
    gain = np.array([geometric_gain(d) for d in designs])
    ax.semilogy(x, gain / geometric_gain(mid), "k:", label="geometric gain Λ/p1'")
    for key in ratio_keys:
        ax.semilogy(x, np.abs(s[key]) / abs(reference[key]), "o-", ms=3, label=keys[key])
    ax.axhline(1, color="grey", lw=0.6)
    ax.set_xlabel(label)
    ax.grid(alpha=0.3, which="both")
axes[0].set_ylabel("relative to Mid")
axes[0].legend(fontsize=8)
fig.suptitle("Fringe response per unit load along three cuts through the design space", fontsize=11)
fig.tight_layout()
plt.show()

# %% [markdown]
# The phase curve is flat in $p_2$ and $\Delta\alpha$ and falls as $1/p_1$. Along the pitch cuts the
# three image-space quantities lie on one curve that rides on the geometric gain, which diverges at
# $p_1' = p_2$. Along $\Delta\alpha$ the gain falls as the angle takes over, and the twist and press
# responses fall faster still: the fringes are no longer parallel to the grating lines, so a turn
# or a stretch of the upper grating projects less onto the fringe wavevector.
#
# Large gain is cheap to buy and easy to overdo: the fringes wrap (a twist over the paper's range
# already turns Mid's fringes by about $2\pi$ near the contact edge), and a period comparable to
# the field leaves too few fringes to demodulate. Notebook 02 renders what these numbers mean for
# a frame; notebook 06 weighs them against camera noise.
