"""Published FE-validation reference values (``spinecohort/data/validation/*.csv``) as one tidy table.

Every row is one published number: ``level`` (a segment such as ``L3-L4`` or a span such as ``L1-L5``),
``motion`` (a loading direction such as flexion or axial_rotation; for in-vivo data the posture or activity,
`POSTURES`), ``quantity``, ``statistic`` (`STATISTICS`; ``single`` is one measurement of one subject or one
model's prediction), ``value``, ``unit`` and ``source``, with the loading (``moment_nmm``, ``preload_n``; empty
where none applies or the source does not state it), ``n``, ``condition``, ``locator`` (table / figure) and
``provenance`` beside. The README next to the files says what was obtained from where; the numbers wanted but
not obtained are listed, one group a row, in ``gaps/not_obtained.csv`` (`not_obtained`).

The validation tables ask for one kind of reference at a time through `lumbar_total_rom`, `intradiscal_pressure`,
`facet_forces`, `remus_segmental_rom` and `in_vitro_segmental_rom`: each returns the `ACCESSOR_COLUMNS` (plus ``facet`` for facet forces),
sorted cranial to caudal, and an empty frame of the same columns while its numbers are only in the gaps list.

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

import re
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

#: ``model_*`` are summaries over a set of published FE models (Dreischarf et al. 2014 compare eight).
STATISTICS: frozenset[str] = frozenset(
    {"mean", "sd", "median", "min", "max", "low", "high", "single", "model_median", "model_min", "model_max"}
)
LOAD_DIRECTIONS: frozenset[str] = frozenset(
    {"flexion", "extension", "lateral_bending", "axial_rotation", "flexion_extension", "axial_compression"}
)
#: In-vivo postures and activities (intradiscal pressure measured in a volunteer, Wilke et al. 1999).
POSTURES: frozenset[str] = frozenset(
    {
        "lying_prone",
        "lying_lateral",
        "lying_night_start",
        "lying_night_end",
        "standing_relaxed",
        "standing_flexed_forward",
        "sitting_unsupported",
        "sitting_maximum_flexion",
        "sitting_nonchalant",
        "lifting_20kg_round_back",
        "lifting_20kg_flexed_knees",
        "lifting_20kg_close_to_body",
    }
)
MOTIONS: frozenset[str] = LOAD_DIRECTIONS | POSTURES

GAPS_FILE = "gaps/not_obtained.csv"
#: Columns of the not-obtained list, and the quantities it may name beyond `QUANTITY_UNITS`.
GAP_COLUMNS: tuple[str, ...] = (
    "source", "quantity", "levels", "motions", "statistics", "loading", "wanted_from", "searched", "reason"
)  # fmt: skip
GAP_QUANTITIES: frozenset[str] = frozenset(QUANTITY_UNITS) | {"mesh_convergence", "calibration_target"}

#: Pairs (lower, upper) of statistics that must be ordered within one reference.
_ORDERED = (
    ("low", "high"), ("min", "median"), ("median", "max"), ("min", "max"),
    ("model_min", "model_median"), ("model_median", "model_max"), ("model_min", "model_max"),
)  # fmt: skip
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
    filled = table.assign(**{k: table[k].astype(object).fillna("") for k in key})
    return filled.pivot_table(index=key, columns="statistic", values="value", aggfunc="first")


def select_references(table: pd.DataFrame, **criteria: str | float) -> pd.DataFrame:
    """The rows of `table` whose columns equal every given value, e.g. ``quantity="facet_force",
    level="T12-L2"``; an unknown column is an error naming it."""
    unknown = sorted(set(criteria) - set(table.columns))
    if unknown:
        raise ValueError(f"unknown reference columns {unknown}; columns: {list(table.columns)}")
    mask = np.ones(len(table), dtype=bool)
    for col, value in criteria.items():
        mask &= (table[col] == value).to_numpy()
    return table[mask]


def not_obtained() -> pd.DataFrame:
    """The published numbers wanted for the FE validation that could not be obtained (one group a row: source,
    quantity, levels and motions as ``;``-separated lists, statistics, loading, where in the source they are,
    where it was searched and why they are missing)."""
    with resources.files("spinecohort").joinpath(f"{VALIDATION_DIR}/{GAPS_FILE}").open("r", encoding="utf-8") as fh:
        gaps = pd.read_csv(fh, comment="#", keep_default_na=False, dtype=str)
    check_gaps(gaps)
    return gaps


def check_gaps(gaps: pd.DataFrame) -> None:
    """Raise ValueError naming the first problem of a not-obtained list: a missing column, an unknown quantity
    or an empty source, searched or reason cell (a gap must say where it was looked for and why it is one)."""
    missing = [c for c in GAP_COLUMNS if c not in gaps.columns]
    if missing:
        raise ValueError(f"{GAPS_FILE}: missing columns {missing}")
    bad = sorted(set(gaps["quantity"]) - GAP_QUANTITIES)
    if bad:
        raise ValueError(f"{GAPS_FILE}: unknown quantity {bad}; allowed: {sorted(GAP_QUANTITIES)}")
    for col in ("source", "searched", "reason"):
        empty = np.flatnonzero(gaps[col].str.strip() == "")
        if len(empty):
            raise ValueError(f"{GAPS_FILE}: empty {col} in rows {empty.tolist()}")


def gaps_also_obtained(table: pd.DataFrame, gaps: pd.DataFrame) -> pd.DataFrame:
    """The gap rows that the reference `table` already covers: same source and quantity, and at one of the
    gap's levels every one of the gap's statistics present. Such a gap is stale and must leave the list once
    its numbers are in a validation CSV."""
    have = table.groupby(["source", "quantity", "level"])["statistic"].agg(set).to_dict()
    covered = [
        any(set(stats.split(";")) <= have.get((src, qty, lv.strip()), set()) for lv in levels.split(";"))
        for src, qty, levels, stats in zip(gaps["source"], gaps["quantity"], gaps["levels"], gaps["statistics"])
    ]
    return gaps[np.asarray(covered, dtype=bool)]


def reference_coverage(table: pd.DataFrame, gaps: pd.DataFrame) -> pd.DataFrame:
    """Per source: numbers obtained (rows of `table`) and groups not obtained (rows of `gaps`), sorted by source;
    the summary the validation report and docs state."""
    got = table.groupby("source").size().rename("numbers_obtained")
    lost = gaps.groupby("source").size().rename("groups_not_obtained")
    out = pd.concat([got, lost], axis=1).fillna(0).astype(int)
    out.index.name = "source"
    return out.sort_index().reset_index()


# ---- accessors the validation tables use -------------------------------------------------------------------

DREISCHARF_SOURCE = "Dreischarf et al. 2014, J Biomech 47:1757"
REMUS_SOURCE = "Remus et al. 2021, PLoS ONE 16:e0250456"
YAMAMOTO_SOURCE = "Yamamoto et al. 1989, Spine 14:1256"

#: Columns every accessor returns, in this order (`facet_forces` adds ``facet``).
ACCESSOR_COLUMNS: tuple[str, ...] = (
    "level", "motion", "statistic", "value", "unit", "source", "condition",
    "quantity", "moment_nmm", "preload_n", "n", "locator", "provenance",
)  # fmt: skip
#: Which facet of the joint pair a facet force belongs to, read from the row's ``condition``.
FACET_SIDES: tuple[str, ...] = ("ipsilateral", "contralateral", "both", "unspecified")
#: Vertebrae cranial to caudal; a level (``L4-L5``) or span (``L1-L5``) sorts by its cranial, then caudal end.
VERTEBRAE: tuple[str, ...] = tuple(f"T{i}" for i in range(1, 13)) + tuple(f"L{i}" for i in range(1, 6)) + ("S1",)
_LEVEL = re.compile(r"^(T(?:[1-9]|1[0-2])|L[1-5])-(T(?:[1-9]|1[0-2])|L[1-5]|S1)$")
_ROM_QUANTITIES = ("rom", "rom_full")


def lumbar_total_rom(table: pd.DataFrame | None = None) -> pd.DataFrame:
    """Range of motion of the whole L1-L5 span (deg; ``rom`` one side, ``rom_full`` both directions): in-vitro
    medians and ranges (``median``/``min``/``max``) and FE-model summaries (``model_*``). Empty while Dreischarf
    et al. 2014's figures are in the gaps list; its average median differences (``rom_median_difference``) are
    not ROM and stay out. `table` defaults to `load_validation_references()`."""
    table = _references(table)
    rows = table[(table["level"] == "L1-L5") & table["quantity"].isin(_ROM_QUANTITIES)]
    return _tidy(rows)


def intradiscal_pressure(level: str | None = None, table: pd.DataFrame | None = None) -> pd.DataFrame:
    """Nucleus pressure (MPa) at one level (``"L4-L5"``) or every level (None): in vitro under the stated moment
    and preload, and in vivo per posture (moment and preload empty). An unknown level gives an empty frame; a
    malformed one is an error naming it."""
    table = _references(table)
    rows = table[table["quantity"] == "intradiscal_pressure"]
    if level is not None:
        rows = rows[rows["level"] == _checked_level(level)]
    return _tidy(rows)


def facet_forces(level: str | None = None, table: pd.DataFrame | None = None) -> pd.DataFrame:
    """Facet joint contact forces (N) with a ``facet`` column (`FACET_SIDES`): ipsilateral / contralateral where
    the source names the side relative to the bending or rotation, both where it reports the pair's sum,
    unspecified otherwise."""
    table = _references(table)
    rows = table[table["quantity"] == "facet_force"]
    if level is not None:
        rows = rows[rows["level"] == _checked_level(level)]
    out = _tidy(rows)
    out.insert(out.columns.get_loc("condition") + 1, "facet", facet_side(out["condition"]))
    return out


def remus_segmental_rom(table: pd.DataFrame | None = None) -> pd.DataFrame:
    """Remus et al. 2021's predicted ROM (deg) per segment L1-L2 ... L5-S1 of their hybrid model on the same
    Visible Human geometry: the model-to-model comparison. Empty while the article's figures and tables are in the
    gaps list."""
    table = _references(table)
    segment = table["level"].isin([f"{a}-{b}" for a, b in zip(VERTEBRAE[12:], VERTEBRAE[13:])])
    rows = table[(table["source"] == REMUS_SOURCE) & table["quantity"].isin(_ROM_QUANTITIES) & segment]
    return _tidy(rows)


def in_vitro_segmental_rom(table: pd.DataFrame | None = None) -> pd.DataFrame:
    """Yamamoto et al. 1989's in-vitro ROM (deg, one side) per segment L1-L2 ... L5-S1 at 10 N·m: the per-level
    shape beside ours (a moment other than the validation's, so reported, not judged)."""
    table = _references(table)
    rows = table[(table["source"] == YAMAMOTO_SOURCE) & table["quantity"].isin(_ROM_QUANTITIES)]
    return _tidy(rows)


def facet_side(condition: pd.Series) -> np.ndarray:
    """`FACET_SIDES` label per condition text: the words ipsilateral / contralateral, "both facets" or "sum"
    (case-insensitive), else unspecified."""
    text = condition.fillna("").astype(str).str.lower()
    return np.select(
        [
            text.str.contains(r"\bipsilateral\b"),
            text.str.contains(r"\bcontralateral\b"),
            text.str.contains(r"\bboth facets\b|\bsum of\b"),
        ],
        ["ipsilateral", "contralateral", "both"],
        default="unspecified",
    )


def level_order(levels: pd.Series) -> np.ndarray:
    """Sort key cranial to caudal (T1-T2 first, L5-S1 last; spans after the segment they start with); levels not
    of the form ``T1-T2`` sort last."""
    rank = {v: i for i, v in enumerate(VERTEBRAE)}
    parts = levels.astype(str).str.split("-", n=1, expand=True).reindex(columns=[0, 1])
    top = parts[0].map(rank).fillna(len(VERTEBRAE)).to_numpy()
    bottom = parts[1].map(rank).fillna(len(VERTEBRAE)).to_numpy()
    return top * (len(VERTEBRAE) + 1) + bottom


def _checked_level(level: str) -> str:
    if not _LEVEL.match(level):
        raise ValueError(f"level {level!r} is not of the form 'L4-L5' (T1..T12, L1..L5, S1 joined by '-')")
    return level


def _references(table: pd.DataFrame | None) -> pd.DataFrame:
    return load_validation_references() if table is None else table


def _tidy(rows: pd.DataFrame) -> pd.DataFrame:
    """`ACCESSOR_COLUMNS` of `rows` (missing ones empty), value as float, sorted by level, motion, source,
    condition, statistic; the same columns and dtypes when there is no row."""
    out = rows.reindex(columns=list(ACCESSOR_COLUMNS)).copy()
    out["value"] = out["value"].astype(float)
    for col in ("moment_nmm", "preload_n", "n"):
        out[col] = pd.to_numeric(out[col], errors="coerce").astype(float)
    out = out.assign(_order=level_order(out["level"]))
    out = out.sort_values(["_order", "motion", "source", "condition", "statistic"], kind="stable")
    return out.drop(columns="_order").reset_index(drop=True)
