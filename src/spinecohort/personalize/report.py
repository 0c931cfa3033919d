"""The personalization report: parameter errors per method, shape distances, Jacobian checks, run times."""

from __future__ import annotations

import numpy as np
import pandas as pd

from spinecohort.measure.spinopelvic import UNITS


def error_summary(table: pd.DataFrame, parameters: list[str]) -> pd.DataFrame:
    """Per method and parameter: mean |error|, max |error| (unit of the parameter) and the bias."""
    rows = []
    for method, g in table.groupby("method", sort=False):
        for p in parameters:
            e = g[f"{p}_error"].to_numpy(float)
            e = e[np.isfinite(e)]
            rows.append(
                {
                    "method": method,
                    "parameter": p,
                    "unit": UNITS.get(p, ""),
                    "n": len(e),
                    "mean_abs_error": np.abs(e).mean(),
                    "max_abs_error": np.abs(e).max(),
                    "bias": e.mean(),
                }
            )
    return pd.DataFrame(rows)


def report_markdown(table: pd.DataFrame, info: dict) -> str:
    """The personalization report: error table per method, shape distances, Jacobian checks, run times."""
    params = info["parameters"]
    summ = error_summary(table, params)
    lines = [
        f"# Personalization report ({info['n_patients']} patients, {info['n_modes']} modes)",
        "",
        f"Fitted parameters: {', '.join(params)}; posture (sagittal rotation) box "
        f"±{info['posture_deg']:g} deg.  Errors are achieved - target, targets measured on each patient's "
        "own mesh.",
        "",
        "## Parameter error (mean / max |achieved - target|)",
        "",
        "| parameter | unit | fit mean | fit max | projection mean | projection max | aligned shape mean | "
        "aligned shape max |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for p in params:
        f = summ[(summ.method == "fit") & (summ.parameter == p)].iloc[0]
        q = summ[(summ.method == "projection") & (summ.parameter == p)].iloc[0]
        lines.append(
            f"| {p} | {UNITS.get(p, '')} | {f.mean_abs_error:.3f} | {f.max_abs_error:.3f} | "
            f"{q.mean_abs_error:.3f} | {q.max_abs_error:.3f} | "
            f"{info['aligned_shape_error_mean_abs'][p]:.3f} | {info['aligned_shape_error_max_abs'][p]:.3f} |"
        )
    lines += [
        "",
        "The aligned-shape columns measure each patient's own GPA-aligned shape (every mode, no fit): "
        "what any model in the SSM frame inherits from the alignment (GPA removes posture, so PT and SS "
        "change; PI and LL do not).",
        "",
        "## Shape distance to the patient's aligned shape (mm)",
        "",
        "Per-vertex distance between corresponding vertices after a rigid superposition (shape only); "
        "in brackets as placed in the SSM frame.",
        "",
        "| method | mean of means | max of means | max of maxima | weights at ±bound |",
        "|---|---|---|---|---|",
    ]
    for method, g in table.groupby("method", sort=False):
        lines.append(
            f"| {method} | {g.dist_mean_mm.mean():.2f} ({g.dist_placed_mean_mm.mean():.2f}) | "
            f"{g.dist_mean_mm.max():.2f} | {g.dist_max_mm.max():.2f} ({g.dist_placed_max_mm.max():.2f}) | "
            f"{int(g.at_bound.sum())} |"
        )
    fit = table[table.method == "fit"]
    if "invalid_before" in fit:
        lines += [
            "",
            "## Hexahedral models (fit method, `personalized/<ID>.inp`)",
            "",
            f"{len(fit)} models; inverted hexes before repair in {int((fit.invalid_before > 0).sum())} "
            f"(total {int(fit.invalid_before.sum())}), after repair {int(fit.invalid_after.sum())}; "
            f"min scaled Jacobian after repair {fit.min_sj_after.min():.3f}.",
        ]
    sur = info["surrogate_rms_error"]
    lines += [
        "",
        "## Run",
        "",
        f"Surrogate (quadratic, held-out RMS error: {', '.join(f'{p} {e:.3f}' for p, e in sur.items())}) "
        f"{info['surrogate_s']:.1f} s; fits {info['fit_s']:.1f} s "
        f"({info['fit_s'] / max(info['n_patients'], 1):.2f} s per patient, "
        f"{fit.evaluations.mean():.0f} models measured each); projections {info['projection_s']:.2f} s.",
        "",
        "## Pros and cons, in numbers",
        "",
        f"- fit: parameters within {summ[summ.method == 'fit'].max_abs_error.max():.3f} (max over "
        f"parameters and patients), needs only the parameters (radiographs), but the shape is the most "
        f"probable one for them: {fit.dist_mean_mm.mean():.1f} mm mean distance to the patient.",
        f"- projection: shape {table[table.method == 'projection'].dist_mean_mm.mean():.1f} mm mean "
        f"distance, needs the patient's 3-D shape; parameters off by up to "
        f"{summ[summ.method == 'projection'].max_abs_error.max():.1f} (modes truncated, GPA posture).",
        "",
    ]
    return "\n".join(lines)
