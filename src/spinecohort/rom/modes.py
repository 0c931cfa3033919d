"""The cohort's mechanics: segmental ROM of the mean and of each shape mode at its extreme weights, the other
weights 0 (rule ``rom_modes``; docs/explanation/validation.md).

On the default grid (5 modes, levels -3..3 SD) these are 11 models: the mean model_08403 and, per mode i = 1..5, the
models at w_i = -3 and +3 SD, model_id = sum_i (w_i + 3) 7^(5 - i).  Each is solved by the rule ``rom_model`` (one
Snakemake target per model, so a cluster profile fans them out); this module names them and gathers their tables.  Each
model runs the functional units ``rom.mode_units`` (`mode_rom_config`), not the lumbar model: ~2 min per model instead
of ~7 on 2 cores, and a unit's ROM equals that of the same segment inside the lumbar model (a pure moment is the same
at every level, docs/explanation/validation.md).  A load case that did not reach the full moment keeps its ROM at the
load fraction reached (``load_fraction`` < 1), so a non-converging model is reported, not dropped. Units: degrees,
seconds.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from spinecohort.rom.run import solver_config, units_only
from spinecohort.store.zarr_store import model_id, model_name


def mode_rom_config(rom: dict) -> dict:
    """The ``rom`` block of a mode-study model: the functional units ``rom.mode_units`` alone (no lumbar
    model, no ALL run, no rib heads), the solver settings unchanged, the comparison keys left out
    (`spinecohort.rom.run.solver_config`)."""
    return units_only(solver_config(rom), rom["mode_units"])


def mode_models(n_modes: int, levels, mode_levels) -> pd.DataFrame:
    """One row per model of the mode study: model name, shape mode (0 = the mean), weight (SD)."""
    rows = [{"model": model_name(int(model_id(np.zeros(n_modes), levels))), "shape_mode": 0, "weight_sd": 0.0}]
    for i in range(n_modes):
        for w in mode_levels:
            if w == 0:
                continue
            weights = np.zeros(n_modes)
            weights[i] = w
            rows.append(
                {"model": model_name(int(model_id(weights, levels))), "shape_mode": i + 1, "weight_sd": float(w)}
            )
    return pd.DataFrame(rows)


def gather(models: pd.DataFrame, tables: list[pd.DataFrame], cpu_s: list[float]) -> pd.DataFrame:
    """The intact ROM rows of every model's table with its shape mode, weight and the model's CPU time (s,
    the rule rom_model's benchmark); rows of the mean are repeated as weight 0 of every mode so that each
    mode's curve runs through it."""
    out = []
    for m, table, cpu in zip(models.itertuples(), tables, cpu_s):
        t = table[table["variant"] == "intact"].copy()
        t.insert(1, "shape_mode", m.shape_mode)
        t.insert(2, "weight_sd", m.weight_sd)
        t["model_cpu_s"] = cpu
        t["model_solve_s"] = float(t.drop_duplicates(["mode", "unit", "load_case"])["solve_s"].sum())
        out.append(t)
    df = pd.concat(out, ignore_index=True)
    mean = df[df["shape_mode"] == 0]
    modes = sorted(set(df["shape_mode"]) - {0})
    copies = [mean.assign(shape_mode=i) for i in modes]
    return pd.concat([df[df["shape_mode"] != 0], *copies], ignore_index=True).sort_values(
        ["shape_mode", "weight_sd", "mode", "segment", "load_case"], ignore_index=True
    )


def summary(modes: pd.DataFrame) -> pd.DataFrame:
    """Per model: CPU time (s), sum of ccx solve times (s), lowest load fraction reached, cases short of
    the full moment."""
    per = modes.drop_duplicates(["model", "mode", "unit", "load_case"])
    g = per.groupby("model")
    return pd.DataFrame(
        {
            "cpu_s": g["model_cpu_s"].first(),
            "solve_s": g["model_solve_s"].first(),
            "min_load_fraction": g["load_fraction"].min(),
            "cases_short_of_full_load": g["load_fraction"].apply(lambda f: int((f < 1.0 - 1e-6).sum())),
        }
    ).reset_index()
