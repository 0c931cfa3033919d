"""Comparison of a model's range of motion with in-vitro data (the seed's Technical Validation, Figures
10-11): our value in each reference's convention, the acceptance interval, the ALL's effect, the figure.
Degrees.  The analyses themselves: `spinecohort.rom.run` (sub-model `rom.submodel`, decks `rom.deck`,
kinematics `rom.kinematics`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from spinecohort.rom.deck import PLANES

# ----------------------------------------------------------------------------------------------------------
# comparison with in-vitro data


def model_value_deg(table: pd.DataFrame, segment: str, motion: str, side: str, mode: str) -> float:
    """Our ROM (deg) in a reference's convention: one load case, or a plane's full range (sum of both
    sides) / one-side mean.  NaN if the table lacks a needed load case."""
    rows = table[(table["segment"] == segment) & (table["mode"] == mode) & (table["variant"] == "intact")]
    if "load_fraction" in rows:  # a case stopped short of the full moment is not comparable
        rows = rows[rows["load_fraction"] >= 1.0 - 1e-6]
    by_case = dict(zip(rows["load_case"], rows["rom_deg"]))
    cases = PLANES.get(motion, (motion,))
    if any(c not in by_case for c in cases):
        return float("nan")
    vals = [by_case[c] for c in cases]
    if motion in PLANES:
        return float(sum(vals)) if side == "full" else float(np.mean(vals))
    if side == "full":
        raise ValueError(f"reference for {segment} {motion}: a single load case cannot be a full range")
    return float(vals[0])


def validate(
    table: pd.DataFrame, references: list[dict], moment_nmm: float, acceptance_sd: float = 2.0
) -> pd.DataFrame:
    """One row per reference and extraction mode that has its segment: our value, the accepted interval
    (mean +- acceptance_sd SD, or the range), in_range, and the distance from the mean/median (or the
    range's centre).  References at another moment are listed with in_range empty (not judged)."""

    rows = []
    for ref in references:
        for mode in ("lumbar", "unit"):
            if not ((table["segment"] == ref["segment"]) & (table["mode"] == mode)).any():
                continue
            ours = model_value_deg(table, ref["segment"], ref["motion"], ref["side"], mode)
            if ref["statistic"] == "mean_sd":
                centre = ref["value"]
                low, high = centre - acceptance_sd * ref["sd"], centre + acceptance_sd * ref["sd"]
            else:
                low, high = ref["low"], ref["high"]
                centre = ref.get("value", 0.5 * (low + high))
            same_moment = abs(ref["moment_nmm"] - moment_nmm) < 1e-6
            rows.append(
                {
                    "segment": ref["segment"],
                    "motion": ref["motion"],
                    "side": ref["side"],
                    "mode": mode,
                    "model_deg": round(ours, 3),
                    "ref_statistic": ref["statistic"],
                    "ref_value": ref.get("value"),
                    "ref_sd": ref.get("sd"),
                    "ref_low": ref.get("low"),
                    "ref_high": ref.get("high"),
                    "accept_low": round(low, 3),
                    "accept_high": round(high, 3),
                    "in_range": (bool(low <= ours <= high) if same_moment and np.isfinite(ours) else None),
                    "distance_deg": round(ours - centre, 3),
                    "ref_moment_nmm": ref["moment_nmm"],
                    "source": ref["source"],
                }
            )
    return pd.DataFrame(rows)


def all_effect(table: pd.DataFrame) -> pd.DataFrame:
    """Extension ROM with and without the ALL per segment (deg) and the increase without it."""
    ext = table[table["load_case"] == "extension"]
    if "no_ALL" not in set(ext["variant"]):
        return ext.iloc[0:0]
    wide = ext.pivot_table(index=["mode", "unit", "segment"], columns="variant", values="rom_deg").reset_index()
    wide["increase_deg"] = wide["no_ALL"] - wide["intact"]
    return wide


def validation_figure(validation: pd.DataFrame, path: str | Path, title: str = "") -> Path:
    """The seed's Figures 10-11 for our model: ROM bars, in-vitro mean +- SD or range as whiskers; one
    panel per extraction mode."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    modes = [m for m in ("lumbar", "unit") if (validation["mode"] == m).any()]
    fig, axes = plt.subplots(
        len(modes), 1, figsize=(max(6, 0.6 * len(validation) + 3), 3.6 * len(modes)), squeeze=False
    )
    for ax, mode in zip(axes[:, 0], modes):
        v = validation[validation["mode"] == mode].reset_index(drop=True)
        x = np.arange(len(v))
        colors = ["tab:green" if r is True else ("tab:red" if r is False else "tab:gray") for r in v["in_range"]]
        ax.bar(x, v["model_deg"], color=colors, alpha=0.7, label="model (green: in range, red: out)")
        centre = np.where(
            v["ref_statistic"] == "mean_sd",
            v["ref_value"],
            0.5 * (v["ref_low"].astype(float) + v["ref_high"].astype(float)),
        )
        lo = np.where(v["ref_statistic"] == "mean_sd", v["ref_value"] - v["ref_sd"], v["ref_low"].astype(float))
        hi = np.where(v["ref_statistic"] == "mean_sd", v["ref_value"] + v["ref_sd"], v["ref_high"].astype(float))
        ax.errorbar(
            x + 0.25,
            centre,
            yerr=[centre - lo, hi - centre],
            fmt="o",
            color="k",
            capsize=4,
            label="in vitro: mean +- SD / range",
        )
        ax.set_xticks(
            x,
            [f"{s}\n{m.replace('_', ' ')}\n({sd})" for s, m, sd in zip(v["segment"], v["motion"], v["side"])],
            fontsize=7,
        )
        ax.set_ylabel("ROM (deg)")
        ax.set_title(f"{title} {'lumbar model (pelvis..T10)' if mode == 'lumbar' else 'functional units'}".strip())
        ax.legend(fontsize=7, loc="upper left")  # the right end holds the tallest bars (axial rotation)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return Path(path)
