"""`moirejax demo`: the product end to end on an embedded default, no hardware, no downloads.

1. the design table of the paper's three designs and the design maps;
2. a simulated calibration session (`paper` protocol) of a `high`-fidelity unit of the
   Mid design whose true parameters deviate from nominal, unknown to everything after;
3. calibration of that unit (physical parameters, then the residual head);
4. inversion of a held-out `mixed` set of the same unit, before and after calibration,
   with per-axis R² and MAE beside the paper's figures, and the speed.
"""

import time
from pathlib import Path

from .._conventions import WRENCH_AXES
from ..design import design_table, format_design_table, plot_design_maps
from ..physics import preset, save_device


PAPER_R2 = {"fx": 0.99, "fy": 0.99, "fz": 0.992, "tx": 0.98, "ty": 0.98, "tz": 0.999}


def run_demo(out: str = "moirejax-demo", *, smoke: bool = False) -> int:
    """Run the demo into folder `out`; `smoke` shrinks every size (for tests)."""
    from ..calibration import (
        calibrate,
        dataset_reference,
        evaluate,
        heldout_ridge_r2,
        load_calibrated,
        load_recipe,
    )
    from ..data import Dataset
    from ..inverse import invert, Inverter
    from ..simulate import simulate_dataset

    start = time.perf_counter()
    out_dir = Path(out)
    out_dir.mkdir(parents=True, exist_ok=True)
    tables = {name: design_table(preset(name)) for name in ("dense", "mid", "sparse")}
    print(format_design_table(tables["mid"]))
    print(
        "paper: A = 4.00 / 14.00 / 24.00, delta_eff = 0.25 / 0.10 / 0.07 (Dense / Mid / Sparse); here: A = "
        + " / ".join(f"{t['amplification_A']:.2f}" for t in tables.values())
        + ", delta_eff = "
        + " / ".join(f"{t['delta_eff_first_order']:.2f}" for t in tables.values())
    )
    plot_design_maps(out_dir / "design_maps.png")

    n_cal, n_test = (16, 8) if smoke else (120, 40)
    # The smoke run keeps Mid's 32 mm field on a 256 x 256 px camera.
    nominal = preset("mid", height=256, width=256, px_per_mm=8.0) if smoke else preset("mid")
    save_device(out_dir / "mid.json", nominal)
    print(
        f"\nsimulating a high-fidelity Mid unit: {n_cal} calibration frames (paper protocol), {n_test} held-out mixed frames"
    )
    seed = 3
    simulate_dataset(out_dir / "calibration", nominal, "paper", n_cal, seed=seed, overwrite=True)
    simulate_dataset(out_dir / "heldout", nominal, "mixed", n_test, seed=seed, overwrite=True)

    print("\nbefore calibration (nominal design, the unit's own reference frame):")
    before = evaluate(out_dir / "mid.json", out_dir / "heldout", out_dir / "before")
    recipe = load_recipe("unit").replace(rounds=2, parameter_frames=32)
    if smoke:
        # The smoke sizes of notebook 03, whose compiled programs a test run then shares.
        recipe = recipe.replace(rounds=1, parameter_frames=8, parameter_steps=4, latent_steps=8)
    summary = calibrate(
        out_dir / "mid.json", out_dir / "calibration", out_dir / "fit.json", recipe=recipe, baseline_sizes=()
    )
    after = evaluate(out_dir / "fit.json", out_dir / "heldout", out_dir / "after")
    ridge = heldout_ridge_r2(out_dir / "calibration", out_dir / "heldout", (8 if smoke else 20, n_cal))
    # Speed once compiled: the held-out loads are unrelated to each other, so every frame is
    # a cold solve; a stream (warm start from the last frame) is several times faster.
    heldout = Dataset(out_dir / "heldout")
    device, _ = load_calibrated(out_dir / "fit.json")
    inverter = Inverter(device, reference=dataset_reference(heldout))
    frames = [heldout.frame(i) for i in range(min(3 if smoke else 12, len(heldout)))]
    invert(inverter, frames[:1])
    t0 = time.perf_counter()
    invert(inverter, frames)
    cold_ms = (time.perf_counter() - t0) / len(frames) * 1e3

    sizes = " / ".join(ridge)
    print(f"\nheld-out mixed loads of the simulated unit (R2 / MAE); ridge: learned baseline on {sizes} frames")
    print("axis   before calibration        after calibration         ridge R2              paper R2")
    for axis in WRENCH_AXES:
        unit = "N" if axis.startswith("f") else "N·m"
        ridge_r2 = " / ".join(f"{r2[axis]:7.3f}" for r2 in ridge.values())
        print(
            f"{axis:5s}  {before['r2'][axis]:7.3f} / {before['mae'][axis]:8.2g} {unit:4s}   "
            f"{after['r2'][axis]:7.3f} / {after['mae'][axis]:8.2g} {unit:4s}   {ridge_r2:20s}  {PAPER_R2[axis]:.3f}"
        )
    print(
        f"speed: {cold_ms:.0f} ms per independent frame (cold solve, compiled); a stream warm-starts from the"
        " previous frame: benchmarks/invert_speed.py"
    )
    print(
        f"\nplots: {out_dir / 'after' / 'parity.png'}, {out_dir / 'design_maps.png'}, {summary['report']}/parameters.png"
    )
    print(f"total {time.perf_counter() - start:.0f} s")
    return 0
