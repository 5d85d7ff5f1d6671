"""Design tables and design maps: what a pitch pair, angle and stack give as a sensor."""

import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from .._plotting import pyplot, save_figure
from ..physics import (
    Device,
    effective_mismatch_exact,
    effective_mismatch_first_order,
    geometric_amplification,
    moire_orientation,
    moire_period_exact,
    object_mismatch,
    preset,
    PRESET_PITCHES,
    shear_amplification,
)


DESIGN_PARAMETERS = ("p1", "p2", "delta_alpha", "a", "Z")


def _design_vector(device: Device) -> jax.Array:
    return jnp.stack([device.p1, device.p2, device.alpha1 - device.alpha2, device.a, device.Z])


def _period_and_amplification(x: jax.Array) -> jax.Array:
    p1, p2, delta_alpha, a, Z = x
    return jnp.stack(
        [moire_period_exact(p1, p2, delta_alpha, a, Z), geometric_amplification(p1, p2, delta_alpha, a, Z)]
    )


def check_design(device: Device) -> None:
    """Raise `ValueError` for a design that shows no usable fringes."""
    period = float(moire_period_exact(device.p1, device.p2, device.alpha1 - device.alpha2, device.a, device.Z))
    if not math.isfinite(period) or period > 1e6:
        raise ValueError(
            "the apparent pitches are equal and the gratings aligned: the moire period is infinite "
            f"(p1*Z/(Z+a) = {float(device.p1 * device.Z / (device.Z + device.a)):.4g} mm = p2). "
            "Change a pitch, the angle or a/Z."
        )


def design_table(device: Device) -> dict[str, Any]:
    """Geometry and sensitivity figures of a design, as plain Python numbers.

    Both the paper's first-order model (Eq. 7) and the exact parallax model are given;
    `differences` says where they part. Derivatives of the exact period Λ and of the
    amplification A are taken with `jax.jacfwd` with respect to p1, p2, Δα, a and Z.
    """
    check_design(device)
    x = _design_vector(device)
    p1, p2, delta_alpha, a, Z = (float(v) for v in x)
    period, amplification = (float(v) for v in _period_and_amplification(x))
    jac = np.asarray(jax.jacfwd(_period_and_amplification)(x))
    d_eff_first = float(effective_mismatch_first_order(p1, p2, a, Z))
    d_eff_exact = float(effective_mismatch_exact(p1, p2, a, Z))
    p_mean = (p1 + p2) / 2
    period_first = p_mean / d_eff_first if d_eff_first > 0 else math.inf
    K = np.asarray(device.moire_wavevectors())
    fov_h, fov_w = device.field_of_view
    families = []
    for f, Kf in enumerate(K):
        lam = 2 * math.pi / float(np.linalg.norm(Kf))
        theta = float(moire_orientation(jnp.asarray(Kf)))
        # Fringes crossed along the direction of K over the rectified field.
        extent = abs(math.cos(theta)) * fov_w + abs(math.sin(theta)) * fov_h
        families.append(
            {"family": f, "period_mm": lam, "theta_deg": math.degrees(theta), "fringes_across_field": extent / lam}
        )
    table = {
        "p1_mm": p1,
        "p2_mm": p2,
        "delta_alpha_deg": math.degrees(delta_alpha),
        "a_mm": a,
        "Z_mm": Z,
        "a_over_Z": a / Z,
        "layout": device.layout,
        "delta_obj": float(object_mismatch(p1, p2)),
        "delta_eff_first_order": d_eff_first,
        "delta_eff_exact": d_eff_exact,
        "period_mm_exact": period,
        "period_mm_first_order": period_first,
        "amplification_A": amplification,
        "amplification_A_first_order": 1 / d_eff_first if d_eff_first > 0 else math.inf,
        "shear_amplification": float(shear_amplification(p1, p2, delta_alpha, a, Z)),
        "families": families,
        "dperiod": {name: float(jac[0, i]) for i, name in enumerate(DESIGN_PARAMETERS)},
        "damplification": {name: float(jac[1, i]) for i, name in enumerate(DESIGN_PARAMETERS)},
        "differences": (
            f"first-order delta_eff = |delta_obj - a/Z| = {d_eff_first:.3f} uses object pitches; "
            f"the exact projection p1' = p1 Z/(Z+a) gives delta_eff = {d_eff_exact:.3f}, "
            f"period {period:.3f} mm against {period_first:.3f} mm first order "
            f"({100 * (period_first - period) / period:+.1f}%)."
        ),
    }
    return table


def format_design_table(table: dict[str, Any]) -> str:
    """Human-readable rendering of [`design_table`][]."""
    lines = [
        f"design  p1={table['p1_mm']:.4g} mm  p2={table['p2_mm']:.4g} mm  dalpha={table['delta_alpha_deg']:.3g} deg  "
        f"a={table['a_mm']:.4g} mm  Z={table['Z_mm']:.4g} mm  (a/Z={table['a_over_Z']:.3f}, {table['layout']})",
        f"  delta_obj                   {table['delta_obj']:+.4f}",
        f"  delta_eff  first order      {table['delta_eff_first_order']:.4f}   (Eq. 7, |delta_obj - a/Z|)",
        f"  delta_eff  exact parallax   {table['delta_eff_exact']:.4f}   (p1' = p1 Z/(Z+a))",
        f"  period     exact            {table['period_mm_exact']:.4f} mm",
        f"  period     first order      {table['period_mm_first_order']:.4f} mm",
        f"  amplification A             {table['amplification_A']:.2f}   (paper's A = Lambda/p2, exact)",
        f"  amplification first order   {table['amplification_A_first_order']:.2f}   (1/delta_eff)",
        f"  shear amplification         {table['shear_amplification']:.2f}   (fringe shift per surface shift)",
    ]
    for fam in table["families"]:
        lines.append(
            f"  family {fam['family']}: Lambda={fam['period_mm']:.3f} mm  theta={fam['theta_deg']:+.2f} deg  "
            f"{fam['fringes_across_field']:.1f} fringes across the field"
        )
    lines.append("  derivatives            " + "  ".join(f"{n:>12s}" for n in DESIGN_PARAMETERS))
    lines.append("  dLambda/d (mm per unit)" + "  ".join(f"{table['dperiod'][n]:12.4g}" for n in DESIGN_PARAMETERS))
    lines.append(
        "  dA/d (per unit)        " + "  ".join(f"{table['damplification'][n]:12.4g}" for n in DESIGN_PARAMETERS)
    )
    for key in ("force_sensitivity", "observability"):
        if key in table:
            lines.append(f"  {key.replace('_', ' ')}:")
            for name, value in table[key].items():
                lines.append(f"    {name:32s} {value:.4g}" if isinstance(value, float) else f"    {name:32s} {value}")
    if "optimisation" in table:
        lines.extend(_format_optimisation(table["optimisation"]))
    lines.append("  note: " + table["differences"])
    return "\n".join(lines)


def _format_optimisation(report: dict[str, Any]) -> list[str]:
    """The start and the optimum of [`optimise_design`][] side by side."""
    start, best = report["start"], report["optimum"]
    rows = [
        ("p1 (mm)", "p1_mm"),
        ("p2 (mm)", "p2_mm"),
        ("delta alpha (deg)", "delta_alpha_deg"),
        ("a (mm)", "a_mm"),
        ("duty 1", "duty1"),
        ("duty 2", "duty2"),
        ("moire period (mm)", "period_mm"),
        ("stray-beat clearance", "stray_beat_clearance"),
    ]
    lines = [
        f"  optimisation ({report['steps']} steps, {report['seconds']:.0f} s):",
        f"    {'':32s} {'start':>12s} {'optimum':>12s}",
    ]
    lines += [f"    {label:32s} {start[key]:12.4g} {best[key]:12.4g}" for label, key in rows]
    for axis in start["rel_crb"]:
        label = f"CRB/range {axis} ({report['estimator']})"
        lines.append(f"    {label:32s} {start['rel_crb'][axis]:12.3e} {best['rel_crb'][axis]:12.3e}")
    lines.append(f"    {'worst axis':32s} {start['worst_axis']:>12s} {best['worst_axis']:>12s}")
    lines.append(
        f"    {'twist phase range (rad)':32s} {start['phase_range_rad']['tz']:12.3g} {best['phase_range_rad']['tz']:12.3g}"
    )
    lines.append(f"    {'within limits':32s} {start['within_limits']!s:>12s} {best['within_limits']!s:>12s}")
    lines.append(
        f"    worst-axis bound, optimum / start: {best['worst_rel_crb'] / start['worst_rel_crb']:.3f}"
        + ("" if report["feasible"] else " (no iterate met the limits: the last one is shown)")
    )
    other = "pixels" if report["estimator"] == "bands" else "bands"
    lines.append(
        f"    worst-axis bound of the {other} estimator, optimum / start: "
        f"{best['worst_rel_crb_' + other] / start['worst_rel_crb_' + other]:.3f}"
    )
    lines.append("    " + report["estimator_note"])
    return lines


def plot_design_maps(path, device: Device | None = None) -> None:
    """Λ and A over a p1 x p2 grid and over Δα, with the paper's presets marked; PNG."""
    plt = pyplot()
    base = device if device is not None else preset("mid")
    a, Z = float(base.a), float(base.Z)
    pitches = np.linspace(0.15, 0.45, 181)
    P1, P2 = np.meshgrid(pitches, pitches, indexing="xy")
    period = np.asarray(moire_period_exact(P1, P2, 0.0, a, Z))
    amplification = np.asarray(geometric_amplification(P1, P2, 0.0, a, Z))
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.5))
    for ax, field, title in (
        (axes[0], np.log10(np.clip(period, 1e-3, 1e3)), "log10 moire period (mm), aligned gratings"),
        (axes[1], np.log10(np.clip(amplification, 1e-3, 1e4)), "log10 amplification A"),
    ):
        im = ax.pcolormesh(P1, P2, field, shading="auto", cmap="viridis")
        fig.colorbar(im, ax=ax)
        ax.set_xlabel("p1, upper grating (mm)")
        ax.set_ylabel("p2, reference grating (mm)")
        ax.set_title(title, fontsize=10)
        ax.plot(pitches, pitches * Z / (Z + a), "w--", lw=1, label="p1' = p2 (infinite period)")
        for name, (q1, q2) in PRESET_PITCHES.items():
            ax.plot(q1, q2, "r*", ms=12)
            ax.annotate(name, (q1, q2), color="w", xytext=(4, 4), textcoords="offset points")
        ax.plot(float(base.p1), float(base.p2), "c+", ms=14, mew=2)
        ax.legend(loc="lower right", fontsize=8)
    angles = np.linspace(-5, 5, 401)
    ax = axes[2]
    for name, (q1, q2) in PRESET_PITCHES.items():
        ax.semilogy(
            angles, np.asarray(moire_period_exact(q1, q2, np.radians(angles), a, Z)), label=f"{name} Lambda (mm)"
        )
    ax.set_xlabel("delta alpha (deg)")
    ax.set_ylabel("moire period (mm)")
    ax.set_title(f"period against angle, a/Z = {a / Z:.2f}", fontsize=10)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    save_figure(fig, path)
