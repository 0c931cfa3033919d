"""Figures of the virtual cohort: its spinopelvic parameters against the patients' with the inclusion
thresholds, and its mesh quality before and after repair with the mean model's Table 3."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from spinecohort.figures.canvas import canvas, save

CRITERIA_COLUMNS: dict[str, str] = {"PI_minus_LL_min_deg": "PI_minus_LL", "PT_min_deg": "PT", "SVA_T1_min_mm": "SVA_T1"}

PARAMETER_LABELS: dict[str, str] = {
    "PI": "pelvic incidence PI",
    "PT": "pelvic tilt PT",
    "SS": "sacral slope SS",
    "LL": "lumbar lordosis LL (L1-S1)",
    "LL_L4S1": "lower lumbar lordosis L4-S1",
    "LL_L1L5": "lordosis L1-L5",
    "PI_minus_LL": "PI - LL mismatch",
    "TPA": "T1 pelvic angle TPA",
    "T1SPI": "T1 spinopelvic inclination",
    "GT": "global tilt GT",
    "TK_T1T12": "kyphosis T1-T12",
    "TK_T4T12": "thoracic kyphosis T4-T12",
    "TK_T5T12": "kyphosis T5-T12",
    "Cobb": "main coronal Cobb angle",
    "SVA_T1": "T1 sagittal offset (SVA proxy)",
    "SVA_C7est": "SVA, C7 estimated",
    "RPV": "relative pelvic version RPV",
    "RLL": "relative lumbar lordosis RLL",
    "RSA": "relative spinopelvic alignment RSA",
    "LDI": "lordosis distribution index LDI",
    "GAP_assumed_age": "GAP score (assumed age)",
    "GAP_noage": "GAP score without age",
}


def parameter_histograms_figure(
    virtual: pd.DataFrame,
    patients: pd.DataFrame,
    criteria: dict[str, float],
    parameters: list[str],
    path: str | Path,
    size_px: tuple[int, int] = (2000, 1400),
    dpi: int = 150,
    units: dict[str, str] | None = None,
) -> pd.DataFrame:
    """Histogram per parameter of the virtual cohort (density) with the patients' histogram overlaid and the
    inclusion thresholds (``criteria``: keys of ``CRITERIA_COLUMNS``, lower bounds) marked.

    virtual, patients: parameter tables (column names as in ``measure``, e.g. ``PI``, ``PI_minus_LL``).
    Returns the share (%) of virtual models and patients above each threshold (one row per criterion)."""
    from spinecohort.measure.spinopelvic import UNITS

    units = UNITS if units is None else units
    for name, table in (("virtual cohort", virtual), ("patients", patients)):
        missing = [p for p in parameters if p not in table.columns]
        if missing:
            raise ValueError(f"the {name} table has no column(s) {missing}")
    unknown = set(criteria) - set(CRITERIA_COLUMNS)
    if unknown:
        raise ValueError(f"unknown inclusion criteria {sorted(unknown)}; known: {sorted(CRITERIA_COLUMNS)}")
    thresholds = {CRITERIA_COLUMNS[k]: float(v) for k, v in criteria.items()}
    n = len(parameters)
    ncols = 4 if n > 9 else 3 if n > 4 else n
    nrows = int(np.ceil(n / ncols))
    fig = canvas(size_px, dpi)
    axes = np.atleast_1d(fig.subplots(nrows, ncols, squeeze=False)).ravel()
    shares = []
    for ax, p in zip(axes, parameters):
        v = virtual[p].to_numpy(float)
        q = patients[p].to_numpy(float)
        v, q = v[np.isfinite(v)], q[np.isfinite(q)]
        both = np.concatenate([v, q])
        lo, hi = (both.min(), both.max()) if both.size else (0.0, 1.0)
        if p in thresholds:
            lo, hi = min(lo, thresholds[p]), max(hi, thresholds[p])
        pad = 0.03 * (hi - lo or 1.0)
        edges = np.linspace(lo - pad, hi + pad, 41)
        ax.hist(v, bins=edges, density=True, color="#8fb3d9", label=f"virtual models (n = {v.size:,})")
        ax.hist(
            q, bins=edges[::4], density=True, histtype="step", color="#1f2d3d", lw=1.6, label=f"patients (n = {q.size})"
        )
        unit = units.get(p, "")
        if p in thresholds:
            t = thresholds[p]
            ax.axvspan(edges[0], t, color="#c0392b", alpha=0.08, lw=0)
            ax.axvline(t, color="#c0392b", ls="--", lw=1.4)
            sv, sq = 100 * np.mean(v > t) if v.size else np.nan, 100 * np.mean(q > t) if q.size else np.nan
            shares.append(
                {"parameter": p, "threshold": t, "unit": unit, "pct_virtual_above": sv, "pct_patients_above": sq}
            )
            ax.set_title(
                f"inclusion > {t:g} {unit}: virtual {sv:.0f} %, patients {sq:.0f} %", fontsize=8, color="#c0392b"
            )
        ax.set_xlim(edges[0], edges[-1])
        ax.set_xlabel(f"{PARAMETER_LABELS.get(p, p)} [{unit}]" if unit else PARAMETER_LABELS.get(p, p), fontsize=8)
        ax.set_ylabel(f"density [1/{unit}]" if unit else "density", fontsize=8)
        ax.tick_params(labelsize=7)
    for ax in axes[n:]:
        ax.set_visible(False)
    handles, labels = axes[0].get_legend_handles_labels()
    from matplotlib.patches import Patch

    handles.append(Patch(facecolor="#c0392b", alpha=0.25, label="excluded by an inclusion criterion"))
    fig.legend(handles=handles, loc="lower center", ncol=3, fontsize=8, frameon=False)
    all_in = np.ones(len(virtual), bool)
    for p, t in thresholds.items():
        all_in &= virtual[p].to_numpy(float) > t
    crit = ", ".join(f"{p.replace('_minus_', ' - ')} > {t:g} {units.get(p, '')}" for p, t in thresholds.items())
    fig.suptitle(
        f"Spinopelvic parameters of the virtual cohort and the patients\n"
        f"{100 * all_in.mean():.1f} % of the virtual models meet every inclusion criterion ({crit})",
        fontsize=11,
    )
    fig.tight_layout(rect=(0, 0.04, 1, 0.95))
    save(fig, path)
    return pd.DataFrame(shares)


# ----------------------------------------------------------------------------------------------------------
# Mesh-quality summary of the virtual cohort and the mean model


def quality_summary_figure(
    quality: pd.DataFrame,
    table3: pd.DataFrame,
    path: str | Path,
    size_px: tuple[int, int] = (1800, 1300),
    dpi: int = 150,
) -> None:
    """Four panels: the per-model minimum scaled Jacobian before and after repair; its distribution per
    tissue (after repair); the share of models with inverted hexes before repair, repaired, and left; and the
    seed's Table 3 indicators of the mean model per tissue.

    quality: the shards' quality tables concatenated (``min_sj_before``, ``min_sj_after``, ``invalid_before``,
    ``invalid_after``, ``repaired``, ``min_sj_<tissue>``).  table3: ``results/template/mean_quality.csv``."""
    need = {"min_sj_before", "min_sj_after", "invalid_before", "invalid_after", "repaired"}
    if need - set(quality.columns):
        raise ValueError(f"the quality table lacks columns {sorted(need - set(quality.columns))}")
    need3 = {
        "part",
        "pct_errors",
        "pct_warnings",
        "pct_edge_ratio_gt_10",
        "pct_max_face_angle_gt_160",
        "nodal_jacobian_ratio_min",
    }
    if need3 - set(table3.columns):
        raise ValueError(f"the Table 3 summary lacks columns {sorted(need3 - set(table3.columns))}")
    n = len(quality)
    fig = canvas(size_px, dpi)
    (a, b), (c, d) = fig.subplots(2, 2)

    lo = min(quality["min_sj_before"].min(), quality["min_sj_after"].min(), 0.0)
    edges = np.linspace(lo - 0.02, 1.0, 52)
    a.hist(quality["min_sj_before"], bins=edges, color="#8fb3d9", label="before repair")
    a.hist(quality["min_sj_after"], bins=edges, histtype="step", color="#1f2d3d", lw=1.5, label="after repair")
    a.axvline(0.0, color="#c0392b", lw=1.2, label="inverted (<= 0)")
    a.axvline(0.2, color="#e67e22", ls="--", lw=1.2, label="warning (< 0.2)")
    a.set_xlabel("minimum scaled Jacobian of a model [-]")
    a.set_ylabel("models")
    a.set_title(f"Worst element per model (n = {n:,} models)", fontsize=10)
    a.legend(fontsize=7)

    tissue_cols = [col for col in quality.columns if col.startswith("min_sj_") and col not in need]
    if tissue_cols:
        b.boxplot(
            [quality[col].dropna().to_numpy() for col in tissue_cols],
            whis=(0, 100),
            tick_labels=[col[len("min_sj_") :] for col in tissue_cols],
        )
        b.axhline(0.0, color="#c0392b", lw=1.2)
        b.axhline(0.2, color="#e67e22", ls="--", lw=1.2)
    b.set_xlabel("tissue")
    b.set_ylabel("minimum scaled Jacobian per model [-]")
    b.set_title("Worst element per model and tissue (after repair; whiskers: min-max)", fontsize=10)

    before = int((quality["invalid_before"] > 0).sum())
    repaired = int(((quality["invalid_before"] > 0) & (quality["invalid_after"] == 0)).sum())
    left = int((quality["invalid_after"] > 0).sum())
    counts = [before, repaired, left]
    bars = c.bar(
        ["inverted hexes\nbefore repair", "repaired", "inverted hexes\nafter repair"],
        [100 * k / max(n, 1) for k in counts],
        color=["#8fb3d9", "#2ca25f", "#c0392b"],
    )
    for bar, k in zip(bars, counts):
        c.text(
            bar.get_x() + bar.get_width() / 2,
            bar.get_height(),
            f"{k:,} model{'s' if k != 1 else ''}",
            ha="center",
            va="bottom",
            fontsize=8,
        )
    n_before, n_after = int(quality["invalid_before"].sum()), int(quality["invalid_after"].sum())
    left_txt = (
        f"inverted hexes: {n_before:,} before, {n_after:,} after repair" if n_before else "no inverted hex in any model"
    )
    c.set_ylabel("share of the virtual models [%]")
    c.set_ylim(0, max(1.0, 1.25 * max(100 * k / max(n, 1) for k in counts)))
    c.set_title(f"Models with inverted hexes ({left_txt})", fontsize=10)

    t3 = table3.set_index("part")
    cols = [
        ("pct_errors", "errors (sJ <= 0)"),
        ("pct_warnings", "warnings (sJ < 0.2 or face angle)"),
        ("pct_edge_ratio_gt_10", "edge ratio > 10"),
        ("pct_max_face_angle_gt_160", "face angle > 160 deg"),
    ]
    x = np.arange(len(t3))
    width = 0.8 / len(cols)
    for k, (col, label) in enumerate(cols):
        bars = d.bar(x + (k - (len(cols) - 1) / 2) * width, t3[col], width, label=label)
        d.bar_label(bars, fmt="%.1f", fontsize=6)
    d.set_xticks(x, [f"{p}\n(Jr min {t3.loc[p, 'nodal_jacobian_ratio_min']:.2f})" for p in t3.index], fontsize=8)
    d.set_ylabel("share of elements [%]")
    d.set_title("Table 3 indicators of the hex mean model per tissue (Jr: nodal Jacobian ratio)", fontsize=10)
    d.legend(fontsize=7)
    for ax in (a, b, c, d):
        ax.grid(alpha=0.3, axis="y")
        ax.tick_params(labelsize=8)
    fig.suptitle("Hexahedral mesh quality of the virtual cohort", fontsize=12)
    fig.tight_layout(rect=(0, 0, 1, 0.96))
    save(fig, path)
