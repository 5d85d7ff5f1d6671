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
# # 04 · Carrying a calibration to a second unit
#
# Calibrating a unit (notebook 03) takes hundreds of frames under a reference force/torque sensor.
# A second unit of the same design differs from the first in the same ways the first differed
# from its drawing: its elastomer is a bit stiffer or softer, its camera a bit brighter, its
# gratings registered differently. Most of what calibration learned, though, is the *design*:
# how a load moves the fringes, how the contact lights up, what the physics leaves for the
# residual head.
#
# `transfer(fit_a_json, data_b, fit_b_json, max_frames=20)` starts from unit A's fitted device and
# refits, on at most 20 frames of unit B, only what varies from unit to unit (the `transfer` recipe of
# `moirejax/fits/recipes/transfer.json`: stiffness, glow gain, optical gain, with priors around A's values),
# keeping A's residual head. This notebook compares, on
# held-out mixed loads of unit B:
#
# 1. **no transfer**: unit A's calibration applied to unit B as it is;
# 2. **transfer**: A's calibration refitted on 20 frames of B;
# 3. **a learned baseline**: ridge regression from B's frames to the wrench (`ridge_baseline`),
#    trained from scratch on 20 frames of B (and, at full size, 100 and 500).
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
    dataset_reference,
    evaluate,
    format_metrics,
    load_recipe,
    ridge_baseline,
    simulate_dataset,
    transfer,
    WRENCH_AXES,
    wrench_metrics,
)


SMOKE = os.environ.get("MOIREJAX_SMOKE") == "1"
# Two units of the same design (different deviations, loads and noise): unit A (the unit of
# notebook 03) is softer than its design, unit B stiffer. Unit B's fringes fall in the same
# spectral bins as A's: the inversion's band windows are static, so the two units share the
# compiled inversion and calibration programs (a unit with another fringe period compiles its own).
SEED_A, SEED_B = 3, 43
TRANSFER_FRAMES = 10 if SMOKE else 20
# Unit A's calibration session. In smoke mode unit A is fitted with the transfer recipe's
# parameters on exactly as many frames as the transfer uses, so that both fits run the same
# compiled solver; at full size it gets the default recipe on a full session.
N_CALIBRATION_A = TRANSFER_FRAMES + 2 if SMOKE else 300
TRANSFER_RECIPE = load_recipe("transfer")  # moirejax/fits/recipes/transfer.json
RECIPE_A = (
    TRANSFER_RECIPE.replace(name="unit-smoke", rounds=1, parameter_frames=TRANSFER_FRAMES)
    if SMOKE
    else load_recipe("unit")
)
# Unit B: a pool of paper-protocol frames (the transfer takes 20 of them, the ridge baseline up to
# 500) and a held-out session of mixed loads.
RIDGE_SIZES = (TRANSFER_FRAMES,) if SMOKE else (TRANSFER_FRAMES, 100, 500)
N_POOL_B = TRANSFER_FRAMES + 2 if SMOKE else 510
N_HELDOUT_B = 8 if SMOKE else 60

work = Path(tempfile.mkdtemp(prefix="moirejax-04-"))  # datasets, device files and report PNGs
# In smoke mode the camera is 256 x 256 px at 8 px/mm: the same 32 mm field at half the resolution.
nominal = mj.preset("mid", height=256, width=256, px_per_mm=8.0) if SMOKE else mj.preset("mid")
nominal_json = work / "mid.json"
mj.save_device(nominal_json, nominal)
print(f"working folder {work}")
print(f"unit A: {N_CALIBRATION_A} calibration frames; unit B: pool of {N_POOL_B}, {N_HELDOUT_B} held out")
print(f"transfer recipe: {TRANSFER_RECIPE.to_json()}")

# %% [markdown]
# ## 1. Two units of one design
#
# As in notebook 03, `simulate_dataset` draws each unit around the nominal Mid design from its
# seed (`perturb_device`) and renders `high`-fidelity frames of it. Unit A gets a calibration
# session; unit B a pool of calibration-protocol frames and a held-out session of mixed loads.

# %%
start = time.perf_counter()
calibration_a = simulate_dataset(work / "unit_a", nominal, "paper", N_CALIBRATION_A, seed=SEED_A)
pool_b = simulate_dataset(work / "unit_b", nominal, "paper", N_POOL_B, seed=SEED_B)
heldout_b = simulate_dataset(work / "unit_b_heldout", nominal, "mixed", N_HELDOUT_B, seed=SEED_B)
print(f"simulated {N_CALIBRATION_A + N_POOL_B + N_HELDOUT_B} frames in {time.perf_counter() - start:.0f} s")
unit_a = mj.device_from_json(Dataset(calibration_a).true_device)
unit_b = mj.device_from_json(Dataset(pool_b).true_device)
assert Dataset(heldout_b).true_device == Dataset(pool_b).true_device, "same seed, same unit"


def period_mm(device):
    return float(2 * np.pi / np.linalg.norm(np.asarray(device.moire_wavevectors())[0]))


quantities = {
    "p1 (mm)": lambda d: float(d.p1),
    "p2 (mm)": lambda d: float(d.p2),
    "a (mm)": lambda d: float(d.a),
    "E (MPa)": lambda d: float(d.elastomer.E),
    "optical gain": lambda d: float(d.optics.gain),
    "background": lambda d: float(d.optics.background),
    "moiré period Λ (mm)": period_mm,
}
rows = ["| quantity | nominal | unit A | unit B |", "|---|---|---|---|"]
for label, get in quantities.items():
    n = get(nominal)
    rows.append(
        f"| {label} | {n:.4g} | {get(unit_a):.4g} ({100 * (get(unit_a) / n - 1):+.1f}%) "
        f"| {get(unit_b):.4g} ({100 * (get(unit_b) / n - 1):+.1f}%) |"
    )
display(Markdown("\n".join(rows)))
display(Image(filename=str(work / "unit_b_contact_sheet.png")))

# %% [markdown]
# ## 2. Calibrate unit A
#
# The full calibration of notebook 03: physical parameters and latent contacts, then the residual
# head (trained only from 50 usable frames or more, so not in smoke mode).

# %%
fit_a_json = work / "fit_a.json"
start = time.perf_counter()
summary_a = calibrate(nominal_json, calibration_a, fit_a_json, recipe=RECIPE_A, baseline_sizes=())
print(f"calibrated unit A in {time.perf_counter() - start:.0f} s")
for p in summary_a["parameters"]:
    print(
        f"  {p['parameter']:18s} nominal {p['nominal']:.4g} -> fitted {p['fitted']:.4g} ± {p['sd']:.2g}  true {p['true']:.4g}"
    )
print(f"residual head of unit A: {json.loads(fit_a_json.read_text())['calibration']['residual_head']}")

# %% [markdown]
# ## 3. Transfer to unit B with 20 frames
#
# `transfer` opens unit B's frames, takes its no-contact reference from the contact-free ones,
# picks at most `max_frames` frames in contact and runs the same alternating fit as calibration,
# starting from unit A's device, with the `transfer` recipe. The optical registration of B's gratings
# (phases) and its apparent upper pitch and angle come from B's own reference frame, as in every
# inversion; the refit adjusts stiffness and light. A's residual head is copied beside B's device.

# %%
fit_b_json = work / "fit_b.json"
start = time.perf_counter()
summary_b = transfer(fit_a_json, pool_b, fit_b_json, max_frames=TRANSFER_FRAMES)
print(f"transferred in {time.perf_counter() - start:.0f} s, on {summary_b['frames']} frames of unit B")
fit_a = mj.device_from_json(json.loads(fit_a_json.read_text()))
fit_b = mj.device_from_json(json.loads(fit_b_json.read_text()))
getters = {
    "elastomer.E": lambda d: float(d.elastomer.E),
    "optics.glow_gain": lambda d: float(d.optics.glow_gain),
    "optics.gain": lambda d: float(d.optics.gain),
}
rows = ["| parameter | unit A's fit | unit B's fit ± 1σ | unit B true |", "|---|---|---|---|"]
for name, get in getters.items():
    rows.append(
        f"| {name} | {get(fit_a):.4g} | {get(fit_b):.4g} ± {summary_b['uncertainty'][name]:.2g} | {get(unit_b):.4g} |"
    )
display(Markdown("\n".join(rows)))

# %% [markdown]
# ## 4. Unit B's held-out loads: no transfer, transfer, and a learned baseline
#
# Both device files are evaluated on B's held-out mixed loads with B's own reference frame.
# `evaluate` applies a residual head when the device file names one and then reports the physics
# alone under `physics_only`.

# %%
results = {}
results["unit A's fit, no transfer"] = evaluate(fit_a_json, heldout_b, work / "eval_no_transfer")
results[f"transfer, {summary_b['frames']} frames of B"] = evaluate(fit_b_json, heldout_b, work / "eval_transfer")
for label in list(results):
    if "physics_only" in results[label]:
        results[f"{label} (physics only)"] = results[label]["physics_only"]
for label, metrics in results.items():
    print(format_metrics(metrics, title=f"\n{label}"))

# %% [markdown]
# The learned baseline sees no physics: `ridge_baseline(train_frames, train_wrench, test_frames,
# reference)` downsamples `frame - reference` to 24 × 24 pixels and fits a ridge regression to the
# wrench, choosing the regularisation by leave-one-out. It is trained on the first $k$ in-contact
# frames of unit B's pool (the paper protocol cycles through its four load groups, so any $k$ sees
# all of them) and scored on the same held-out frames.

# %%
pool = Dataset(pool_b)
test = Dataset(heldout_b)
reference = dataset_reference(pool)
train_idx = np.flatnonzero(pool.contact)
test_idx = np.flatnonzero(test.contact)
test_frames = np.stack([test.frame(int(i)) for i in test_idx])
for k in RIDGE_SIZES:
    if k > len(train_idx):
        print(f"ridge on {k} frames: the pool has only {len(train_idx)}")
        continue
    train_frames = np.stack([pool.frame(int(i)) for i in train_idx[:k]])
    predicted = ridge_baseline(train_frames, pool.wrenches[train_idx[:k]], test_frames, reference)
    results[f"ridge baseline, {k} frames of B"] = wrench_metrics(test.wrenches[test_idx], predicted)
    print(format_metrics(results[f"ridge baseline, {k} frames of B"], title=f"\nridge baseline, {k} frames of B"))

# %% [markdown]
# ### Held-out R² on unit B
#
# R² of each axis on the same held-out frames (MAE beside it: N for forces, mN·m for torques).

# %%
header = "| method | " + " | ".join(WRENCH_AXES) + " |"
rows = [header, "|---|" + "---|" * len(WRENCH_AXES)]
for label, m in results.items():
    cells = []
    for axis in WRENCH_AXES:
        scale, unit = (1.0, "N") if axis.startswith("f") else (1e3, "mN·m")
        cells.append(f"{m['r2'][axis]:.3f} ({scale * m['mae'][axis]:.2g} {unit})")
    rows.append(f"| {label} | " + " | ".join(cells) + " |")
display(Markdown("\n".join(rows)))
print(f"held-out frames of unit B: {len(test_idx)}")

fig, ax = plt.subplots(figsize=(10, 3.8))
width = 0.8 / len(results)
for k, (label, m) in enumerate(results.items()):
    offset = (k - (len(results) - 1) / 2) * width
    ax.bar(np.arange(6) + offset, [max(m["r2"][a], -0.5) for a in WRENCH_AXES], width, label=label)
ax.set_xticks(np.arange(6), WRENCH_AXES)
ax.axhline(1.0, color="k", lw=0.8)
ax.set_ylim(-0.5, 1.05)
ax.set_ylabel("held-out R² on unit B (clipped at −0.5)")
ax.legend(fontsize=8, loc="lower right")
ax.grid(alpha=0.3, axis="y")
fig.tight_layout()
plt.show()

# %% [markdown]
# The parity plot of the transferred calibration on unit B's held-out loads:

# %%
display(Image(filename=str(work / "eval_transfer" / "parity.png")))

# %% [markdown]
# ## Reading the result
#
# The table is what this run measured, on one pair of simulated units; with the smoke sizes it
# only shows that the pieces run. What to look for at full size:
#
# - **No transfer against transfer.** Unit A's fit carries A's stiffness and optical gain. Where
#   B's differ (compare the true values in section 1), A's fit reads B's forces with the ratio of
#   the two stiffnesses; the refit on 20 frames is what removes that scale error.
# - **Physics against data.** Twenty frames can pin down three physical parameters, because every
#   frame constrains them through the whole model. The ridge regression has to learn the map from
#   a 576-pixel difference image to six wrench axes from the same twenty frames; see how many it
#   needs to catch up, and that it knows nothing about loads outside the protocol it was trained on
#   (it is scored on mixed loads here).
# - **Uncertainties** of the transferred parameters come from the 20 frames only, and like unit
#   A's they exclude model error: compare the fitted values with unit B's true ones.
#
# Notebook 05 runs a calibrated device live.
