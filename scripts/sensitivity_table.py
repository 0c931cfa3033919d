"""The sensitivity table of docs/explanation/fe-model.md as Markdown, from the rule's own output:

    .venv/bin/python scripts/sensitivity_table.py [results/rom/sensitivity.csv] > table.md

Rows: the calibrated ROM (deg), then per parameter end the change of every compared ROM (deg); min load: the
least load fraction any case reached (a case short of the load is not compared: nan); guide: the largest moment
(N.mm) that held a top turning about its load's axis (the guided attempt: a constrained value), 0 if all free.
"""

import sys

import pandas as pd

t = pd.read_csv(sys.argv[1] if len(sys.argv) > 1 else "results/rom/sensitivity.csv")
t["col"] = t["segment"] + " " + t["motion"]
cols = list(dict.fromkeys(t["col"]))
short = {"flexion": "F", "extension": "E", "lateral_bending": "LB", "axial_rotation": "AR", "flexion_extension": "F/E"}


def name(c):
    seg, mot = c.split(" ", 1)
    return (
        f"{seg} {short.get(mot, mot.replace('flexion_minus_extension', 'F−E').replace('lateral_minus_axial', 'LB−AR'))}"
    )


print("| variant | " + " | ".join(name(c) for c in cols) + " | min load | guide (N·mm) |")
print("|---|" + "--:|" * (len(cols) + 2))
base = t[t["parameter"] == "baseline"].set_index("col")
print(
    "| **calibrated (deg)** | "
    + " | ".join(f"{base.loc[c, 'rom_deg']:.2f}" for c in cols)
    + f" | {base['min_load_fraction'].min():.2f} | {base['max_guide_moment_nmm'].max():.0f} |"
)
for (p, lv, v), g in t[t["parameter"] != "baseline"].groupby(["parameter", "level", "value"], sort=False):
    g = g.set_index("col")
    print(
        f"| {p} {lv} ({v:g}) | "
        + " | ".join(f"{g.loc[c, 'change_deg']:+.2f}" for c in cols)
        + f" | {g['min_load_fraction'].min():.2f} | {g['max_guide_moment_nmm'].max():.0f} |"
    )
