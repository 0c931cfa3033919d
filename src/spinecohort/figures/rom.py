"""Figures of the range-of-motion analyses: validation against in-vitro ranges, ROM per shape mode, and the
sensitivity to the material parameters."""

from __future__ import annotations

from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
import pandas as pd


def validation_figure(validation: pd.DataFrame, path: str | Path, title: str = "") -> Path:
    """The seed's Figures 10-11 for our model: ROM bars (`spinecohort.rom.compare.validate` table), the
    accepted in-vitro interval as whiskers; one panel per extraction mode."""
    modes = [m for m in ("lumbar", "unit") if (validation["mode"] == m).any()]
    fig, axes = plt.subplots(
        len(modes), 1, figsize=(max(6, 0.6 * len(validation) + 3), 3.6 * len(modes)), squeeze=False
    )
    for ax, mode in zip(axes[:, 0], modes):
        v = validation[validation["mode"] == mode].reset_index(drop=True)
        x = np.arange(len(v))
        colors = ["tab:green" if r is True else ("tab:red" if r is False else "tab:gray") for r in v["in_range"]]
        ribs = (v["variant"] == "rib_heads").to_numpy() if "variant" in v else np.zeros(len(v), bool)
        ax.bar(x, v["model_deg"], color=colors, alpha=0.7, label="model (green: in range, red: out)")
        if ribs.any():  # the same unit solved with the specimens' rib heads: its own bar, hatched
            ax.bar(x[ribs], v["model_deg"][ribs], color="none", hatch="//", edgecolor="0.3", label="with rib heads")
        # whiskers: the calibration criterion's accepted interval (mean +- acceptance_sd SD, or the range
        # corrected for the missing rib heads; spinecohort.rom.compare)
        lo, hi = v["accept_low"].astype(float), v["accept_high"].astype(float)
        centre = np.where(v["ref_statistic"] == "mean_sd", v["ref_value"].astype(float), 0.5 * (lo + hi))
        ax.errorbar(
            x + 0.25,
            centre,
            yerr=[centre - lo, hi - centre],
            fmt="o",
            color="k",
            capsize=4,
            label="in vitro: accepted interval",
        )
        ax.set_xticks(
            x,
            [
                f"{s}\n{m.replace('_', ' ')}\n({sd}{', rib heads' if r else ''})"
                for s, m, sd, r in zip(v["segment"], v["motion"], v["side"], ribs)
            ],
            fontsize=7,
        )
        ax.set_ylabel("ROM (deg)")
        ax.set_title(f"{title} {'lumbar model (pelvis..T10)' if mode == 'lumbar' else 'functional units'}".strip())
        ax.legend(fontsize=7, loc="upper left")  # the right end holds the tallest bars (axial rotation)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return Path(path)


def rom_modes_figure(modes: pd.DataFrame, path: str | Path) -> Path:
    """Segmental ROM vs shape-mode weight (`spinecohort.rom.modes.gather` table): one row of panels per
    motion plane (full range, both directions summed), one column per segment and extraction; one line per
    shape mode, through the mean at weight 0.  Open markers: a case short of the full moment."""
    from spinecohort.rom.deck import PLANES

    cols = modes[["mode", "segment"]].drop_duplicates().sort_values(["mode", "segment"], key=_segment_key)
    fig, axes = plt.subplots(
        len(PLANES), len(cols), figsize=(1.9 * len(cols) + 1, 2.2 * len(PLANES)), squeeze=False, sharex=True
    )
    colours = plt.get_cmap("tab10")
    for r, (plane, cases) in enumerate(PLANES.items()):
        for c, (mode, seg) in enumerate(cols.itertuples(index=False)):
            ax = axes[r, c]
            d = modes[(modes["mode"] == mode) & (modes["segment"] == seg) & modes["load_case"].isin(cases)]
            full = d.groupby(["shape_mode", "weight_sd"]).agg(rom=("rom_deg", "sum"), frac=("load_fraction", "min"))
            for k, (sm, g) in enumerate(full.groupby(level=0)):
                g = g.droplevel(0).sort_index()
                ax.plot(g.index, g["rom"], "-", color=colours(k), label=f"mode {sm}")
                short = g["frac"] < 1.0 - 1e-6
                ax.plot(g.index[~short], g["rom"][~short], "o", color=colours(k), ms=3)
                ax.plot(g.index[short], g["rom"][short], "o", mfc="none", color=colours(k), ms=5)
            if r == 0:
                ax.set_title(f"{seg}\n({mode})", fontsize=8)
            if c == 0:
                ax.set_ylabel(f"{plane.replace('_', ' ')}\nROM (deg)", fontsize=8)
            if r == len(PLANES) - 1:
                ax.set_xlabel("weight (SD)", fontsize=8)
            ax.tick_params(labelsize=7)
            ax.grid(alpha=0.3)
    axes[0, 0].legend(fontsize=6)
    fig.suptitle("Segmental ROM vs shape-mode weight (7.5 N.m; open marker: load not reached)", fontsize=10)
    fig.tight_layout(rect=(0, 0, 1, 0.96))
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return Path(path)


def _segment_key(s: pd.Series) -> pd.Series:
    """Sort key of mode ('lumbar' before 'unit') and segment names (cranial first: T before L before S)."""
    if s.name == "mode":
        return s
    from spinecohort.rom.submodel import COLUMN

    return s.map(lambda seg: COLUMN.index(seg.split("-")[0]))


def rom_sensitivity_figure(sens: pd.DataFrame, path: str | Path) -> Path:
    """Change of every compared ROM (columns; deg) with each calibrated parameter at the low and high end
    of its published range (rows), `spinecohort.rom.sensitivity.sensitivity` table, as an annotated heat map."""
    d = sens[sens["parameter"] != "baseline"].copy()
    d["row"] = d["parameter"] + " " + d["level"] + " (" + d["value"].map("{:g}".format) + ")"
    if "max_guide_moment_nmm" in d:  # a variant with a guided case: its values include a constrained one
        d["row"] += d["max_guide_moment_nmm"].map(lambda v: f" [guided {v:.0f} N.mm]" if v > 0 else "")
    d["col"] = d["segment"] + " " + d["motion"].str.replace("_", " ") + " (" + d["side"] + ")"
    order_cols = list(dict.fromkeys(d["col"]))
    # a comparison without value in every variant (a case short of the full load) stays as an empty column
    m = d.pivot_table(index="row", columns="col", values="change_deg", sort=False, dropna=False)
    m = m.reindex(index=list(dict.fromkeys(d["row"])), columns=order_cols)
    lim = max(float(np.nanmax(np.abs(m.to_numpy()))), 0.1)
    fig, ax = plt.subplots(figsize=(0.75 * m.shape[1] + 4, 0.32 * m.shape[0] + 2.5))
    im = ax.imshow(m.to_numpy(), cmap="RdBu_r", vmin=-lim, vmax=lim, aspect="auto")
    for (i, j), v in np.ndenumerate(m.to_numpy()):
        if np.isfinite(v):
            colour = "white" if abs(v) > 0.6 * lim else "black"  # legible on the darkest cells
            ax.text(j, i, f"{v:+.1f}", ha="center", va="center", fontsize=6, color=colour)
        else:  # not compared: that case stopped short of the full moment (the table's min_load_fraction)
            ax.add_patch(plt.Rectangle((j - 0.5, i - 0.5), 1, 1, facecolor="0.85", hatch="///", edgecolor="0.6"))
            ax.text(j, i, "short", ha="center", va="center", fontsize=6, color="0.25")
    ax.set_xticks(range(m.shape[1]), m.columns, rotation=60, ha="right", fontsize=7)
    ax.set_yticks(range(m.shape[0]), m.index, fontsize=7)
    fig.colorbar(im, ax=ax, label="change of ROM from the calibrated model (deg)")
    ax.set_title(
        "ROM sensitivity: each parameter at the ends of its published range (functional units, 7.5 N.m;"
        " hatched: case short of the load, not compared)",
        fontsize=9,
    )
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return Path(path)


#: the load cases in the order the loads figure draws them
LOAD_CASE_ORDER = ("flexion", "extension", "lateral_left", "lateral_right", "axial_left", "axial_right")


def loads_figure(idp: pd.DataFrame, facets: pd.DataFrame, path: str | Path, title: str = "") -> Path:
    """The lumbar model's nucleus pressure per disc and load case (top) and its facet force per joint, load case
    and side (bottom: left solid, right hatched; contact struts and extension stop added), from `spinecohort.rom.run.solve_model_loads`'s
    tables (the functional units when the run has no lumbar model); a case short of the full moment drawn pale."""
    mode = "lumbar" if (idp["mode"] == "lumbar").any() else "unit"
    fig, axes = plt.subplots(2, 1, figsize=(10, 7))
    colors = dict(zip(LOAD_CASE_ORDER, plt.get_cmap("tab10").colors))
    width = 0.8 / len(LOAD_CASE_ORDER)
    for ax, t, index, value, label in (
        (axes[0], idp, "disc", "pressure_mpa", "nucleus pressure (MPa)"),
        (axes[1], _joint_totals(facets), "joint", "force_n", "facet force (N)"),
    ):
        t = t[(t["mode"] == mode) & (t["variant"] == "intact")] if len(t) else t
        levels = sorted(set(t[index]), key=_segment_order) if len(t) else []
        x = np.arange(len(levels))
        for k, case in enumerate(LOAD_CASE_ORDER):
            c = t[t["load_case"] == case]
            sides = (("L", "", 0.5), ("R", "///", 0.5)) if index == "joint" else ((None, "", 1.0),)
            for j, (side, hatch, share) in enumerate(sides):
                s = c if side is None else c[c["side"] == side]
                y = s.set_index(index)[value].reindex(levels).to_numpy(dtype=float)
                full = s.set_index(index)["load_fraction"].reindex(levels).fillna(0).to_numpy() >= 1 - 1e-6
                xs = x - 0.4 + width * (k + j * share) + 0.5 * width * share
                bars = ax.bar(xs, np.nan_to_num(y), width * share, color=colors[case], hatch=hatch, edgecolor="white",
                              label=case.replace("_", " ") if j == 0 else None)  # fmt: skip
                for b, f in zip(bars, full):
                    b.set_alpha(1.0 if f else 0.35)
        ax.set_xticks(x, levels)
        ax.set_ylabel(label)
        ax.axhline(0.0, color="k", lw=0.6)
    axes[0].legend(fontsize=7, ncol=3)
    where = "lumbar model (pelvis..T10)" if mode == "lumbar" else "functional units"
    axes[0].set_title(f"{title} {where}, pure moments".strip())
    axes[1].set_title("facet joints, contact strut + extension stop: left (solid), right (hatched)", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return Path(path)


def _joint_totals(facets: pd.DataFrame) -> pd.DataFrame:
    """Facet force per joint side and case, every kind of strut (contact, extension stop) added."""
    if not len(facets):
        return facets
    keys = ["mode", "variant", "joint", "side", "load_case"]
    return (
        facets.groupby(keys, sort=False)
        .agg(force_n=("force_n", "sum"), load_fraction=("load_fraction", "min"))
        .reset_index()
    )


def _segment_order(level: str) -> int:
    """Cranial first: the index of a segment's upper vertebra in the column T1 .. S1."""
    from spinecohort.rom.submodel import COLUMN

    return COLUMN.index(level.split("-")[0])
