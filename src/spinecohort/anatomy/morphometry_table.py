"""The per-level morphometry of the labeled reference spine against published values, as a Markdown table.

``python -m spinecohort.anatomy.morphometry_table --markdown`` prints the table; ``--write [PAGE]`` puts it
into ``docs/explanation/anatomy.md`` between the two marker comments; ``--check [PAGE]`` exits 1 when the page
holds another table.  One row per published cell (level, quantity, source) with a dispersion: the measured
value, the published mean and interval, the verdict, and for a value outside its interval the reason
(:data:`REASONS`).  Measured on the vendored reference with its own labels, endplate rim bands and facet
articular surfaces (`measure_reference`).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import pandas as pd

from spinecohort.anatomy import morphometry as M
from spinecohort.anatomy.labels import FACET_SURFACES, LEVELS, REGIONS
from spinecohort.anatomy.reference import Reference, load_reference

START = "<!-- morphometry-table:start (python -m spinecohort.anatomy.morphometry_table --write) -->"
END = "<!-- morphometry-table:end -->"
PAGE = Path("docs/explanation/anatomy.md")

#: Why a reference value lies outside its published interval: quantity -> (levels, reason).  A cell outside
#: its interval and not named here is marked "unexplained".
REASONS: dict[str, tuple[tuple[str, ...], str]] = {
    "body_height_posterior": (
        ("T12", "L1", "L2"),
        "T12: built to Panjabi 1991's 22.7 mm (inside Kunkel 2011's interval); Busscher 2010's six male CT "
        "spines are taller; L1, L2: this donor's tall lumbar bodies, measured on the whole-vertebra "
        "surfaces, which lie up to 2 mm outside the body-only surfaces of the same donor on the endplates "
        "(`anatomy.assemble.BODY_TOLERANCE_MM`); Busscher's CT heights hold them",
    ),
    "body_height_anterior": (
        ("T12", "L5"),
        "T12: built to Panjabi 1991's posterior height times Kunkel 2011's anterior/posterior ratio (inside "
        "Kunkel's interval), below Busscher 2010's six male CT spines; L5: the donor's strongly wedged L5, "
        "measured on the whole-vertebra surface",
    ),
    "endplate_width_upper": (
        ("T9",),
        "the widths are interpolated from the typical-thoracic mean (placed at T5.5) to Panjabi 1991's T11; "
        "T9 is the widest level the pooled T2-T9 interval covers",
    ),
    "canal_depth": (
        ("T11", "T12", "L1", "L3", "L5"),
        "a narrow canal in this reference (below Panjabi's mean at every level): the Remus "
        "whole-vertebra surfaces lie outside the body-only ones (see the heights), and an outward offset "
        "narrows a hole by twice its size; T11 and T12 keep L1's canal depth, scaled with the arch",
    ),
    "canal_width": (("L3",), "the narrow canal of this reference (see canal depth)"),
    "pedicle_width": (
        ("T1", "T5", "T12"),
        "the thoracic pedicles are L1's scaled with the body and the arch, 5.9 mm at T1 widening to 9.9 mm "
        "at T12; the narrow mid-thoracic pedicles (3.65 mm at T5 in 20 central-Indian columns) and the wide "
        "T1 pedicle (9.3 mm on Indian CT) are not modelled; T12 is inside Panjabi 1991 and Kaur 2016",
    ),
    "pedicle_height": (
        ("T12",),
        "L1's pedicle scaled by the height of a thoracic motion segment (0.7 at T12): 11.5 mm against the "
        "15.5 mm of 20 central-Indian columns, the only stored thoracic pedicle height",
    ),
    "facet_sup_transverse": (
        tuple(lv for lv in LEVELS if lv not in ("T6", "T7", "T12")),
        "T1-T11: the articular pillars of the L1 template swirled about their vertical axes until the superior "
        "articular faces face posteriorly and laterally, 27.5 deg from the frontal plane (the middle of "
        "Masharawi's 25-30); their articular patches (the process within 4 mm of its partner, used here) lag "
        "the turned articular face and face 18-23 deg laterally at T2-T5 and T8-T11 (66-72 deg); T1's patch is the "
        "tip cap of a process without partner; "
        "L1-L5: the Visible Human lumbar facets are more sagittal than Masharawi's ranges (the upstream "
        "patches: L2 25.0, L3 27.4, L4 25.2, L5 38.4 deg, `tests/test_morphometry.py`), the reference's remeshed "
        "and pushed-apart patches more so",
    ),
}


def measure_reference(ref: Reference | None = None) -> pd.DataFrame:
    """Long table (level, quantity, value) of `M.measure_vertebra` for T1..L5 of the reference: its region
    labels, the rim bands of its endplates (``Landmarks.endplate_sup/inf``) and its facet articular
    surfaces (``sets['facet_surface_*']``)."""
    ref = ref if ref is not None else load_reference()
    rows = []
    for i, lv in enumerate(LEVELS):
        parts = M.parts_of_vertebra(ref.region, REGIONS, ref.level == i)
        facets = {k: ref.sets[f"facet_surface_{k}"][lv] for k in FACET_SURFACES if lv in ref.sets[f"facet_surface_{k}"]}
        sup, inf = ref.landmarks.endplate_sup[lv], ref.landmarks.endplate_inf[lv]
        values = M.measure_vertebra(ref.vertices, ref.faces, parts, sup, inf, facet_surfaces=facets)
        rows += [{"level": lv, "quantity": k, "value": v} for k, v in values.items()]
    return pd.DataFrame(rows, columns=["level", "quantity", "value"])


def judged(measured: pd.DataFrame, reference: pd.DataFrame | None = None) -> pd.DataFrame:
    """`M.compare_with_reference` restricted to published cells, in level then quantity order, with the
    reason of every value outside its interval (``reason``: empty when inside, "unexplained" when not named)."""
    reference = reference if reference is not None else M.reference_table()
    out = M.compare_with_reference(measured, reference)
    out = out[out["verdict"] != "no reference"].copy()
    out["order"] = out["level"].map(LEVELS.index)
    out = out.sort_values(["order", "quantity", "source"], kind="stable").drop(columns="order")

    def reason(row) -> str:
        if row["verdict"] != "outside":
            return ""
        levels, text = REASONS.get(row["quantity"], ((), ""))
        return text if row["level"] in levels else "unexplained"

    out["reason"] = [reason(r) for r in out.to_dict("records")]
    return out.reset_index(drop=True)


def _published(row) -> str:
    if row["criterion"] == "published range":
        return f"{row['ref_low']:.0f}–{row['ref_high']:.0f}"
    if row["criterion"] == "no interval":
        return f"{row['ref_mean']:.1f} (no dispersion)"
    return f"{row['ref_mean']:.1f} [{row['ref_low']:.1f}–{row['ref_high']:.1f}]"


def markdown(table: pd.DataFrame) -> str:
    """The Markdown table of `judged` (one row per cell), reasons as numbered notes under it."""
    notes: dict[str, int] = {}
    lines = [
        "| level | quantity | measured | published: mean [interval] | source | verdict |",
        "|---|---|---:|---|---|---|",
    ]
    for row in table.to_dict("records"):
        verdict = row["verdict"]
        if row["reason"]:
            k = notes.setdefault(row["reason"], len(notes) + 1)
            verdict = f"{verdict} ({k})"
        unit = "°" if row["unit"] == "deg" else " mm"
        lines.append(
            f"| {row['level']} | {row['quantity']} | {row['value']:.1f}{unit} | {_published(row)} | "
            f"{row['source']} | {verdict} |"
        )
    counts = table["verdict"].value_counts()
    lines += [
        "",
        "Interval: the published range, else mean ± 2 SD (SD = SEM·√n where only the SEM is published). "
        + ", ".join(f"{counts.get(v, 0)} {v}" for v in ("inside", "outside", "no interval"))
        + f" of {len(table)} cells.",
        "",
    ]
    lines += [f"- ({k}) {text}" + ("" if text.endswith(".") else ".") for text, k in notes.items()]
    return "\n".join(lines) + "\n"


def replace_between_markers(page_text: str, block: str) -> str:
    """``page_text`` with everything between `START` and `END` replaced by ``block``; a clear error when the
    markers are missing."""
    if START not in page_text or END not in page_text:
        raise ValueError(f"the page lacks the marker comments {START!r} and {END!r}")
    head, rest = page_text.split(START, 1)
    _, tail = rest.split(END, 1)
    return f"{head}{START}\n{block}{END}{tail}"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    group = parser.add_mutually_exclusive_group(required=True)
    group.add_argument("--markdown", action="store_true", help="print the table")
    group.add_argument("--write", nargs="?", const=PAGE, type=Path, help="write it into PAGE between the markers")
    group.add_argument("--check", nargs="?", const=PAGE, type=Path, help="exit 1 if PAGE holds another table")
    args = parser.parse_args(argv)
    block = markdown(judged(measure_reference()))
    if args.markdown:
        sys.stdout.write(block)
        return 0
    page = args.write or args.check
    text = page.read_text(encoding="utf-8")
    new = replace_between_markers(text, block)
    if args.check:
        if new != text:
            print(f"{page}: the morphometry table is out of date; run python -m {__spec__.name} --write")
            return 1
        return 0
    page.write_text(new, encoding="utf-8")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
