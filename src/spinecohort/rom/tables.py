"""The ROM tables of the docs as Markdown, from the rules' own output (``spinecohort rom-table``).

``sensitivity_markdown`` reads ``results/rom/sensitivity.csv``: the calibrated ROM (deg), then, per parameter
end, the change of every compared ROM (deg); ``min load`` is the least load fraction any case reached (a case
short of the load is not compared: nan); ``guide`` the largest moment (N·mm) that held a top turning about its
load's axis (the guided attempt), 0 when every case turned freely.

``modes_markdown`` reads ``results/rom/modes.csv``: one row per model (the mean, then each mode at its weights),
the full-range ROM (deg) of each unit's own segment, F/E = flexion + extension, LB = left + right, AR = left +
right; ``*`` marks a case short of the full moment (its ROM at the load reached), ``g`` a case solved by the
guided attempt.
"""

from __future__ import annotations

import pandas as pd

#: short names of the compared motions in the sensitivity table's header
MOTION_SHORT = {
    "flexion": "F",
    "extension": "E",
    "lateral_bending": "LB",
    "axial_rotation": "AR",
    "flexion_extension": "F/E",
    "flexion_minus_extension": "F−E",
    "lateral_minus_axial": "LB−AR",
}
#: the functional units and planes of the mode study's table
MODE_UNITS = ("T2-T3", "T6-T7", "T10-T11", "L1-L2", "L3-L4", "L4-L5")
MODE_PLANES = {
    "F/E": ("flexion", "extension"),
    "LB": ("lateral_left", "lateral_right"),
    "AR": ("axial_left", "axial_right"),
}


def _row(cells) -> str:
    return "| " + " | ".join(cells) + " |"


def sensitivity_markdown(table: pd.DataFrame) -> str:
    """The sensitivity table (columns segment, motion, parameter, level, value, rom_deg, change_deg,
    min_load_fraction, max_guide_moment_nmm) as a Markdown table."""
    t = table.assign(col=table["segment"] + " " + table["motion"])
    cols = list(dict.fromkeys(t["col"]))
    names = [f"{c.split(' ', 1)[0]} {MOTION_SHORT.get(c.split(' ', 1)[1], c.split(' ', 1)[1])}" for c in cols]
    lines = [_row(["variant", *names, "min load", "guide (N·mm)"]), "|---|" + "--:|" * (len(cols) + 2)]
    base = t[t["parameter"] == "baseline"].set_index("col")
    lines.append(
        _row(
            [
                "**calibrated (deg)**",
                *(f"{base.loc[c, 'rom_deg']:.2f}" for c in cols),
                f"{base['min_load_fraction'].min():.2f}",
                f"{base['max_guide_moment_nmm'].max():.0f}",
            ]
        )
    )
    for (p, lv, v), g in t[t["parameter"] != "baseline"].groupby(["parameter", "level", "value"], sort=False):
        g = g.set_index("col")
        lines.append(
            _row(
                [
                    f"{p} {lv} ({v:g})",
                    *(f"{g.loc[c, 'change_deg']:+.2f}" for c in cols),
                    f"{g['min_load_fraction'].min():.2f}",
                    f"{g['max_guide_moment_nmm'].max():.0f}",
                ]
            )
        )
    return "\n".join(lines) + "\n"


def modes_markdown(table: pd.DataFrame) -> str:
    """The mode-study table (columns model, shape_mode, weight_sd, unit, segment, load_case, rom_deg,
    load_fraction, guide_moment_nmm) as a Markdown table."""
    t = table[table["segment"] == table["unit"]].drop_duplicates(["model", "unit", "load_case"])
    models = t.drop_duplicates("model").sort_values(["shape_mode", "weight_sd"])
    models = pd.concat([models[models["weight_sd"] == 0].head(1), models[models["weight_sd"] != 0]])
    head = [f"{u} {p}" if p == "F/E" else p for u in MODE_UNITS for p in MODE_PLANES]
    lines = [_row(["model", "mode", "w (SD)", *head]), "|---|--:|--:|" + "--:|" * len(head)]
    for m in models.itertuples():
        rows = t[t["model"] == m.model].set_index(["unit", "load_case"])
        cells = []
        for u in MODE_UNITS:
            for cases in MODE_PLANES.values():
                r = rows.loc[[(u, c) for c in cases]]
                short = "*" if (r["load_fraction"] < 1.0 - 1e-6).any() else ""
                guided = "g" if (r["guide_moment_nmm"] > 0).any() else ""
                cells.append(f"{r['rom_deg'].sum():.1f}{short}{guided}")
        mode = "0" if m.weight_sd == 0 else str(m.shape_mode)
        w = "0" if m.weight_sd == 0 else f"{m.weight_sd:+g}".replace("-", "−")
        lines.append(_row([m.model, mode, w, *cells]))
    return "\n".join(lines) + "\n"
