"""The shard jobs' tables as columns: an ordered ``dict`` of equal-length numpy arrays, written to CSV
byte for byte as ``pandas.DataFrame(columns).to_csv(path, index=False, float_format=...)`` writes them.

A shard job makes three small tables; it never imports pandas (docs/explanation/library-paths.md measures
what that saves).  Readers of the tables (``measure.tables``, the platform) use pandas.
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

#: ordered column name -> (rows,) array
Columns = dict[str, np.ndarray]

#: per-model quality columns of the shard tables carried into the virtual-cohort sheet
QUALITY_SUMMARY = [
    "min_sj_before",
    "min_sj_after",
    "invalid_before",
    "invalid_after",
    "nodes_moved",
    "max_displacement_mm",
    "repaired",
]
#: disc-contact columns (present when the hex SSM carries a contact map; spinecohort.mesh.contact)
CONTACT_SUMMARY = ["min_disc_gap_before_mm", "discs_opened", "distraction_mm"]


def concat_columns(parts: list[Columns]) -> Columns:
    """The rows of ``parts`` (same columns, in the first part's order) one after the other."""
    if not parts:
        return {}
    names = list(parts[0])
    for i, p in enumerate(parts[1:], 1):
        if list(p) != names:
            raise ValueError(f"part {i} has columns {list(p)[:5]}..., the first part {names[:5]}...")
    return {k: np.concatenate([np.asarray(p[k]) for p in parts]) for k in names}


def _is_missing(v) -> bool:
    return v is None or (isinstance(v, float) and v != v)


def _texts(col: np.ndarray, float_format: str) -> list[str]:
    """The CSV fields of one column as pandas writes them: floats by ``float_format`` (NaN empty), integers
    and booleans by ``str``, other objects by ``str`` (None and NaN empty)."""
    kind = col.dtype.kind
    values = col.tolist()
    if kind == "f":
        return ["" if v != v else float_format % v for v in values]
    if kind in "iub":
        return [str(v) for v in values]
    return ["" if _is_missing(v) else str(v) for v in values]


def write_csv(columns: Columns, path: str | Path, float_format: str) -> None:
    """``pandas.DataFrame(columns).to_csv(path, index=False, float_format=float_format)``, byte for byte
    (tested): a header of the names, then one line per row, fields quoted only where they hold a comma, a
    quote or a line break (the ``csv`` module, which pandas uses too), lines ending in \\n."""
    arrays = [np.asarray(v) for v in columns.values()]
    n = {len(a) for a in arrays}
    if len(n) > 1:
        raise ValueError(f"{path}: columns of different lengths {sorted(n)}")
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh, lineterminator="\n")
        w.writerow(columns)
        w.writerows(zip(*(_texts(a, float_format) for a in arrays)))
