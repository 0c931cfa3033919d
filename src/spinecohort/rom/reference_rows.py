"""The packaged references (`spinecohort.rom.references`) a validation beyond segmental ROM compares with, read
by their ``quantity`` column, so a new CSV with a known quantity is picked up without code changes.

Every accessor returns the tidy long table (columns level, motion, quantity, statistic, value, unit, source,
condition, moment_nmm, preload_n, ...; ``facet`` for facet forces), empty when nothing was obtained:

* `lumbar_total_rom`: L1-L5 rotation (``rom`` one direction, ``rom_full`` both), e.g. Dreischarf et al. 2014's
  in-vitro median/min/max and the eight models' range;
* `intradiscal_pressure`: nucleus pressure, of one disc or all;
* `facet_forces`: facet joint contact force, with the loaded ``facet`` (ipsilateral / contralateral / left /
  right, or empty for both) from the row's own column or its condition text (Jaumard et al. 2011);
* `remus_segmental_rom`: the segmental ROM L1-S1 of the model built on the same anatomy (Remus et al. 2021).

Which rows a run can be judged by (the loading) is the comparison's business (`spinecohort.rom.outcomes`).
"""

from __future__ import annotations

import pandas as pd

from spinecohort.rom.references import load_validation_references

#: the lumbar segments of a same-geometry comparison, cranial first
LUMBAR_SEGMENTS = ("L1-L2", "L2-L3", "L3-L4", "L4-L5", "L5-S1")
#: words of a condition text that name the facet a force was measured on
FACET_WORDS = ("ipsilateral", "contralateral", "left", "right")


def reference_rows(quantities: tuple[str, ...], level: str | None = None) -> pd.DataFrame:
    """The packaged rows of `quantities` (at `level` if given)."""
    table = load_validation_references()
    rows = table[table["quantity"].isin(quantities)]
    if level is not None:
        rows = rows[rows["level"] == level]
    return rows.reset_index(drop=True)


def lumbar_total_rom() -> pd.DataFrame:
    """L1-L5 total rotation references (quantities rom and rom_full)."""
    return reference_rows(("rom", "rom_full"), "L1-L5")


def intradiscal_pressure(level: str | None = None) -> pd.DataFrame:
    """Nucleus pressure references (MPa) of disc `level` ('L4-L5'), or of every disc."""
    return reference_rows(("intradiscal_pressure",), level)


def facet_of(condition: object) -> str:
    """The facet a condition text names ('in vitro, intact, ipsilateral facet' -> 'ipsilateral'), '' if none."""
    text = str(condition).lower() if isinstance(condition, str) else ""
    return next((w for w in FACET_WORDS if w in text), "")


def facet_forces() -> pd.DataFrame:
    """Facet joint force references (N) with a ``facet`` column."""
    rows = reference_rows(("facet_force",))
    if "facet" not in rows:
        rows = rows.assign(facet=[facet_of(c) for c in rows.get("condition", pd.Series("", index=rows.index))])
    return rows


def remus_segmental_rom() -> pd.DataFrame:
    """Segmental ROM L1-S1 of Remus et al. 2021's model (quantities rom and rom_full)."""
    rows = reference_rows(("rom", "rom_full"))
    rows = rows[rows["source"].str.contains("Remus", case=False) & rows["level"].isin(LUMBAR_SEGMENTS)]
    return rows.reset_index(drop=True)
