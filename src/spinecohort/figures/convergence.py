"""Figure of the mesh-convergence study of the ROM (`spinecohort.rom.convergence`)."""

from __future__ import annotations

from pathlib import Path

import matplotlib.pyplot as plt
import pandas as pd


def convergence_figure(table: pd.DataFrame, default: str, max_change: float, path: str | Path) -> Path:
    """ROM (deg) against the unit's element count, one panel per functional unit, one line per load case; the
    default resolution's points ringed, the band of +-max_change around the next finer resolution's ROM shaded."""
    units = list(dict.fromkeys(table["unit"]))
    fig, axes = plt.subplots(1, len(units), figsize=(4.2 * len(units), 3.8), squeeze=False)
    for ax, unit in zip(axes[0], units):
        t = table[table["unit"] == unit]
        for case, c in t.groupby("load_case", sort=False):
            c = c.sort_values("unit_elements")
            (line,) = ax.plot(c["unit_elements"], c["rom_deg"], "o-", label=case.replace("_", " "))
            d = c[c["resolution"] == default]
            ax.plot(d["unit_elements"], d["rom_deg"], "o", ms=11, mfc="none", color=line.get_color())
            finer = c[c["unit_elements"] > d["unit_elements"].max()].head(1) if len(d) else c.iloc[:0]
            for _, f in finer.iterrows():
                x = [d["unit_elements"].iloc[0], f["unit_elements"]]
                ax.fill_between(
                    x,
                    f["rom_deg"] * (1 - max_change),
                    f["rom_deg"] * (1 + max_change),
                    color=line.get_color(),
                    alpha=0.12,
                    lw=0,
                )
        ticks = t.drop_duplicates("resolution").sort_values("unit_elements")
        ax.set_xscale("log")
        ax.set_xticks(
            ticks["unit_elements"],
            [f"{r}\n{n}" for r, n in zip(ticks["resolution"], ticks["unit_elements"])],
            fontsize=7,
        )
        ax.minorticks_off()
        ax.set_xlabel("resolution, elements of the unit")
        ax.set_ylabel("ROM (deg)")
        ax.set_title(unit)
        ax.set_ylim(bottom=0)
    axes[0, 0].legend(fontsize=7)
    fig.suptitle(
        f"ROM vs template resolution (ringed: the default; band: ±{100 * max_change:g} % of the next finer)", fontsize=9
    )
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return Path(path)
