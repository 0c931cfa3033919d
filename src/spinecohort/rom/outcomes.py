"""The validation beyond segmental ROM, as published spine models are validated: the nucleus pressure of every
lumbar disc, the facet joint forces, the L1-L5 total rotation, the segmental ROM beside the model built on the
same anatomy (Remus et al. 2021) and the physiological orderings, each with ours, the reference, the criterion
and a verdict (docs/explanation/validation.md).

Criteria (`reference_intervals`): an in-vitro median with its range accepts the range (min..max); a mean +- SD
accepts mean +- ``acceptance_sd`` SD; a range of models (low..high) accepts the range; a single value (one model,
or a mean without its SD) is reported beside ours, not judged.  Only references under the run's loading are
compared: the same pure moment and no preload; one under another pure moment (Yamamoto et al. 1989's per-level
ROM at 10 N·m) or an unstated one is reported beside ours, not judged.  Without a reference our value is reported
with the verdict "no reference obtained".

Our values come from the lumbar model, intact (`spinecohort.rom.run.solve_model_loads`; from the functional units
when a run has no lumbar model):

* nucleus pressure (MPa) per disc and motion: flexion, extension, and the mean of both sides of lateral bending
  and of axial rotation;
* facet force (N) per joint: the sum of the compressive forces of its contact struts and its extension stop (the
  inferior articular process tip on the lamina below: both stand in for the joint's surface contact, and in
  extension the stop carries it; the per-case table keeps them apart); flexion and extension as the mean of
  the left and right joint, lateral bending and axial rotation for the
  ipsilateral joint (on the side the top bends or its front turns to: left joint in left bending and left axial
  rotation) and the contralateral one, each the mean over both directions.  A reference measured over a span
  (Jaumard et al. 2011's T12-L2: gauges on the L2 superior articular processes) is compared at the span's
  lowest joint (L1-L2);
* L1-L5 total rotation: the sum of L1-L2 .. L4-L5 per load case, in the reference's convention (``rom`` one
  direction, lateral bending and axial rotation the mean of both sides; ``rom_full`` both directions added);
* segmental ROM L1-S1 the same way per segment, beside the same-geometry model and in vitro.

A load case short of the full moment gives no value (NaN, not judged).  Units: MPa, N, degrees.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from spinecohort.rom.compare import model_value_deg, orderings
from spinecohort.rom.references import LOAD_DIRECTIONS
from spinecohort.rom.submodel import COLUMN

MOTIONS = ("flexion", "extension", "lateral_bending", "axial_rotation")
#: the load cases of a motion (one direction each)
CASES = {
    "flexion": ("flexion",),
    "extension": ("extension",),
    "lateral_bending": ("lateral_left", "lateral_right"),
    "axial_rotation": ("axial_left", "axial_right"),
}
#: the joint side ipsilateral to a one-sided load case (the side the top bends or its front turns to)
IPSILATERAL = {"lateral_left": "L", "lateral_right": "R", "axial_left": "L", "axial_right": "R"}
L1_L5 = ("L1-L2", "L2-L3", "L3-L4", "L4-L5")
COLUMNS = [
    "quantity", "level", "motion", "facet", "side", "ours", "unit", "reference", "criterion",
    "accept_low", "accept_high", "verdict", "source", "ref_level",
]  # fmt: skip
#: the quantities of the outcome table and their references' quantities (``rom``: one direction)
QUANTITIES = {
    "intradiscal_pressure": ("MPa", ("intradiscal_pressure",)),
    "facet_force": ("N", ("facet_force",)),
    "lumbar_total_rom": ("deg", ("rom", "rom_full")),
    "segmental_rom_same_geometry": ("deg", ("rom", "rom_full")),
}


def reference_intervals(refs: pd.DataFrame, moment_nmm: float, acceptance_sd: float) -> pd.DataFrame:
    """One row per reference of the long table `refs` under the run's loading: a load direction (not an in-vivo
    posture), no preload and the moment `moment_nmm`, or an unstated moment (then reported, not judged).  Columns:
    its key (source, level, motion, quantity, facet, condition, unit), the reference as text, the criterion, the
    accepted interval and whether it is judged (see the module docstring)."""
    cols = ["source", "level", "motion", "quantity", "facet", "condition", "unit"]
    out_cols = cols + ["reference", "criterion", "accept_low", "accept_high", "judged"]
    if refs is None or not len(refs):
        return pd.DataFrame(columns=out_cols)
    r = refs.assign(**{c: refs[c] if c in refs else "" for c in ("facet", "condition")})
    moment = pd.to_numeric(r.get("moment_nmm", np.nan), errors="coerce")
    preload = pd.to_numeric(r.get("preload_n", np.nan), errors="coerce").fillna(0.0)
    keep = (preload == 0.0) & r["motion"].isin(LOAD_DIRECTIONS)
    # the moment is part of a reference's key (-1: not stated): one source's values under two moments are two
    # references, and only the run's own is judged
    r = r[keep].assign(moment=moment[keep].fillna(-1.0))
    if not len(r):
        return pd.DataFrame(columns=out_cols)
    # a force the source gives without naming the side is compared with our mean of the two sides
    r = r.assign(facet=r["facet"].fillna("").replace("unspecified", ""), condition=r["condition"].fillna(""))
    key = cols + ["moment"]
    wide = r.pivot_table(index=key, columns="statistic", values="value", aggfunc="first").reset_index()
    rows = []
    for w in wide.to_dict("records"):
        has = {k for k, v in w.items() if k not in key and np.isfinite(v)}
        m = w["moment"]
        hidden = not np.isclose(m, moment_nmm)
        if hidden:  # another moment or none stated: shown beside ours, never judged
            has -= {"sd", "min", "max", "low", "high"}
        if not has:
            continue
        if {"median", "min", "max"} <= has:
            lo, hi, text = w["min"], w["max"], f"{w['median']:g} ({w['min']:g}–{w['max']:g})"
            crit = "median; inside its min–max"
        elif {"mean", "sd"} <= has:
            lo, hi = w["mean"] - acceptance_sd * w["sd"], w["mean"] + acceptance_sd * w["sd"]
            text, crit = f"{w['mean']:g} ± {w['sd']:g}", f"mean ± {acceptance_sd:g} SD"
        elif {"low", "high"} <= has or {"min", "max"} <= has:
            a, b = ("low", "high") if {"low", "high"} <= has else ("min", "max")
            lo, hi, text, crit = w[a], w[b], f"{w[a]:g}–{w[b]:g}", "inside the range"
        else:
            stat = sorted(has)[0]
            lo = hi = np.nan
            text = f"{w[stat]:g} ({stat})"
            crit = (
                "one value: reported, not judged"
                if not hidden
                else "moment not stated: reported, not judged"
                if m < 0
                else f"at {m / 1000:g} N·m, not {moment_nmm / 1000:g}: reported, not judged"
            )
        rows.append({**{c: w[c] for c in cols}, "reference": text, "criterion": crit, "accept_low": lo,
                     "accept_high": hi, "judged": bool(np.isfinite(lo))})  # fmt: skip
    return pd.DataFrame(rows, columns=out_cols)


def compared_level(level: str) -> str:
    """The joint a facet-force reference over a span is compared at: its lowest segment ('T12-L2' -> 'L1-L2')."""
    up, lo = level.split("-")
    if lo in COLUMN and up in COLUMN and COLUMN.index(lo) - COLUMN.index(up) > 1:
        return f"{COLUMN[COLUMN.index(lo) - 1]}-{lo}"
    return level


def _full_load(table: pd.DataFrame, mode: str) -> pd.DataFrame:
    """The intact rows of extraction `mode`, a case short of the full moment dropped."""
    t = table[(table["mode"] == mode) & (table["variant"] == "intact")]
    return t[t["load_fraction"] >= 1.0 - 1e-6] if "load_fraction" in t else t


def idp_value(idp: pd.DataFrame, level: str, motion: str, facet: str = "", mode: str = "lumbar") -> float:
    """Nucleus pressure (MPa) of disc `level` in `motion` (mean over its load cases; NaN if one is missing)."""
    t = _full_load(idp, mode)
    by_case = dict(zip(t.loc[t["disc"] == level, "load_case"], t.loc[t["disc"] == level, "pressure_mpa"]))
    vals = [by_case.get(c, np.nan) for c in CASES.get(motion, ())]
    return float(np.mean(vals)) if vals else np.nan


def facet_value(facets: pd.DataFrame, level: str, motion: str, facet: str = "", mode: str = "lumbar") -> float:
    """Contact force (N) of joint `level` in `motion` on `facet` (see the module docstring): '' = mean of both
    joints, 'ipsilateral' / 'contralateral' relative to each one-sided case, 'left' / 'right' by side."""
    t = _full_load(facets, mode)
    t = t[t["joint"] == level].groupby(["load_case", "side"])["force_n"].sum(min_count=1)
    force = t.to_dict()
    vals = []
    for case in CASES.get(motion, ()):
        ipsi = IPSILATERAL.get(case)
        if facet in ("left", "right"):
            sides = ["L" if facet == "left" else "R"]
        elif facet in ("ipsilateral", "contralateral") and ipsi:
            sides = [ipsi if facet == "ipsilateral" else {"L": "R", "R": "L"}[ipsi]]
        elif facet == "":
            sides = ["L", "R"]
        else:
            return np.nan
        vals += [force.get((case, s), np.nan) for s in sides]
    return float(np.mean(vals)) if vals else np.nan


def rom_value(table: pd.DataFrame, level: str, motion: str, side: str, mode: str = "lumbar") -> float:
    """ROM (deg) of segment `level` or of the span L1-L5 (the sum of its segments per load case), in the
    convention `side` ('one': one direction, both sides' mean; 'full': both directions added)."""
    t = _full_load(table, mode)
    if level == "L1-L5":
        seg = t[t["segment"].isin(L1_L5)]
        if seg.groupby("load_case")["segment"].nunique().lt(len(L1_L5)).any():
            return np.nan
        t = seg.groupby("load_case", as_index=False)["rom_deg"].sum().assign(segment=level, mode=mode, variant="intact")
    return model_value_deg(t, level, motion, side, mode)


def _judge(ours: float, ref: dict | None) -> str:
    if ref is None:
        return "no reference obtained"
    if not ref["judged"] or not np.isfinite(ours):
        return "not judged"
    return "yes" if ref["accept_low"] <= ours <= ref["accept_high"] else "no"


def compare_quantity(quantity: str, keys: list[tuple], value, refs: pd.DataFrame) -> pd.DataFrame:
    """Rows of one quantity: for every key (level, motion, facet, side) of ours and of the references (judged by
    `reference_intervals`), our value `value(level, motion, facet, side)` and each matching reference's verdict."""
    unit, _ = QUANTITIES[quantity]
    refs = refs.assign(
        cmp_level=[compared_level(lv) if quantity == "facet_force" else lv for lv in refs["level"]],
        side=["full" if q == "rom_full" else ("one" if q == "rom" else "") for q in refs["quantity"]],
    )
    matched = {}
    for r in refs.to_dict("records"):
        matched.setdefault((r["cmp_level"], r["motion"], r["facet"], r["side"]), []).append(r)
    rows = []
    for key in dict.fromkeys([*keys, *matched]):
        ours = value(*key)
        for ref in matched.get(key, [None]):
            rows.append(
                {
                    "quantity": quantity,
                    "level": key[0],
                    "motion": key[1],
                    "facet": key[2],
                    "side": key[3],
                    "ours": round(ours, 4) if np.isfinite(ours) else np.nan,
                    "unit": unit,
                    "reference": ref["reference"] if ref else "",
                    "criterion": ref["criterion"] if ref else "",
                    "accept_low": ref["accept_low"] if ref else np.nan,
                    "accept_high": ref["accept_high"] if ref else np.nan,
                    "verdict": _judge(ours, ref),
                    "source": (f"{ref['source']} ({ref['condition']})" if ref["condition"] else ref["source"])
                    if ref
                    else "",
                    "ref_level": ref["level"] if ref else "",
                }
            )
    return pd.DataFrame(rows, columns=COLUMNS)


def ordering_rows(table: pd.DataFrame, mode: str = "lumbar") -> pd.DataFrame:
    """The physiological orderings of every lumbar segment of the lumbar model (`spinecohort.rom.compare.orderings`)
    as judged rows: flexion > extension and axial rotation < lateral bending (one side, deg)."""
    order = orderings(table[table["variant"] == "intact"], mode=mode)
    rows = []
    src = "Niosi et al. 2006 Eur Spine J 15:913 (L3-L4, intact)"
    for o in order.to_dict("records"):
        for motion, diff, ok in (
            ("flexion > extension", o["flexion_minus_extension_deg"], o["flexion_gt_extension"]),
            ("axial rotation < lateral bending", o["lateral_minus_axial_deg"], o["axial_lt_lateral"]),
        ):
            rows.append(
                {
                    "quantity": "ordering",
                    "level": o["segment"],
                    "motion": motion,
                    "facet": "",
                    "side": "one",
                    "ours": diff,
                    "unit": "deg",
                    "reference": "F − E > 0" if motion[0] == "f" else "LB − AR > 0",
                    "criterion": "difference > 0",
                    "accept_low": 0.0,
                    "accept_high": np.inf,
                    "verdict": ("yes" if ok else "no") if np.isfinite(diff) else "not judged",
                    "source": src,
                    "ref_level": "",
                }  # fmt: skip
            )
    return pd.DataFrame(rows, columns=COLUMNS)


def extraction(table: pd.DataFrame) -> str:
    """The extraction the outcomes come from: the lumbar model if the run has one, else the functional units."""
    return "lumbar" if (table["mode"] == "lumbar").any() else "unit"


def outcomes(
    table: pd.DataFrame,
    idp: pd.DataFrame,
    facets: pd.DataFrame,
    references: dict[str, pd.DataFrame],
    moment_nmm: float,
    acceptance_sd: float,
) -> pd.DataFrame:
    """Every outcome row (`COLUMNS`) of the lumbar model: nucleus pressure of each lumbar disc, facet force of each
    joint, L1-L5 total ROM, segmental ROM L1-S1 beside the same-geometry model, then the orderings.
    references: quantity of `QUANTITIES` -> long reference table (`spinecohort.rom.references` accessors)."""
    mode = extraction(table)
    discs = sorted({d for d in idp.loc[idp["mode"] == mode, "disc"] if d.startswith("L")}) if len(idp) else []
    joints = facets.loc[facets["mode"] == mode, "joint"].drop_duplicates().tolist() if len(facets) else []
    segs = [s for s in ("L1-L2", "L2-L3", "L3-L4", "L4-L5", "L5-S1") if (table["segment"] == s).any()]
    facet_keys = [("flexion", ""), ("extension", "")] + [
        (m, f) for m in ("lateral_bending", "axial_rotation") for f in ("ipsilateral", "contralateral")
    ]
    spec = {
        "intradiscal_pressure": ([(d, m, "", "") for d in discs for m in MOTIONS], lambda lv, m, f, s: idp_value(idp, lv, m, f, mode)),
        "facet_force": ([(j, m, f, "") for j in joints for m, f in facet_keys], lambda lv, m, f, s: facet_value(facets, lv, m, f, mode)),
        "lumbar_total_rom": ([("L1-L5", m, "", "one") for m in MOTIONS], lambda lv, m, f, s: rom_value(table, lv, m, s, mode)),
        "segmental_rom_same_geometry": ([(g, m, "", "one") for g in segs for m in MOTIONS], lambda lv, m, f, s: rom_value(table, lv, m, s, mode)),
    }  # fmt: skip
    parts = []
    for quantity, (keys, value) in spec.items():
        refs = references.get(quantity)
        if refs is not None and len(refs):
            refs = refs[refs["quantity"].isin(QUANTITIES[quantity][1])]
        refs = reference_intervals(refs, moment_nmm, acceptance_sd)
        parts.append(compare_quantity(quantity, keys, value, refs))
    parts.append(ordering_rows(table, mode))
    return pd.concat([p for p in parts if len(p)], ignore_index=True)


#: section headings of the outcome table's Markdown, by quantity
HEADINGS = {
    "intradiscal_pressure": "Intradiscal pressure (nucleus)",
    "facet_force": "Facet joint forces (contact struts and extension stops)",
    "lumbar_total_rom": "L1–L5 total range of motion",
    "segmental_rom_same_geometry": "Segmental ROM L1–S1 beside the same-geometry model (Remus et al. 2021) and in vitro (Yamamoto et al. 1989)",
    "ordering": "Physiological orderings",
}


def _cell(v, fmt: str = ".2f") -> str:
    return "—" if v is None or (isinstance(v, float) and not np.isfinite(v)) or v == "" else format(v, fmt)


def outcomes_markdown(out: pd.DataFrame, idp: pd.DataFrame, facets: pd.DataFrame) -> str:
    """The outcome table as Markdown sections (ours, reference, criterion, accepted, verdict, source) with a count
    of what was judged, and the per-case nucleus pressures and facet forces (of the lumbar model, else the units)."""
    mode = extraction(idp) if len(idp) else "lumbar"
    lines = [f"Beyond ROM, from the {'lumbar model' if mode == 'lumbar' else 'functional units'}, intact.", ""]
    for quantity, heading in HEADINGS.items():
        sub = out[out["quantity"] == quantity]
        if not len(sub):
            continue
        unit = sub["unit"].iloc[0]
        lines += [f"## {heading}", "", f"| level | motion | facet | ours ({unit}) | reference | criterion | accepted | "
                  "verdict | source |", "|---|---|---|--:|---|---|---|---|---|"]  # fmt: skip
        for r in sub.itertuples():
            acc = f"{_cell(r.accept_low)}–{_cell(r.accept_high)}" if np.isfinite(r.accept_low) else "—"
            acc = f"> {_cell(r.accept_low)}" if np.isinf(r.accept_high) else acc
            level = r.level if not r.ref_level or r.ref_level == r.level else f"{r.level} (ref. {r.ref_level})"
            lines.append(
                f"| {level} | {r.motion} | {r.facet or '—'} | {_cell(r.ours)} | {r.reference or '—'} | "
                f"{r.criterion or '—'} | {acc} | {r.verdict} | {r.source or '—'} |"
            )
        judged = sub["verdict"].isin(["yes", "no"])
        lines += ["", f"Judged: {int((sub['verdict'] == 'yes').sum())} of {int(judged.sum())} in range; "
                  f"{int((sub['verdict'] == 'no reference obtained').sum())} without a reference, "
                  f"{int((sub['verdict'] == 'not judged').sum())} reported, not judged.", ""]  # fmt: skip
        if quantity == "intradiscal_pressure" and len(idp):
            lines += [
                "Nucleus pressure per load case (MPa):",
                "",
                _pivot_md(idp, mode, "disc", "pressure_mpa", "{:.3f}"),
                "",
            ]
        if quantity == "facet_force" and len(facets):
            lines += ["Facet force per load case (N, contact struts + extension stop; L/R = left/right joint):", "",
                      _facet_md(facets, mode), ""]  # fmt: skip
    return "\n".join(lines) + "\n"


def _case_order(cases) -> list[str]:
    """The load cases present, flexion first (`CASES`' order)."""
    order = [c for cases_of in CASES.values() for c in cases_of]
    return sorted(set(cases), key=lambda c: order.index(c) if c in order else len(order))


def _facet_md(facets: pd.DataFrame, mode: str) -> str:
    """The per-case facet forces as Markdown: one row per joint side, '<contact> + <stop>' per load case (N)."""
    f = facets[(facets["mode"] == mode) & (facets["variant"] == "intact")]
    wide = f.pivot_table(index=["joint", "side"], columns=["load_case", "kind"], values="force_n", sort=False)
    cases = _case_order(f["load_case"])
    rows = ["| joint | side | " + " | ".join(cases) + " |", "|---|---|" + "--:|" * len(cases)]
    for (joint, side), r in wide.iterrows():
        cells = [" + ".join(f"{r.get((c, k), np.nan):.1f}" for k in ("joint", "tip") if (c, k) in r) for c in cases]
        rows.append(f"| {joint} | {side} | " + " | ".join(cells) + " |")
    return "\n".join(rows)


def _pivot_md(t: pd.DataFrame, mode: str, index: str, value: str, fmt: str) -> str:
    """A per-case table of extraction `mode` as Markdown: rows `index`, columns the load cases."""
    t = t[(t["mode"] == mode) & (t["variant"] == "intact")]
    wide = t.pivot_table(index=index, columns="load_case", values=value, aggfunc="first", sort=False)
    wide = wide.loc[sorted(wide.index, key=lambda lv: COLUMN.index(lv.split("-")[0])), _case_order(wide.columns)]
    head = "| " + index + " | " + " | ".join(map(str, wide.columns)) + " |"
    rows = [head, "|---|" + "--:|" * len(wide.columns)]
    for k, r in wide.iterrows():
        rows.append(f"| {k} | " + " | ".join("—" if not np.isfinite(v) else fmt.format(v) for v in r) + " |")
    return "\n".join(rows)
