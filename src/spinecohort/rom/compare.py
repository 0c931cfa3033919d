"""Comparison of a ROM table (`spinecohort.rom.run.solve_model`) with in-vitro references.

Two criteria are reported side by side (docs/explanation/validation.md):

* **calibration criterion** (``in_range``): a mean +- SD reference accepts mean +- ``acceptance_sd`` SD
  (config ``rom.acceptance_sd``, 1 SD); a range reference whose specimens kept their costovertebral joints
  (``rib_heads: true``, Wilke et al. 2017) is widened by the measured effect of removing the rib heads,
  because the model has none: ``low * (1 + f_low) .. high * (1 + f_high)`` with the factors per motion plane
  of ``rom.rib_correction`` (Liebsch & Wilke 2020, single thoracic segments, ribs kept -> removed: F/E +7 %,
  LB +10..12 %, AR +11..19 %);
* **seed criterion** (``in_range_seed``): mean +- ``seed_acceptance_sd`` SD (2 SD) and the raw range.

Units: degrees, N.mm.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from spinecohort.rom.deck import PLANES

#: the plane of every motion a reference may name (a load case belongs to its plane)
PLANE_OF = {c: p for p, cases in PLANES.items() for c in cases} | {p: p for p in PLANES}


def model_value_deg(
    table: pd.DataFrame, segment: str, motion: str, side: str, mode: str, variant: str = "intact"
) -> float:
    """Our ROM (deg) in a reference's convention: one load case, or a plane's full range (sum of both
    sides) / one-side mean.  NaN if the table lacks a needed load case."""
    rows = table[(table["segment"] == segment) & (table["mode"] == mode) & (table["variant"] == variant)]
    if "load_fraction" in rows:  # a case stopped short of the full moment is not comparable
        rows = rows[rows["load_fraction"] >= 1.0 - 1e-6]
    by_case = dict(zip(rows["load_case"], rows["rom_deg"]))
    cases = PLANES.get(motion, (motion,))
    if any(c not in by_case for c in cases):
        return float("nan")
    vals = [by_case[c] for c in cases]
    if motion in PLANES:
        return float(sum(vals)) if side == "full" else float(np.mean(vals))
    if side == "full":
        raise ValueError(f"reference for {segment} {motion}: a single load case cannot be a full range")
    return float(vals[0])


def accepted_interval(
    ref: dict, acceptance_sd: float, rib_correction: dict | None = None
) -> tuple[float, float, float, str]:
    """(low, high, centre, criterion text) of a reference: mean +- acceptance_sd SD, or its range, widened
    by ``rib_correction[plane] = (f_low, f_high)`` when the specimens kept their rib heads and the model has
    none (``ref['rib_heads']``)."""
    if ref["statistic"] == "mean_sd":
        c, s = float(ref["value"]), float(ref["sd"])
        return c - acceptance_sd * s, c + acceptance_sd * s, c, f"mean ± {acceptance_sd:g} SD"
    low, high = float(ref["low"]), float(ref["high"])
    if ref.get("rib_heads") and rib_correction:
        f_lo, f_hi = rib_correction[PLANE_OF[ref["motion"]]]
        low, high = low * (1.0 + f_lo), high * (1.0 + f_hi)
        pct = f"+{100 * f_lo:.0f} %" if f_lo == f_hi else f"+{100 * f_lo:.0f} / +{100 * f_hi:.0f} %"
        text = f"range {pct} (no rib heads)"
        return low, high, 0.5 * (low + high), text
    return low, high, float(ref.get("value", 0.5 * (low + high))), "range"


def validate(
    table: pd.DataFrame,
    references: list[dict],
    moment_nmm: float,
    acceptance_sd: float = 1.0,
    rib_correction: dict | None = None,
    seed_acceptance_sd: float = 2.0,
) -> pd.DataFrame:
    """One row per reference and extraction (mode, variant) that has its segment: our value, the accepted
    interval of the calibration criterion (`accepted_interval` with ``acceptance_sd`` and ``rib_correction``)
    and of the seed's (``seed_acceptance_sd``, raw ranges), in_range / in_range_seed, and the distance from
    the criterion's centre.  The ``rib_heads`` variant (units solved with the specimens' rib heads,
    `spinecohort.rom.ribs`) is judged against the raw ranges: it has what the specimens had.  References at
    another moment are listed with in_range empty (not judged)."""
    rows = []
    variants = set(table["variant"]) if "variant" in table else {"intact"}
    for ref in references:
        for mode, variant in (("lumbar", "intact"), ("unit", "intact"), ("unit", "rib_heads")):
            here = (table["segment"] == ref["segment"]) & (table["mode"] == mode)
            if variant not in variants or not here.any():
                continue
            solved = variant
            if variant == "rib_heads":
                if not ref.get("rib_heads"):
                    continue
                # a disc no rib bridges (T10-T11: rib 11 articulates with T11 only) was tested as the model is
                solved = variant if (here & (table["variant"] == variant)).any() else "intact"
            ours = model_value_deg(table, ref["segment"], ref["motion"], ref["side"], mode, solved)
            corr = rib_correction if variant == "intact" else None
            low, high, centre, criterion = accepted_interval(ref, acceptance_sd, corr)
            if variant == "rib_heads":
                criterion += " (model with rib heads)" if solved == variant else " (no rib bridges this disc)"
            s_low, s_high, _, _ = accepted_interval(ref, seed_acceptance_sd, None)
            judged = abs(ref["moment_nmm"] - moment_nmm) < 1e-6 and np.isfinite(ours)
            rows.append(
                {
                    "segment": ref["segment"],
                    "motion": ref["motion"],
                    "side": ref["side"],
                    "mode": mode,
                    "variant": variant,
                    "model_deg": round(ours, 3),
                    "ref_statistic": ref["statistic"],
                    "ref_value": ref.get("value"),
                    "ref_sd": ref.get("sd"),
                    "ref_low": ref.get("low"),
                    "ref_high": ref.get("high"),
                    "criterion": criterion,
                    "accept_low": round(low, 3),
                    "accept_high": round(high, 3),
                    "in_range": bool(low <= ours <= high) if judged else None,
                    "distance_deg": round(ours - centre, 3),
                    "seed_low": round(s_low, 3),
                    "seed_high": round(s_high, 3),
                    "in_range_seed": bool(s_low <= ours <= s_high) if judged else None,
                    "ref_moment_nmm": ref["moment_nmm"],
                    "source": ref["source"],
                }
            )
    return pd.DataFrame(rows)


def orderings(table: pd.DataFrame, segments: list[str] | None = None, mode: str = "lumbar") -> pd.DataFrame:
    """Physiological orderings per lumbar segment (Niosi et al. 2006, intact L3-L4: flexion 3.7 > extension
    3.3 deg one side; axial rotation 2.1 < lateral bending 3.8 deg one side): flexion - extension and
    lateral bending - axial rotation (one-side means, deg), and whether each is > 0."""
    rows = []
    segs = segments or sorted(
        {s for s in table.loc[table["mode"] == mode, "segment"] if s.startswith("L")}, key=lambda s: s
    )
    for seg in segs:
        f = model_value_deg(table, seg, "flexion", "one", mode)
        e = model_value_deg(table, seg, "extension", "one", mode)
        lb = model_value_deg(table, seg, "lateral_bending", "one", mode)
        ar = model_value_deg(table, seg, "axial_rotation", "one", mode)
        rows.append(
            {
                "segment": seg,
                "mode": mode,
                "flexion_minus_extension_deg": round(f - e, 3),
                "flexion_gt_extension": bool(f > e),
                "lateral_minus_axial_deg": round(lb - ar, 3),
                "axial_lt_lateral": bool(ar < lb),
            }
        )
    return pd.DataFrame(rows)


def all_effect(table: pd.DataFrame) -> pd.DataFrame:
    """Extension ROM with and without the ALL per segment (deg) and the increase without it."""
    ext = table[(table["load_case"] == "extension") & table["variant"].isin(["intact", "no_ALL"])]
    if "no_ALL" not in set(ext["variant"]):
        return ext.iloc[0:0]
    wide = ext.pivot_table(index=["mode", "unit", "segment"], columns="variant", values="rom_deg").reset_index()
    wide["increase_deg"] = wide["no_ALL"] - wide["intact"]
    return wide


def validate_from_config(table: pd.DataFrame, rom: dict) -> pd.DataFrame:
    """`validate` with the config's ``rom`` block (references, moment, acceptance_sd, rib_correction,
    seed_acceptance_sd)."""
    return validate(
        table,
        rom["references"],
        rom["moment_nmm"],
        rom["acceptance_sd"],
        {k: tuple(v) for k, v in rom["rib_correction"].items()},
        rom["seed_acceptance_sd"],
    )


def with_rib_heads(val: pd.DataFrame) -> pd.DataFrame | None:
    """The comparisons as the specimens were tested: every intact row, except that a unit row whose
    (segment, motion) was also solved with the rib heads is replaced by that row.  None without such rows."""
    if "variant" not in val or not (val["variant"] == "rib_heads").any():
        return None
    ribs = val[val["variant"] == "rib_heads"]
    have = set(zip(ribs["segment"], ribs["motion"]))
    intact = val[val["variant"] == "intact"]
    keep = ~((intact["mode"] == "unit") & np.array([k in have for k in zip(intact["segment"], intact["motion"])]))
    return pd.concat([intact[keep], ribs], ignore_index=True)


def validation_markdown(val: pd.DataFrame) -> str:
    """The validation table as the Markdown docs/explanation/validation.md shows (so the documented table is the
    code's own output): ours, reference, both criteria, in range, distance from the criterion's centre."""

    def ref_text(r) -> str:
        if r.ref_statistic == "mean_sd":
            return f"{r.ref_value:g} ± {r.ref_sd:g}"
        return f"{r.ref_low:g}–{r.ref_high:g}"

    def yes(v) -> str:
        return "—" if v is None or (isinstance(v, float) and np.isnan(v)) else ("yes" if bool(v) else "no")

    lines = [
        "| segment | motion | side | mode | ours (deg) | reference | criterion | accepted | in range | "
        "seed criterion (±2 SD / raw) | in range (seed) | ours − centre |",
        "|---|---|---|---|--:|---|---|---|---|---|---|--:|",
    ]

    def num(v: float, fmt: str) -> str:
        return "—" if not np.isfinite(v) else format(v, fmt)

    variant = val["variant"] if "variant" in val else pd.Series("intact", index=val.index)
    for r, v in zip(val.itertuples(), variant):
        mode = r.mode + (" + rib heads" if v == "rib_heads" else "")
        lines.append(
            f"| {r.segment} | {r.motion} | {r.side} | {mode} | {num(r.model_deg, '.2f')} | {ref_text(r)} | {r.criterion} | "
            f"{r.accept_low:.2f}–{r.accept_high:.2f} | {yes(r.in_range)} | {r.seed_low:.2f}–{r.seed_high:.2f} | "
            f"{yes(r.in_range_seed)} | {num(r.distance_deg, '+.2f')} |"
        )
    lines.append("")
    for label, sub in (("", val[variant == "intact"]), ("with rib heads", with_rib_heads(val))):
        if label and sub is None:
            continue
        judged = sub["in_range"].notna()
        short = int((~judged).sum())
        lines.append(
            (f"In range, {label} in the thoracic units (raw ranges): " if label else "In range: ")
            + f"{int(sub.loc[judged, 'in_range'].astype(bool).sum())} of {int(judged.sum())} judged "
            f"(seed criterion: {int(sub.loc[judged, 'in_range_seed'].astype(bool).sum())})"
            + (f"; {short} not judged (a load case short of the full moment, or another moment)." if short else ".")
        )
    return "\n".join(lines) + "\n"
