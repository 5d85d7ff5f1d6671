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
# # 03 · Calibrating a unit against known loads
#
# No fabricated sensor is its drawing. The pitches are off by a fraction of a percent, the
# gratings are rotated a little, the elastomer is softer or stiffer than the datasheet, and the
# camera's gain and background differ. Notebook 02 showed that each of these moves the fringes'
# response to a load; an inversion that trusts the nominal design reads the wrong wrench.
#
# Calibration presses the unit with **known wrenches** (a reference force/torque sensor) and fits
# the parameters of the model until it reproduces what the camera saw. This notebook does that for
# a simulated unit whose true parameters we know, so the fit can be checked against the truth:
#
# 1. simulate a `high`-fidelity unit of the Mid design that deviates from its design, with a
#    calibration session (the paper's isolated-axis protocol) and a held-out session of mixed
#    loads;
# 2. invert the held-out frames with the nominal design, *before* calibration;
# 3. calibrate: fit the unit's physical parameters and latent contacts, then a small residual
#    head, and read the report (parity plots, fitted parameters against the truth);
# 4. invert the held-out frames again, *after* calibration, with and without the head.
#
# Set `MOIREJAX_SMOKE=1` for a quick pass at reduced sizes (the test suite does). The smoke sizes
# are far too small for the numbers to mean much; they only show that everything runs.

# %%
import json
import os
import tempfile
import time
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
from IPython.display import display, Image, Markdown

import moirejax as mj
from moirejax import (
    calibrate,
    Dataset,
    Deviations,
    evaluate,
    format_metrics,
    load_recipe,
    simulate_dataset,
    WRENCH_AXES,
    WRENCH_UNITS,
)


SMOKE = os.environ.get("MOIREJAX_SMOKE") == "1"
SEED = 3  # draws the unit (its deviations), its loads and its noise
N_CALIBRATION = 16 if SMOKE else 300  # calibration frames (paper protocol), a few contact-free first
N_HELDOUT = 8 if SMOKE else 60  # held-out frames (mixed loads); the first two are contact-free
RECIPE = load_recipe("unit")
if SMOKE:
    RECIPE = RECIPE.replace(rounds=1, parameter_frames=8, parameter_steps=4, latent_steps=8)
BASELINE_SIZES = (10,) if SMOKE else (20, 100, 200)

work = Path(tempfile.mkdtemp(prefix="moirejax-03-"))  # datasets, device files and report PNGs
# In smoke mode the camera is 256 x 256 px at 8 px/mm: the same 32 mm field at half the resolution.
nominal = mj.preset("mid", height=256, width=256, px_per_mm=8.0) if SMOKE else mj.preset("mid")
nominal_json = work / "mid.json"
mj.save_device(nominal_json, nominal)
print(f"working folder {work}")
print(f"{N_CALIBRATION} calibration frames, {N_HELDOUT} held-out frames, recipe {RECIPE}")

# %% [markdown]
# ## 1. A unit that deviates from its design
#
# `simulate_dataset(out, nominal, protocol, n, seed=S)` draws a unit around the nominal design with
# `perturb_device` (every deviation uniform within `Deviations`: pitches ±2%, angles ±0.5°,
# separation ±5%, stiffness ±30%, optical gain ±10%, background ±5%, and a random registration
# of each grating) and renders `n` frames of it under a load protocol with the `high`-fidelity
# renderer: area-sampled binary gratings, lens distortion, a grating phase error fixed per unit,
# shot and read noise, 8-bit frames. The **same seed draws the same unit**, so the two sessions
# below are two recordings of one sensor:
#
# - `paper`: the paper's calibration protocol, isolated axes (centre presses, shear under
#   preload, twist under preload, off-centre presses), after a few contact-free frames;
# - `mixed`: random combined loads at random positions, a harder test than the protocol the unit
#   was calibrated on.
#
# The dataset's manifest records the nominal device and, apart from it, the true one. Nothing
# after this cell looks at the truth except to score the result.

# %%
print(Deviations())
start = time.perf_counter()
calibration_dir = simulate_dataset(work / "calibration", nominal, "paper", N_CALIBRATION, seed=SEED)
heldout_dir = simulate_dataset(work / "heldout", nominal, "mixed", N_HELDOUT, seed=SEED)
print(f"simulated {N_CALIBRATION + N_HELDOUT} frames in {time.perf_counter() - start:.0f} s")
calibration, heldout = Dataset(calibration_dir), Dataset(heldout_dir)
assert calibration.true_device == heldout.true_device, "same seed, same unit"
print(calibration, heldout, sep="\n")
print(f"contact-free frames: {int(np.sum(~calibration.contact))} + {int(np.sum(~heldout.contact))}")
display(Image(filename=str(work / "calibration_contact_sheet.png")))

# %% [markdown]
# How far the unit is from its design. The moiré period is what the camera sees; a few percent of
# pitch change near $p_1' = p_2$ moves it by much more (notebook 01).

# %%
truth = mj.device_from_json(calibration.true_device)


def period_mm(device):
    return float(2 * np.pi / np.linalg.norm(np.asarray(device.moire_wavevectors())[0]))


quantities = {
    "p1 (mm)": lambda d: float(d.p1),
    "p2 (mm)": lambda d: float(d.p2),
    "α1 (deg)": lambda d: float(np.degrees(d.alpha1)),
    "α2 (deg)": lambda d: float(np.degrees(d.alpha2)),
    "a (mm)": lambda d: float(d.a),
    "E (MPa)": lambda d: float(d.elastomer.E),
    "optical gain": lambda d: float(d.optics.gain),
    "background": lambda d: float(d.optics.background),
    "glow gain": lambda d: float(d.optics.glow_gain),
    "moiré period Λ (mm)": period_mm,
}
rows = ["| quantity | nominal | true unit | change |", "|---|---|---|---|"]
for label, get in quantities.items():
    n, t = get(nominal), get(truth)
    change = f"{100 * (t - n) / n:+.1f}%" if n else f"{t - n:+.3f}"
    rows.append(f"| {label} | {n:.4g} | {t:.4g} | {change} |")
display(Markdown("\n".join(rows)))

# %% [markdown]
# ## 2. Before calibration
#
# `evaluate(device_json, dataset, out_dir)` inverts every in-contact frame of a dataset with a
# device, compares the wrenches with the reference readings, and writes `metrics.json`,
# `parity.png` and `residuals.png`. It takes the unit's no-contact reference from the dataset's
# contact-free frames; the inversion then matches the model's moiré wavevectors to those measured
# on that reference (`match_reference_geometry`), which fixes the apparent upper pitch and angle.
# So even the nominal design starts from the unit's own fringe geometry; what it gets wrong is the
# rest: the stiffness that turns a load into displacement, the optics that turn a press into
# light.

# %%
before = evaluate(nominal_json, heldout_dir, work / "before")
print(format_metrics(before, title="nominal design on the held-out mixed loads"))

# %% [markdown]
# ## 3. Calibration
#
# `calibrate(nominal_json, data, fit_json, recipe="unit")` fits the unit in two stages.
#
# **Physical parameters.** The unknowns are a few parameters shared by all frames (the recipe's
# `free` list) and, per frame, the contact that the reference sensor does not report: centre,
# radius and exposure (the *latents*). The wrench of every frame is known. The fit alternates two
# `optimistix` Levenberg–Marquardt solves in the demodulated domain that the inversion uses
# (notebook 02): the shared parameters over a random subset of `parameter_frames` frames with the
# latents fixed, then the latents of the frames those subsets use (one frame after another) with
# the parameters fixed, `rounds` times. Positive parameters are fitted in log space; their 1-σ uncertainties come from
# the Gauss–Newton information at the end.
#
# The default recipe frees the stiffness $E$ and five optical parameters (glow gain and width, rim
# gain, overall gain, defocus). It leaves the grating geometry alone: the reference frame already fixes
# the apparent upper pitch and angle, and what remains (the common scale of both pitches, the
# separation) is degenerate with the stiffness in every load response.
#
# **Residual head.** The calibration frames are then inverted with the fitted device, and a small
# linear correction (`ResidualHead`: linear in the physical wrench estimate, the contact centre
# and log radius, and in the load times the contact's position and size) learns what the physics
# leaves, by ridge regression with a cross-validated penalty; an axis whose cross-validated error
# it does not lower keeps only its mean residual. A correction of that form adds up over the axes of a load, so
# what it learns from the protocol's isolated axes holds for combined loads. From fewer than 50
# usable frames no head is trained (a correction learned from a few dozen frames extrapolates
# badly to other loads): the smoke run stops at the physics.
#
# The report beside the fitted device holds `metrics.json` (in-sample metrics with and without
# the head, fitted parameters with their truth, the cost per round, the paper's Eq. 9 tilt matrix,
# the ridge baseline) and the plots.

# %%
fit_json = work / "fit.json"
start = time.perf_counter()
summary = calibrate(nominal_json, calibration_dir, fit_json, recipe=RECIPE, baseline_sizes=BASELINE_SIZES)
print(f"calibrated in {time.perf_counter() - start:.0f} s; wrote {fit_json.name}, {Path(summary['report']).name}/")
report = Path(summary["report"])
written = json.loads((report / "metrics.json").read_text())
for h in written["history"]:
    print(f"round {h['round']}: " + ", ".join(f"{k} {v:.4g}" for k, v in h.items() if k != "round"))
head_name = json.loads(fit_json.read_text())["calibration"]["residual_head"]
print(format_metrics(summary["physics_only"], title="\nphysics only, calibration frames (in-sample)"))
if head_name is not None:
    print(format_metrics(summary["metrics"], title="\nwith the residual head, calibration frames (in-sample)"))
else:
    print(f"\nno residual head: {written['residual_head']}")

# %% [markdown]
# The in-sample parity plot (estimate against reference per axis, with the inversion's 95%
# intervals). In-sample means the head has seen four fifths of these frames; the held-out test is
# in section 4.

# %%
display(Image(filename=str(report / "parity.png")))

# %% [markdown]
# ### Fitted parameters against the truth
#
# `parameters.png` shows each free parameter's deviation from nominal: fitted (with its 95%
# interval) and the true unit's (red crosses). `perturb_device` varies the stiffness and the
# optical gain; the glow, rim and defocus of this simulated unit are the nominal ones, so for those
# the right answer is "no change".

# %%
display(Image(filename=str(report / "parameters.png")))
rows = ["| parameter | nominal | fitted ± 1σ | true | fitted − true (σ) |", "|---|---|---|---|---|"]
for p in written["parameters"]:
    z = (p["fitted"] - p["true"]) / p["sd"] if p["sd"] > 0 else float("nan")
    rows.append(
        f"| {p['parameter']} | {p['nominal']:.4g} | {p['fitted']:.4g} ± {p['sd']:.2g} | {p['true']:.4g} | {z:+.1f} |"
    )
display(Markdown("\n".join(rows)))
E = next(p for p in written["parameters"] if p["parameter"] == "elastomer.E")
print(
    f"stiffness: nominal {E['nominal']:.3f} MPa, true {E['true']:.3f} MPa, fitted {E['fitted']:.3f} MPa: "
    f"{100 * (1 - abs(E['fitted'] - E['true']) / abs(E['nominal'] - E['true'])):.0f}% of the gap closed"
)

# %% [markdown]
# The sigmas are the Gauss–Newton uncertainties of the parameter solve, scaled by its residual;
# they do not include what the model cannot represent (the high-fidelity renderer's binary
# gratings, distortion and phase error; the pitch and separation deviations the recipe does not
# free), so a fitted value several sigmas from the truth is a model error, not bad luck.
#
# The report also holds the paper's Eq. 9, a linear map from the contact centre in the image to
# $(T_x, T_y)$, fitted by least squares, and a learned baseline (ridge regression on
# downsampled frames, `ridge_baseline`) trained on a number of the calibration frames and scored by
# five-fold cross-validation over them (every frame predicted by a model that did not see it).

# %%
tilt = np.round(written["tilt_matrix"], 5).tolist()
print(f"tilt matrix (Eq. 9, N·m per mm): {tilt}, R² {written['tilt_matrix_r2']:.3f}")
for n_train, r2 in written["ridge_baseline_r2_crossvalidated"].items():
    # metrics.json writes an undefined value (an axis this session never loads) as null.
    values = ", ".join(f"{a} {r2[a]:.3f}" if r2[a] is not None else f"{a} undefined" for a in WRENCH_AXES)
    print(f"ridge baseline on {n_train} frames, cross-validated R²: {values}")
if head_name is not None:
    print(f"residual head training: {written['residual_head']}")

# %% [markdown]
# ## 4. After calibration, on the held-out loads
#
# When the fitted device file names a residual head, `evaluate` applies it: its returned metrics
# are those of the corrected wrench, and the physical inversion alone is reported beside them under
# `physics_only`. Without a head the two are the same.

# %%
after = evaluate(fit_json, heldout_dir, work / "after")
physics = after["physics_only"] if head_name is not None else after
print(format_metrics(physics, title="calibrated, physics only, held-out mixed loads"))
if head_name is not None:
    print(format_metrics(after, title="\ncalibrated with the residual head, held-out mixed loads"))

# %%
columns = {"nominal design": before, "calibrated, physics only": physics}
if head_name is not None:
    columns["calibrated + head"] = after
header = "| axis | " + " | ".join(f"{c}: R² / MAE" for c in columns) + " |"
rows = [header, "|---|" + "---|" * len(columns)]
for j, axis in enumerate(WRENCH_AXES):
    scale, unit = (1.0, "N") if WRENCH_UNITS[j] == "N" else (1e3, "mN·m")
    cells = [f"{m['r2'][axis]:.3f} / {scale * m['mae'][axis]:.3g} {unit}" for m in columns.values()]
    rows.append(f"| {axis} | " + " | ".join(cells) + " |")
rows.append("| frames (failed) | " + " | ".join(f"{m['n']} ({m['n_failed']})" for m in columns.values()) + " |")
display(Markdown("\n".join(rows)))

fig, ax = plt.subplots(figsize=(9, 3.5))
width = 0.8 / len(columns)
for k, (label, m) in enumerate(columns.items()):
    offset = (k - (len(columns) - 1) / 2) * width
    ax.bar(np.arange(6) + offset, [max(m["r2"][a], -0.5) for a in WRENCH_AXES], width, label=label)
ax.set_xticks(np.arange(6), WRENCH_AXES)
ax.axhline(1.0, color="k", lw=0.8)
ax.set_ylim(-0.5, 1.05)
ax.set_ylabel("held-out R² (clipped at −0.5)")
ax.legend(fontsize=8, loc="lower right")
ax.grid(alpha=0.3, axis="y")
fig.tight_layout()
plt.show()

# %% [markdown]
# The held-out parity plot after calibration, with the head:

# %%
display(Image(filename=str(work / "after" / "parity.png")))
status = json.loads((work / "after" / "metrics.json").read_text())["status_counts"]
print(f"inversion status on the held-out frames: {status}")

# %% [markdown]
# ## Reading the result
#
# The table above is what this run measured; with the smoke sizes (a handful of frames, one short
# round) it says little beyond "it runs", and even at full size it is one simulated unit, one
# seed. Things to look for:
#
# - **Force scale.** A stiffness error scales the displacement of every load, so before
#   calibration the forces come out too large or too small; the fit of $E$ is what moves $F_x$,
#   $F_y$ and $T_z$. Compare the fitted and true $E$ above.
# - **The press.** $F_z$ is read largely from the contact's light (glow and rim) and from the
#   local change of fringe period; the optical gain and the glow gain set that scale.
# - **Off-centre moments.** $T_x$ and $T_y$ follow from where the contact is times $F_z$, so they
#   are good whenever the contact is found and $F_z$ is right.
# - **The head** can only correct what is systematic in the calibration frames. On a held-out set
#   with a different load distribution (mixed loads against isolated axes) it can help or hurt;
#   the physics-only column is the honest measure of the model.
#
# A calibration is only as good as the reference wrenches and the spread of loads it saw. Notebook
# 04 carries this calibration to a second unit with twenty frames instead of hundreds.
