"""Spinopelvic parameters of a batch of spine models, measured on corresponding landmark vertices.

docs/explanation/measurement.md states every definition and choice.  Millimetres and degrees throughout.

Pipeline per batch (all array operations over the B models; only the 17 levels / 17 discs are looped):

1. Endplate planes: total-least-squares fit of every endplate patch (`spinecohort.measure.fits`), normals
   oriented cranially (n.V > 0); the vertex mean is the endplate centre because the patches are sampled
   centrally symmetric.
2. Femoral heads: algebraic sphere fit (`spinecohort.measure.fits`).
3. Patient frame and the parameters' formulas (`spinecohort.measure.formulas`).
4. The rim extremes (disc heights, the S1 posterosuperior corner) and the landmark vertices used one by one,
   gathered once per batch (numba: a gathered float64 copy of every landmark vertex would cost more than the
   measurement).
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numba
import numpy as np

from spinecohort.cohort.landmarks import DISCS, LEVELS, Landmarks, disc_name
from spinecohort.measure import gap_score as _gap
from spinecohort.measure.fits import fit_spheres, plane_fits
from spinecohort.measure.formulas import (
    cobb_angle,
    cor_deg,
    disc_heights_mm,
    global_tilt_deg,
    kyphosis_deg,
    lordosis_deg,
    patient_frame,
    pelvic_incidence_deg,
    pelvic_tilt_deg,
    sacral_slope_deg,
    sag_deg,
    sva_mm,
    t1_pelvic_angle_deg,
    t1_spinopelvic_inclination_deg,
    unsigned_pelvic_incidence_deg,
)

if TYPE_CHECKING:  # the shard jobs measure without pandas (measure_columns)
    import pandas as pd

C7_PROXIES = ("extrapolated", "T1")

_ANGLE_COLS = [
    "PI",
    "PT",
    "SS",
    "LL",
    "LL_L4S1",
    "LL_L1L5",
    "PI_minus_LL",
    "LL_minus_PI",
    "GT",
    "GT_T1",
    "T1SPI",
    "TPA",
    "TK_T1T12",
    "TK_T4T12",
    "TK_T5T12",
    "Cobb",
    "Cobb2",
    "RPV",
    "RLL",
    "RSA",
    "PI_identity_err",
]
_DISC_COLS = [f"{p}_{disc_name(u, l)}" for u, l in DISCS for p in ("DH", "DHa", "DHp")]

#: Unit of every numeric column of :func:`measure` ("" = dimensionless / label).
UNITS: dict[str, str] = {
    **{c: "deg" for c in _ANGLE_COLS},
    "LDI": "%",
    "SVA_T1": "mm",
    "SVA_C7est": "mm",
    "FH_radius_L": "mm",
    "FH_radius_R": "mm",
    "HA_width": "mm",
    "endplate_rms_max": "mm",
    **{c: "mm" for c in _DISC_COLS},
    **{
        c: "points"
        for c in ("RPV_pts", "RLL_pts", "LDI_pts", "RSA_pts", "Age_pts", "GAP_noage", "GAP", "GAP_assumed_age")
    },
}


def parameter_table_header(df: pd.DataFrame) -> pd.DataFrame:
    """Copy of ``df`` with unit-bearing headers for spreadsheets, e.g. ``"PI [deg]"``, ``"DH_L4-L5 [mm]"``."""
    return df.rename(columns={c: f"{c} [{UNITS[c]}]" for c in df.columns if UNITS.get(c)})


class _Block:
    """The landmark vertices of the batch that are used one by one (rims, femoral heads, symphysis) gathered
    once (one fancy-index pass), addressed by set name.

    Coordinates are relative to a per-model local origin (B, 3), so positions from it are only used in
    differences.
    """

    def __init__(self, points: np.ndarray, sets: dict[str, np.ndarray], origin: np.ndarray):
        idx = [np.asarray(i, dtype=np.int64).ravel() for i in sets.values()]
        ends = np.cumsum([len(i) for i in idx])
        self.slices = {k: slice(e - len(i), e) for k, i, e in zip(sets, idx, ends)}
        # one pass: gather, to float64, relative to the origin (a float32 (B, 95k, 3) batch is never copied)
        self.pts = np.empty((points.shape[0], int(ends[-1]) if len(ends) else 0, 3))
        first = _gather_relative_nb(points, np.concatenate(idx), np.ascontiguousarray(origin, dtype=float), self.pts)
        if first >= 0:
            name = next(k for k, sl in self.slices.items() if sl.start <= first < sl.stop)
            raise ValueError(f"non-finite coordinates in landmark set {name}")

    def __getitem__(self, name: str) -> np.ndarray:
        return self.pts[:, self.slices[name]]

    def extremes(self, names: list[str], direction: np.ndarray) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """Per set of ``names``: its vertices with the largest and the smallest projection on ``direction``
        (B, 3), per model (the first one on a tie, like ``argmax``), all sets in one pass."""
        sl = [self.slices[k] for k in names]
        starts = np.array([x.start for x in sl], dtype=np.int64)
        stops = np.array([x.stop for x in sl], dtype=np.int64)
        rows = _extreme_rows_nb(self.pts, starts, stops, np.ascontiguousarray(direction, dtype=float))
        picked = np.take_along_axis(self.pts, rows.reshape(len(rows), -1)[:, :, None], axis=1)
        picked = picked.reshape(len(rows), len(names), 2, 3)
        return {k: (picked[:, j, 0], picked[:, j, 1]) for j, k in enumerate(names)}


@numba.njit(cache=True)
def _gather_relative_nb(points, rows, origin, out):
    """out[b, i] = points[b, rows[i]] - origin[b] in float64 (B, len(rows), 3); returns the first i whose
    gathered coordinates are not finite in some model, else -1."""
    bad = rows.shape[0]
    for b in range(points.shape[0]):
        o0, o1, o2 = origin[b, 0], origin[b, 1], origin[b, 2]
        for i in range(rows.shape[0]):
            r = rows[i]
            x, y, z = np.float64(points[b, r, 0]), np.float64(points[b, r, 1]), np.float64(points[b, r, 2])
            if not (np.isfinite(x) and np.isfinite(y) and np.isfinite(z)) and i < bad:
                bad = i
            out[b, i, 0], out[b, i, 1], out[b, i, 2] = x - o0, y - o1, z - o2
    return bad if bad < rows.shape[0] else -1


@numba.njit(cache=True)
def _extreme_rows_nb(pts, starts, stops, direction):
    """Rows of pts (B, N, 3) with the largest and smallest projection on direction (B, 3) within each row range
    [starts[j], stops[j]) -> (B, J, 2) int64 (first on a tie)."""
    n_models, n_sets = pts.shape[0], starts.shape[0]
    rows = np.empty((n_models, n_sets, 2), dtype=np.int64)
    for b in range(n_models):
        d0, d1, d2 = direction[b, 0], direction[b, 1], direction[b, 2]
        for j in range(n_sets):
            hi = lo = starts[j]
            p_hi = p_lo = pts[b, hi, 0] * d0 + pts[b, hi, 1] * d1 + pts[b, hi, 2] * d2
            for i in range(starts[j] + 1, stops[j]):
                p = pts[b, i, 0] * d0 + pts[b, i, 1] * d1 + pts[b, i, 2] * d2
                if p > p_hi:
                    hi, p_hi = i, p
                if p < p_lo:
                    lo, p_lo = i, p
            rows[b, j, 0], rows[b, j, 1] = hi, lo
    return rows


def measure_columns(
    points,
    landmarks: Landmarks,
    vertical=(0.0, 0.0, 1.0),
    age=None,
    assumed_age: float = 65.0,
    c7_proxy: str = "extrapolated",
    ldi_min_ll_deg: float = _gap.LDI_MIN_LL_DEG,
    ldi_undefined_points: float = 0.0,
    cobb_secondary_min_deg: float = 10.0,
) -> dict[str, np.ndarray]:
    """Measure every spinopelvic parameter of a batch of models in correspondence.

    points: (B, N, 3) or (N, 3) vertex coordinates in mm (RAS); the landmark index sets name the vertices.
    vertical: the "up" direction of the frame (normalised here); positional parameters depend on it.
    age: None (GAP = NaN), a scalar or (B,) ages in years.  assumed_age: age for ``GAP_assumed_age``.
    c7_proxy: "extrapolated" (C7c = 2 T1c - T2c, default) or "T1" (C7c = T1c) for ``GT``; the choice is
        written to ``GT_proxy``.  ``SVA_C7est`` always uses the extrapolated centre, ``SVA_T1`` the T1 centre.
    ldi_min_ll_deg: LDI is NaN (``LDI_undefined``) where LL <= this.  ldi_undefined_points: LDI points there.
    cobb_secondary_min_deg: smallest secondary coronal curve reported in ``Cobb2``.
    Returns the columns (B,) arrays in table order, column units in :data:`UNITS` (:func:`measure`: as a
    DataFrame).
    """
    pts = np.asarray(points)
    if pts.dtype.kind not in "fiu":
        raise ValueError(f"points must be a numeric array, got dtype {pts.dtype}")
    if pts.ndim == 2:
        pts = pts[None]
    if pts.ndim != 3 or pts.shape[2] != 3:
        raise ValueError(f"points must have shape (B, N, 3) or (N, 3), got {np.shape(points)}")
    b, n_vert, _ = pts.shape
    if b == 0:
        raise ValueError("points: empty batch")
    landmarks.validate(n_vert, "measure landmarks")
    if c7_proxy not in C7_PROXIES:
        raise ValueError(f"c7_proxy must be one of {C7_PROXIES}, got {c7_proxy!r}")
    v = np.asarray(vertical, dtype=float).reshape(-1)
    if v.shape != (3,) or not np.all(np.isfinite(v)) or np.linalg.norm(v) < 1e-12:
        raise ValueError(f"vertical must be a finite non-zero 3-vector, got {vertical!r}")
    v = v / np.linalg.norm(v)
    age_arr = np.full(b, np.nan) if age is None else np.asarray(age, dtype=float)
    if age_arr.ndim == 0:
        age_arr = np.full(b, float(age_arr))
    if age_arr.shape != (b,):
        raise ValueError(f"age must be None, a scalar or one value per model ({b}), got shape {age_arr.shape}")

    # one local origin per model (its first endplate vertex): every parameter is translation invariant, and
    # small coordinates keep the raw-moment plane fits accurate
    patches = {f"{lv} sup": landmarks.endplate_sup[lv] for lv in LEVELS + ("S1",)}
    patches.update({f"{lv} inf": landmarks.endplate_inf[lv] for lv in LEVELS})
    origin_row = int(np.asarray(patches[f"{LEVELS[0]} sup"]).ravel()[0])
    sets = {f"{lv} sup rim": landmarks.rim_sup[lv] for lv in LEVELS + ("S1",)}
    sets.update({f"{lv} inf rim": landmarks.rim_inf[lv] for lv in LEVELS})
    sets.update({f"femoral head {k}": landmarks.femoral_head[k] for k in ("L", "R")})
    sets["pubic symphysis"] = landmarks.pubic_symphysis
    blk = _Block(pts, sets, pts[:, origin_row].astype(float))

    # 1. endplate planes: the 35 patches of all models in one pass (sup T1..L5, S1, then inf T1..L5)
    nl = len(LEVELS)
    centre, normal, rms = plane_fits(pts, patches, origin_row, v)
    c_sup, n_sup, s1_c, s1_n = centre[:, :nl], normal[:, :nl], centre[:, nl], normal[:, nl]
    c_inf, n_inf = centre[:, nl + 1 :], normal[:, nl + 1 :]
    rms_max = rms.max(axis=1)

    # 2. femoral heads, 3. frame
    fh_c = {}
    fh_r = {}
    for side in ("L", "R"):
        fh_c[side], fh_r[side] = fit_spheres(blk[f"femoral head {side}"])
    symph = blk["pubic symphysis"].mean(axis=1)
    lh, ant, flipped = patient_frame(fh_c["L"], fh_c["R"], v, symph, s1_c)
    ha = 0.5 * (fh_c["L"] + fh_c["R"])

    # 4. parameters
    ss = sacral_slope_deg(s1_n, ant, v)
    pt = pelvic_tilt_deg(s1_c, ha, ant, v)
    pi = pelvic_incidence_deg(ss, pt)
    pi_err = np.abs(pi - unsigned_pelvic_incidence_deg(s1_n, s1_c, ha, ant, v))
    th_sup = sag_deg(n_sup, ant[:, None], v)
    th_inf = sag_deg(n_inf, ant[:, None], v)
    li = {lv: i for i, lv in enumerate(LEVELS)}
    ll = lordosis_deg(th_sup[:, li["L1"]], ss)
    ll_l4s1 = lordosis_deg(th_sup[:, li["L4"]], ss)
    ll_l1l5 = lordosis_deg(th_sup[:, li["L1"]], th_inf[:, li["L5"]])
    body = 0.5 * (c_sup + c_inf)
    t1c, t2c = body[:, li["T1"]], body[:, li["T2"]]
    c7_ext = 2.0 * t1c - t2c
    c7 = c7_ext if c7_proxy == "extrapolated" else t1c
    t1spi = t1_spinopelvic_inclination_deg(t1c, ha, ant, v)
    rims = [k for k in sets if k.endswith(" rim")]
    rim_ext = blk.extremes(rims, ant)  # (most anterior, most posterior) vertex of every rim
    s1ps = rim_ext["S1 sup rim"][1]

    out: dict[str, np.ndarray | list] = {
        "PI": pi,
        "PT": pt,
        "SS": ss,
        "LL": ll,
        "LL_L4S1": ll_l4s1,
        "LL_L1L5": ll_l1l5,
        "PI_minus_LL": pi - ll,
        "LL_minus_PI": ll - pi,
        "GT": global_tilt_deg(pt, c7, s1_c, ant, v),
        "GT_proxy": np.full(b, c7_proxy, dtype=object),
        "GT_T1": global_tilt_deg(pt, t1c, s1_c, ant, v),
        "T1SPI": t1spi,
        "TPA": t1_pelvic_angle_deg(pt, t1spi),
        "TK_T1T12": kyphosis_deg(th_sup[:, li["T1"]], th_inf[:, li["T12"]]),
        "TK_T4T12": kyphosis_deg(th_sup[:, li["T4"]], th_inf[:, li["T12"]]),
        "TK_T5T12": kyphosis_deg(th_sup[:, li["T5"]], th_inf[:, li["T12"]]),
    }
    cobb = cobb_angle(cor_deg(n_sup, lh[:, None], v), cor_deg(n_inf, lh[:, None], v), cobb_secondary_min_deg)
    names = np.array(LEVELS, dtype=object)
    out.update(
        {
            "Cobb": cobb["cobb"],
            "Cobb_convexity": cobb["convexity"].astype(int),
            "Cobb_upper": names[cobb["upper"]],
            "Cobb_lower": names[cobb["lower"]],
            "Cobb_apex": names[cobb["apex"]],
            "Cobb2": cobb["cobb2"],
            "Cobb2_upper": np.where(cobb["upper2"] >= 0, names[cobb["upper2"]], ""),
            "Cobb2_lower": np.where(cobb["lower2"] >= 0, names[cobb["lower2"]], ""),
            "SVA_T1": sva_mm(t1c, s1ps, ant),
            "SVA_C7est": sva_mm(c7_ext, s1ps, ant),
        }
    )
    for _k, (upper, lower) in enumerate(DISCS):
        iu = li[upper]
        cl = s1_c if lower == "S1" else c_sup[:, li[lower]]
        nl_ = s1_n if lower == "S1" else n_sup[:, li[lower]]
        ru, rl = f"{upper} inf rim", f"{lower} sup rim"
        name = disc_name(upper, lower)
        dh, dha, dhp = disc_heights_mm(
            c_inf[:, iu],
            n_inf[:, iu],
            cl,
            nl_,
            rim_ext[ru][0],
            rim_ext[rl][0],
            rim_ext[ru][1],
            rim_ext[rl][1],
        )
        out[f"DH_{name}"], out[f"DHa_{name}"], out[f"DHp_{name}"] = dh, dha, dhp
    # anatomical sides: with swapped labels the fit called "L" is the right head
    out["FH_radius_L"] = np.where(flipped, fh_r["R"], fh_r["L"])
    out["FH_radius_R"] = np.where(flipped, fh_r["L"], fh_r["R"])
    out["HA_width"] = np.linalg.norm(fh_c["R"] - fh_c["L"], axis=1)

    g = _gap.gap_score(pi, ss, ll, ll_l4s1, out["GT"], age_arr, ldi_undefined_points, ldi_min_ll_deg)
    assumed = g["GAP_noage"] + _gap.age_points(assumed_age)
    known = ~np.isnan(age_arr)
    out.update(
        {
            "RPV": g["RPV"],
            "RLL": g["RLL"],
            "RSA": g["RSA"],
            "LDI": g["LDI"],
            "LDI_undefined": np.isnan(g["LDI"]),
            "RPV_pts": g["RPV_pts"],
            "RLL_pts": g["RLL_pts"],
            "LDI_pts": g["LDI_pts"],
            "RSA_pts": g["RSA_pts"],
            "Age_pts": np.where(known, g["Age_pts"], _gap.age_points(assumed_age)),
            "GAP_noage": g["GAP_noage"],
            "GAP": g["GAP"],
            "GAP_assumed_age": assumed,
            "GAP_category": _gap.gap_category(np.where(known, g["GAP"], assumed)),
            "PI_identity_err": pi_err,
            "endplate_rms_max": rms_max,
        }
    )
    return out


def measure(points, landmarks: Landmarks, **kwargs) -> pd.DataFrame:
    """Every spinopelvic parameter of a batch of models (:func:`measure_columns`, same arguments) as a
    DataFrame with B rows."""
    import pandas as pd

    return pd.DataFrame(measure_columns(points, landmarks, **kwargs))


def measure_batch(points, landmarks: Landmarks | str | Path, vertical_axis=(0.0, 0.0, 1.0), **kwargs) -> pd.DataFrame:
    """Workflow adapter: :func:`measure` with ``landmarks`` given as a :class:`Landmarks` or a JSON path."""
    if not isinstance(landmarks, Landmarks):
        landmarks = Landmarks.load(landmarks)
    return measure(points, landmarks, vertical=vertical_axis, **kwargs)
