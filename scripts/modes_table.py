"""The mode-study table of docs/explanation/fe-model.md as Markdown, from the rule's own output:

    .venv/bin/python scripts/modes_table.py [results/rom/modes.csv] > table.md

One row per model (the mean, then each mode at its weights): full-range ROM (deg) of each unit's own
segment, F/E = flexion + extension, LB = left + right, AR = left + right; * = a case short of the full moment
(its ROM at the load reached); g = a case solved by the guided attempt (the top turned about the load's axis
only; the moment that held it is the table's guide_moment_nmm).
"""

import sys

import pandas as pd

UNITS = ("T2-T3", "T6-T7", "T10-T11", "L1-L2", "L3-L4", "L4-L5")
PLANES = {"F/E": ("flexion", "extension"), "LB": ("lateral_left", "lateral_right"), "AR": ("axial_left", "axial_right")}

t = pd.read_csv(sys.argv[1] if len(sys.argv) > 1 else "results/rom/modes.csv")
t = t[t["segment"] == t["unit"]].drop_duplicates(["model", "unit", "load_case"])
models = t.drop_duplicates("model").sort_values(["shape_mode", "weight_sd"])
models = pd.concat([models[models["weight_sd"] == 0].head(1), models[models["weight_sd"] != 0]])
head = " | ".join(f"{u} {p}" if p == "F/E" else p for u in UNITS for p in PLANES)
print(f"| model | mode | w (SD) | {head} |")
print("|---|--:|--:|" + "--:|" * (len(UNITS) * len(PLANES)))
for m in models.itertuples():
    rows = t[t["model"] == m.model].set_index(["unit", "load_case"])
    cells = []
    for u in UNITS:
        for cases in PLANES.values():
            r = rows.loc[[(u, c) for c in cases]]
            short = "*" if (r["load_fraction"] < 1.0 - 1e-6).any() else ""
            guided = "g" if (r["guide_moment_nmm"] > 0).any() else ""
            cells.append(f"{r['rom_deg'].sum():.1f}{short}{guided}")
    mode = 0 if m.weight_sd == 0 else m.shape_mode
    w = "0" if m.weight_sd == 0 else f"{m.weight_sd:+g}".replace("-", "−")
    print(f"| {m.model} | {mode} | {w} | " + " | ".join(cells) + " |")
