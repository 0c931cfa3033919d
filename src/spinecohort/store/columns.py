"""The shard jobs' tables as columns: an ordered ``dict`` of equal-length numpy arrays, batch by batch, and
the names of the columns the virtual-cohort sheet carries.  ``pandas.DataFrame(columns)`` is the table.
"""

from __future__ import annotations

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
