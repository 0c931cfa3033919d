"""Parameter tables: the sheet-versus-measurement comparison and the Descriptive_List workbook."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from spinecohort.atomic import atomic_write
from spinecohort.measure.spinopelvic import UNITS, parameter_table_header
from spinecohort.store.columns import CONTACT_SUMMARY, QUALITY_SUMMARY

NOTES = [
    ("model_id / ID", "", "virtual model index (sum over modes of (w_i + 3) * 7^(5 - i)) / patient ID"),
    (
        "PI, PT, SS",
        "deg",
        "pelvic incidence, tilt, sacral slope; signed, PI = PT + SS; PT > 0 when S1 is behind the hip axis",
    ),
    (
        "LL, LL_L4S1, LL_L1L5",
        "deg",
        "lumbar lordosis L1-S1 (GAP's), L4-S1, L1-L5 (superior to inferior endplates); + = lordosis",
    ),
    (
        "PI_minus_LL, LL_minus_PI",
        "deg",
        "mismatch; the seed's column 'LL-PI' is LL_minus_PI (its inclusion criterion means PI_minus_LL > 10)",
    ),
    (
        "GT, GT_T1",
        "deg",
        "global tilt with the C7 proxy named in GT_proxy (C7 is not modelled), and with the T1 centre",
    ),
    ("T1SPI, TPA", "deg", "T1 spinopelvic inclination, T1 pelvic angle = PT + T1SPI"),
    ("TK_*", "deg", "thoracic kyphosis between superior endplate of the first and inferior endplate of the last level"),
    (
        "Cobb, Cobb2",
        "deg",
        "main / largest secondary coronal curve (endplate tilts), end and apex levels in Cobb_upper/lower/apex",
    ),
    ("RPV, RLL, RSA", "deg", "GAP relative pelvic version, lumbar lordosis, spinopelvic alignment"),
    ("LDI", "%", "lordosis distribution index 100 L4-S1 / L1-S1; NaN (LDI_undefined) when LL <= 1 deg"),
    (
        "GAP, GAP_noage, GAP_assumed_age",
        "points",
        "GAP score with the patient's age / without the age term / with the assumed age",
    ),
    (
        "SVA_T1, SVA_C7est",
        "mm",
        "sagittal offset proxies: T1 / extrapolated C7 centre ahead of the S1 posterosuperior corner",
    ),
    ("DH_, DHa_, DHp_<disc>", "mm", "central, anterior and posterior disc heights"),
    ("FH_radius_L/R, HA_width", "mm", "femoral head radii (sphere fits), distance between the head centres"),
    (
        "pers_fit_*, pers_proj_*",
        "SD / deg / mm",
        "personalized models (personalized/personalization.csv): mode "
        "weights b, fitted posture, achieved - target error per fitted parameter, per-vertex distance to the patient's "
        "aligned shape; fit = weights fitted to the parameters (the <ID>.inp model), proj = projection of the shape",
    ),
]


def compare_with_sheet(measured: pd.DataFrame, sheet: pd.DataFrame) -> pd.DataFrame:
    """Per numeric parameter present in both tables: mean signed, mean and max absolute differences
    (sheet - measured), in the parameter's unit.  For the synthetic cohort the sheet holds the generator's
    true values, so this is the measurement error."""
    m = measured.set_index("ID")
    s = sheet.set_index("ID").loc[m.index]
    rows = []
    for col in m.columns:
        if (
            col in s.columns
            and col != "age"
            and pd.api.types.is_numeric_dtype(m[col])
            and pd.api.types.is_numeric_dtype(s[col])
        ):
            d = (s[col].astype(float) - m[col].astype(float)).to_numpy()
            d = d[np.isfinite(d)]
            if len(d):
                rows.append((col, UNITS.get(col, ""), len(d), d.mean(), np.abs(d).mean(), np.abs(d).max()))
    return pd.DataFrame(rows, columns=["parameter", "unit", "n", "mean_diff", "mean_abs_diff", "max_abs_diff"])


def write_descriptive_list(
    path: str | Path, patients: pd.DataFrame | None = None, virtual: pd.DataFrame | None = None
) -> None:
    """``Descriptive_List.xlsx``: sheet 1 the virtual cohort, sheet 2 the patients (as in the seed), then a
    notes sheet with units and definitions; headers carry units, e.g. ``PI [deg]``."""
    with atomic_write(path) as tmp, pd.ExcelWriter(tmp, engine="openpyxl") as xl:
        for name, df in (("Virtual cohort", virtual), ("Patients", patients)):
            if df is None:
                continue
            parameter_table_header(df).to_excel(xl, sheet_name=name, index=False, float_format="%.4f")
            ws = xl.sheets[name]
            ws.freeze_panes = "B2"
            for cell in ws[1]:
                cell.font = cell.font.copy(bold=True)
        pd.DataFrame(NOTES, columns=["columns", "unit", "definition"]).to_excel(xl, sheet_name="Notes", index=False)


def virtual_cohort_table(params: list[pd.DataFrame], quality: list[pd.DataFrame]) -> pd.DataFrame:
    """All shards' parameter tables (model_id as ``model_NNNNN``, weights, parameters) joined with the
    quality summary columns of their Jacobian check / repair, sorted by model ID."""
    p = pd.concat(params, ignore_index=True)
    q = pd.concat(quality, ignore_index=True)
    cols = QUALITY_SUMMARY + [c for c in CONTACT_SUMMARY if c in q.columns]
    q = q.assign(model_id=[f"model_{int(i):05d}" for i in q["model_id"]])[["model_id", *cols]]
    dup = p["model_id"].duplicated()
    if dup.any():
        raise ValueError(f"duplicate model IDs in the shard tables, e.g. {p.loc[dup, 'model_id'].iloc[0]}")
    out = p.merge(q, on="model_id", how="left", validate="one_to_one")
    missing = out["min_sj_after"].isna()
    if missing.any():
        raise ValueError(
            f"{int(missing.sum())} models have no quality row, e.g. {out.loc[missing, 'model_id'].iloc[0]}"
        )
    return out.sort_values("model_id", ignore_index=True)


def tri_vs_hex_summary(diffs: list[pd.DataFrame]) -> pd.DataFrame:
    """Per parameter over all shards: max |tri - hex| and its mean over every model, in its unit: the shards'
    means weighted by their ``n_models`` (shards differ in size: the default's 8,407 and 8,400 models; a table
    without the column counts each shard whose mean exists once)."""
    d = pd.concat(diffs, ignore_index=True)
    n = d["n_models"] if "n_models" in d else d["mean_abs_diff"].notna().astype(float)  # 0 where the mean is NaN
    d = d.assign(_n=n, _sum=d["mean_abs_diff"].fillna(0.0) * n)
    out = (
        d.groupby("parameter", sort=False)
        .agg(max_abs_diff=("max_abs_diff", "max"), _sum=("_sum", "sum"), _n=("_n", "sum"))
        .reset_index()
    )
    out["mean_abs_diff"] = out["_sum"] / out["_n"].where(out["_n"] > 0)  # no model measured it: NaN
    out = out.drop(columns=["_sum", "_n"])
    out.insert(1, "unit", [UNITS.get(c, "") for c in out["parameter"]])
    return out


#: prefix of each personalization method's columns in the Patients sheet
PERSONALIZATION_PREFIX = {"fit": "pers_fit", "projection": "pers_proj"}


def with_personalization(patients: pd.DataFrame, personalization: pd.DataFrame) -> pd.DataFrame:
    """Patient sheet plus, per personalization method, its weights, posture, achieved-minus-target error of
    every fitted parameter and shape distances, with units in the headers, e.g. ``pers_fit_b1 [SD]``,
    ``pers_fit_PI_error [deg]``, ``pers_proj_dist_mean [mm]`` (``personalize.cohort.personalize_cohort`` table)."""
    out = patients.copy()
    for method, prefix in PERSONALIZATION_PREFIX.items():
        g = personalization[personalization["method"] == method].set_index("ID")
        if g.empty:
            continue
        cols = {}
        for c in g.columns:
            if c.startswith("b") and c[1:].isdigit():
                cols[c] = f"{prefix}_{c} [SD]"
            elif c == "posture_deg":
                cols[c] = f"{prefix}_posture [deg]"
            elif c.endswith("_error") and c[:-6] in UNITS:
                cols[c] = f"{prefix}_{c} [{UNITS[c[:-6]]}]"
            elif c in ("dist_mean_mm", "dist_max_mm"):
                cols[c] = f"{prefix}_{c[:-3]} [mm]"
            elif c == "invalid_after":
                cols[c] = f"{prefix}_inverted_hexes"
        # columns without content for this method (a projection has no posture and no FE model) are left out
        keep = [c for c in cols if g[c].notna().any() and not (c == "posture_deg" and (g[c] == 0).all())]
        g = g[keep].rename(columns=cols)
        g.index = g.index.astype(str)
        out = out.join(g, on="ID")
    return out


def write_table_twins(df: pd.DataFrame, csv_path: str | Path) -> list[Path]:
    """Write ``df`` as CSV and as a Parquet twin next to it (same stem; pyarrow, typed columns)."""
    csv_path = Path(csv_path)
    written = []
    for path, write in (
        (csv_path, lambda p: df.to_csv(p, index=False, float_format="%.6f")),
        (csv_path.with_suffix(".parquet"), lambda p: df.to_parquet(p, index=False)),
    ):
        with atomic_write(path) as tmp:
            write(tmp)
        written.append(path)
    return written


def parse_range(text: str, name: str = "range") -> tuple[float | None, float | None]:
    """``"50:60"`` -> (50, 60); ``"25:"`` -> (25, None); ``":10"`` -> (None, 10); bounds inclusive."""
    lo, sep, hi = str(text).partition(":")
    try:
        bounds = tuple(float(v) if v.strip() else None for v in (lo, hi))
    except ValueError:
        bounds = None
    if not sep or bounds is None or bounds == (None, None):
        raise ValueError(f"{name}: '{text}' is not a range; write lo:hi, lo: or :hi (e.g. 50:60)")
    if None not in bounds and bounds[0] > bounds[1]:
        raise ValueError(f"{name}: lower bound {bounds[0]} exceeds upper bound {bounds[1]}")
    return bounds


def query_mask(table: pd.DataFrame, ranges: dict[str, tuple[float | None, float | None]]) -> np.ndarray:
    """(rows,) bool: the rows whose every named column lies in its inclusive range (NaN never matches)."""
    keep = np.ones(len(table), bool)
    for col, (lo, hi) in ranges.items():
        if col not in table.columns or not pd.api.types.is_numeric_dtype(table[col]):
            numeric = [c for c in table.columns if pd.api.types.is_numeric_dtype(table[c])]
            raise ValueError(
                f"no numeric column '{col}' in the virtual cohort; columns: {', '.join(numeric[:40])}, ..."
            )
        v = table[col].to_numpy(float)
        keep &= ~np.isnan(v)
        if lo is not None:
            keep &= v >= lo
        if hi is not None:
            keep &= v <= hi
    return keep


def query_models(table: pd.DataFrame, ranges: dict[str, tuple[float | None, float | None]]) -> list[str]:
    """Model IDs of the rows whose every named column lies in its inclusive range (NaN never matches)."""
    if "model_id" not in table.columns:
        raise ValueError("the table has no model_id column (is it the virtual cohort CSV?)")
    return table.loc[query_mask(table, ranges), "model_id"].astype(str).tolist()
