"""Published FE-validation reference values (``spinecohort/data/validation/*.csv``) as one tidy table.

Every row is one published number: ``level`` (a segment such as ``L3-L4`` or a span such as ``L1-L5``),
``motion`` (flexion, extension, lateral_bending, axial_rotation, flexion_extension), ``quantity``,
``statistic`` (mean, sd, median, min, max, low, high), ``value``, ``unit`` and ``source``, with the loading
(``moment_nmm``, ``preload_n``), ``n``, ``condition``, ``locator`` (table / figure) and ``provenance`` beside.
The README next to the files says what was obtained from where and what was not.

Quantities and their units:

========================  ====  =======================================================================
rom                       deg   rotation from neutral to one side under the moment
rom_full                  deg   full range: both directions of a plane added
rom_median_difference     deg   |median of FE models - median in vitro| (a published summary)
intradiscal_pressure      MPa   nucleus pressure
facet_force               N     facet joint contact force
========================  ====  =======================================================================
"""

from __future__ import annotations

from importlib import resources

import numpy as np
import pandas as pd

VALIDATION_DIR = "data/validation"

#: Columns every file has, in this order first.
TIDY_COLUMNS: tuple[str, ...] = ("level", "motion", "quantity", "statistic", "value", "unit", "source")

#: Unit of every quantity (one unit per quantity across all files).
QUANTITY_UNITS: dict[str, str] = {
    "rom": "deg",
    "rom_full": "deg",
    "rom_median_difference": "deg",
    "intradiscal_pressure": "MPa",
    "facet_force": "N",
}

STATISTICS: frozenset[str] = frozenset({"mean", "sd", "median", "min", "max", "low", "high"})
MOTIONS: frozenset[str] = frozenset({"flexion", "extension", "lateral_bending", "axial_rotation", "flexion_extension"})

#: Pairs (lower, upper) of statistics that must be ordered within one reference.
_ORDERED = (("low", "high"), ("min", "median"), ("median", "max"), ("min", "max"))
_KEY = ["source", "level", "motion", "quantity", "condition", "moment_nmm", "preload_n"]


def validation_files() -> list[str]:
    """Names of the packaged reference files (sorted)."""
    folder = resources.files("spinecohort").joinpath(VALIDATION_DIR)
    return sorted(p.name for p in folder.iterdir() if p.name.endswith(".csv"))


def read_reference_file(name: str) -> pd.DataFrame:
    """One packaged file as a DataFrame, checked by `check_references` (errors name the file)."""
    with resources.files("spinecohort").joinpath(f"{VALIDATION_DIR}/{name}").open("r", encoding="utf-8") as fh:
        table = pd.read_csv(fh, comment="#", keep_default_na=False, na_values=[""])
    try:
        check_references(table)
    except ValueError as err:
        raise ValueError(f"{VALIDATION_DIR}/{name}: {err}") from None
    return table.assign(file=name)


def check_references(table: pd.DataFrame) -> None:
    """Raise ValueError naming the first problem: a missing tidy column, an unknown quantity, statistic or
    motion, a unit that is not its quantity's, a non-finite value, or a lower statistic above its upper
    (low > high, min > median > max) within one reference."""
    missing = [c for c in TIDY_COLUMNS if c not in table.columns]
    if missing:
        raise ValueError(f"missing columns {missing}")
    for col, allowed in (("quantity", QUANTITY_UNITS), ("statistic", STATISTICS), ("motion", MOTIONS)):
        bad = sorted(set(table[col]) - set(allowed))
        if bad:
            raise ValueError(f"unknown {col} {bad}; allowed: {sorted(allowed)}")
    wrong = table[table["unit"] != table["quantity"].map(QUANTITY_UNITS)]
    if len(wrong):
        r = wrong.iloc[0]
        raise ValueError(f"{r['quantity']} in {r['unit']!r}, expected {QUANTITY_UNITS[r['quantity']]!r}")
    values = pd.to_numeric(table["value"], errors="coerce")
    if not np.isfinite(values).all():
        raise ValueError(f"non-numeric or non-finite values in rows {np.flatnonzero(~np.isfinite(values)).tolist()}")
    key = [c for c in _KEY if c in table.columns]
    wide = _pivot(table.assign(value=values), key)
    for lo, hi in _ORDERED:
        if lo in wide and hi in wide:
            bad = wide[wide[lo] > wide[hi]]
            if len(bad):
                raise ValueError(f"{lo} > {hi} for {dict(zip(key, bad.index[0]))}")


def load_validation_references(files: list[str] | None = None) -> pd.DataFrame:
    """All packaged reference files (or the named ones) in one tidy table: the `TIDY_COLUMNS` first, then the
    loading and provenance columns, then ``file``."""
    tables = [read_reference_file(name) for name in (files or validation_files())]
    table = pd.concat(tables, ignore_index=True)
    table["value"] = table["value"].astype(float)
    rest = [c for c in table.columns if c not in TIDY_COLUMNS]
    return table[list(TIDY_COLUMNS) + rest]


def reference_wide(table: pd.DataFrame) -> pd.DataFrame:
    """One row per reference (source, level, motion, quantity, condition, loading) with a column per
    statistic (mean, sd, median, ...) and the unit: the shape a validation table compares against."""
    key = [c for c in _KEY if c in table.columns] + ["unit"]
    wide = _pivot(table, key)
    wide.columns.name = None
    return wide.reset_index()


def _pivot(table: pd.DataFrame, key: list[str]) -> pd.DataFrame:
    """Statistics as columns, one row per key; an empty key cell is a key of its own (not a dropped row)."""
    filled = table.assign(**{k: table[k].fillna("") for k in key})
    return filled.pivot_table(index=key, columns="statistic", values="value", aggfunc="first")
