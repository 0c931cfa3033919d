"""Spinopelvic parameters of a batch of spine models, measured on corresponding landmark vertices.

Follows /work/shared/reference/spinopelvic.md (§7 step by step); docs/measurement.md lists every choice.
Millimetres and degrees throughout.

Pipeline per batch (all array operations over the B models; only the 17 levels / 17 discs are looped):

1. Endplate planes: total-least-squares fit of every endplate patch: the raw moments of all 35 patches of all
   models summed in one numba pass over the batch (each patch about its own first vertex: out-of-plane RMS
   exact to ~1e-9 mm), then the smallest eigenpair of every 3x3 covariance (one numba pass of Jacobi
   rotations); normals oriented cranially
   (n.V > 0); the vertex mean is the endplate centre because the patches are sampled centrally symmetric.
2. Femoral heads: algebraic sphere fit (batched normal equations on mean-centred points, moments in one pass).
3. Patient frame (§1.1/§7.3): V = the explicit vertical, Lh = horizontal part of cR - cL, A = V x Lh.  If the
   pubic symphysis lies posterior to the S1 centre, A and Lh are flipped (left/right labels swapped), which makes
   every output invariant to axial rotation, translation and label swaps.
4. Signed in-plane angles ``sag(v) = atan2(v.A, v.V)`` and ``cor(v) = atan2(v.Lh, v.V)``, so the identities
   PI = PT + SS, TPA = PT + T1SPI and GT = PT + C7VT hold for negative terms too.

The batched plane/sphere fits and rim extremes are written here (small numba loops) because scipy/pyvista fit
one point set at a time; a Python loop over 16,807 models x 35 patches would dominate the run time, and the
numpy form (a gathered copy of every landmark vertex, a matmul per patch) cost 2.5x the time (docs/store.md).
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numba
import numpy as np

from spinecohort.cohort.landmarks import DISCS, LEVELS, Landmarks, disc_name
from spinecohort.measure import gap_score as _gap

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


# --------------------------------------------------------------------------------------------- fits


def fit_planes(patch: np.ndarray, vertical: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Total-least-squares planes of a batch of patches.

    patch: (B, K, 3) mm.  Returns centre (B, 3) = vertex mean, unit normal (B, 3) oriented so that
    normal.vertical > 0, and rms (B,) = out-of-plane RMS residual in mm (sqrt of the smallest eigenvalue of
    the covariance, equal to S[-1]/sqrt(K) of the SVD formulation).

    :func:`_plane_fits` with one patch: raw moments about the first vertex (no centred copy), so round-off
    stays far below 1e-5 mm wherever the model lies.
    """
    patch = np.asarray(patch, dtype=float)
    centre, normal, rms = _plane_fits(patch, {"patch": np.arange(patch.shape[1])}, 0, np.asarray(vertical, float))
    return centre[:, 0] + patch[:, 0], normal[:, 0], rms[:, 0]


@numba.njit(cache=True)
def _patch_moments_nb(points, rows, starts, origin_row):
    """Mean (B, P, 3) and covariance (B, P, 3, 3) of the patches ``rows[starts[j]:starts[j + 1]]`` of points
    (B, N, 3), relative to each model's vertex ``origin_row``: raw moments read straight from the batch (no
    gathered copy), one pass per model."""
    n_models, n_patches = points.shape[0], starts.shape[0] - 1
    mean = np.empty((n_models, n_patches, 3))
    cov = np.empty((n_models, n_patches, 3, 3))
    for b in range(n_models):
        o0, o1, o2 = (
            np.float64(points[b, origin_row, 0]),
            np.float64(points[b, origin_row, 1]),
            np.float64(points[b, origin_row, 2]),
        )
        for j in range(n_patches):
            # moments about the patch's first vertex: coordinates of the patch's size keep the cancellation in
            # E[q q^T] - E[q] E[q]^T small (out-of-plane RMS of 1e-5 mm patches to ~2e-9 mm), then shifted to the
            # model's origin
            r0 = rows[starts[j]]
            p0, p1, p2 = np.float64(points[b, r0, 0]), np.float64(points[b, r0, 1]), np.float64(points[b, r0, 2])
            sx = sy = sz = sxx = sxy = sxz = syy = syz = szz = 0.0
            for k in range(starts[j], starts[j + 1]):
                r = rows[k]
                x = np.float64(points[b, r, 0]) - p0
                y = np.float64(points[b, r, 1]) - p1
                z = np.float64(points[b, r, 2]) - p2
                sx += x
                sy += y
                sz += z
                sxx += x * x
                sxy += x * y
                sxz += x * z
                syy += y * y
                syz += y * z
                szz += z * z
            n = starts[j + 1] - starts[j]
            mx, my, mz = sx / n, sy / n, sz / n
            mean[b, j, 0], mean[b, j, 1], mean[b, j, 2] = mx + (p0 - o0), my + (p1 - o1), mz + (p2 - o2)
            cov[b, j, 0, 0] = sxx / n - mx * mx
            cov[b, j, 1, 1] = syy / n - my * my
            cov[b, j, 2, 2] = szz / n - mz * mz
            cov[b, j, 0, 1] = cov[b, j, 1, 0] = sxy / n - mx * my
            cov[b, j, 0, 2] = cov[b, j, 2, 0] = sxz / n - mx * mz
            cov[b, j, 1, 2] = cov[b, j, 2, 1] = syz / n - my * mz
    return mean, cov


def _plane_fits(points: np.ndarray, patches: dict[str, np.ndarray], origin_row: int, vertical: np.ndarray):
    """TLS planes of every patch of every model in one pass and one pass of Jacobi rotations: points (B, N, 3) mm,
    patches name -> vertex rows.  Returns centres (B, P, 3) relative to each model's vertex ``origin_row``, unit
    normals (B, P, 3) with normal.vertical > 0, out-of-plane RMS (B, P) mm, patches in the dict's order.  Raw
    moments, each patch about its own first vertex (its coordinates stay of the patch's size)."""
    rows = [np.asarray(v, dtype=np.int64).ravel() for v in patches.values()]
    starts = np.concatenate([[0], np.cumsum([len(r) for r in rows])])
    mean, cov = _patch_moments_nb(points, np.concatenate(rows), starts, origin_row)
    if not np.isfinite(cov).all():
        name = list(patches)[int(np.argmax(~np.isfinite(cov).all(axis=(0, 2, 3))))]
        raise ValueError(f"non-finite coordinates in landmark set {name}")
    w0, normal = np.empty(cov.shape[:-2]), np.empty(cov.shape[:-1])
    _least_eigenpairs_nb(cov.reshape(-1, 3, 3), w0.reshape(-1), normal.reshape(-1, 3))
    normal *= np.where(normal @ vertical < 0, -1.0, 1.0)[..., None]
    return mean, normal, np.sqrt(np.clip(w0, 0.0, None))


@numba.njit(cache=True, error_model="numpy")
def _least_eigenpairs_nb(cov, w0, v0):
    """The smallest eigenvalue w0 (M,) and a unit eigenvector v0 (M, 3) of each symmetric 3x3 matrix of cov
    (M, 3, 3), by cyclic Jacobi rotations (Rutishauser's form, as in Numerical Recipes' ``jacobi``).

    Written here rather than ``np.linalg.eigh`` because LAPACK's per-matrix overhead made that ~0.9-1.3 us per
    3x3 matrix (2 x 35 patches x 16,807 models per store stage); this takes 0.27-0.38 us (the stage's measure
    phase 4.9 -> 4.2 s CPU, docs/store.md session 22).  Jacobi is accurate to round-off in every eigenpair, including the nearly-zero
    out-of-plane variance of a flat patch beside two nearly equal in-plane ones (tested against LAPACK)."""
    a = np.empty((3, 3))
    v = np.empty((3, 3))
    for m in range(cov.shape[0]):
        for i in range(3):
            for j in range(3):
                a[i, j] = cov[m, i, j]
                v[i, j] = 1.0 if i == j else 0.0
        for sweep in range(50):
            off = abs(a[0, 1]) + abs(a[0, 2]) + abs(a[1, 2])
            # converged: an off-diagonal of 1e-18 x the trace tilts an eigenvector by ~1e-18 x trace / gap
            # and moves an eigenvalue by its square over the gap, far below the round-off of the moments
            if off <= 1e-18 * (abs(a[0, 0]) + abs(a[1, 1]) + abs(a[2, 2])):
                break
            for p, q, r in ((0, 1, 2), (0, 2, 1), (1, 2, 0)):
                apq = a[p, q]
                small = 100.0 * abs(apq)
                if sweep > 3 and abs(a[p, p]) + small == abs(a[p, p]) and abs(a[q, q]) + small == abs(a[q, q]):
                    a[p, q] = a[q, p] = 0.0  # below the diagonal's round-off: converged
                    continue
                if apq == 0.0:
                    continue
                h = a[q, q] - a[p, p]
                if abs(h) + small == abs(h):
                    t = apq / h  # tan of the angle ~ its half-angle formula's limit
                else:
                    theta = 0.5 * h / apq
                    t = 1.0 / (abs(theta) + np.sqrt(1.0 + theta * theta))
                    if theta < 0.0:
                        t = -t
                c = 1.0 / np.sqrt(1.0 + t * t)
                s = t * c
                tau = s / (1.0 + c)
                a[p, p] -= t * apq
                a[q, q] += t * apq
                a[p, q] = a[q, p] = 0.0
                arp, arq = a[r, p], a[r, q]
                a[r, p] = a[p, r] = arp - s * (arq + tau * arp)
                a[r, q] = a[q, r] = arq + s * (arp - tau * arq)
                for i in range(3):
                    vip, viq = v[i, p], v[i, q]
                    v[i, p] = vip - s * (viq + tau * vip)
                    v[i, q] = viq + s * (vip - tau * viq)
        k = 0
        if a[1, 1] < a[k, k]:
            k = 1
        if a[2, 2] < a[k, k]:
            k = 2
        w0[m] = a[k, k]
        for i in range(3):
            v0[m, i] = v[i, k]


@numba.njit(cache=True)
def _sphere_moments_nb(pts):
    """Per model of pts (B, K, 3): mean (B, 3), and of the centred points q: sum q q^T (B, 3, 3), sum q |q|^2
    (B, 3) and mean |q|^2 (B,).  Two passes over the points, no temporary arrays."""
    n_models, k = pts.shape[0], pts.shape[1]
    mu, qq, qs, s_mean = (
        np.empty((n_models, 3)),
        np.empty((n_models, 3, 3)),
        np.empty((n_models, 3)),
        np.empty(n_models),
    )
    for b in range(n_models):
        sx = sy = sz = 0.0
        for i in range(k):
            sx += pts[b, i, 0]
            sy += pts[b, i, 1]
            sz += pts[b, i, 2]
        mx, my, mz = sx / k, sy / k, sz / k
        xx = xy = xz = yy = yz = zz = rx = ry = rz = ss = 0.0
        for i in range(k):
            x, y, z = pts[b, i, 0] - mx, pts[b, i, 1] - my, pts[b, i, 2] - mz
            s = x * x + y * y + z * z
            xx += x * x
            xy += x * y
            xz += x * z
            yy += y * y
            yz += y * z
            zz += z * z
            rx += x * s
            ry += y * s
            rz += z * s
            ss += s
        mu[b, 0], mu[b, 1], mu[b, 2] = mx, my, mz
        qq[b, 0, 0], qq[b, 1, 1], qq[b, 2, 2] = xx, yy, zz
        qq[b, 0, 1] = qq[b, 1, 0] = xy
        qq[b, 0, 2] = qq[b, 2, 0] = xz
        qq[b, 1, 2] = qq[b, 2, 1] = yz
        qs[b, 0], qs[b, 1], qs[b, 2] = rx, ry, rz
        s_mean[b] = ss / k
    return mu, qq, qs, s_mean


def fit_spheres(pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Algebraic least-squares spheres of a batch of point sets (works on partial caps).

    pts: (B, K, 3) mm.  Solves [2x 2y 2z 1][c; d] = x^2+y^2+z^2 on mean-centred points (for conditioning).
    Returns centre (B, 3) and radius (B,) in mm.
    """
    mu, qq, qs, s_mean = _sphere_moments_nb(np.asarray(pts, dtype=float))
    # centred points make the column of ones orthogonal to the 2q columns, so the 4x4 normal equations split
    # into a 3x3 system for the centre offset and d = mean(|q|^2)
    c = 0.5 * np.linalg.solve(qq, qs[:, :, None])[:, :, 0]
    return mu + c, np.sqrt(s_mean + np.einsum("bi,bi->b", c, c))


def patient_frame(
    c_left: np.ndarray, c_right: np.ndarray, vertical: np.ndarray, symphysis: np.ndarray, s1_centre: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Medio-lateral Lh (left->right) and anterior A unit vectors (B, 3) from the femoral-head centres.

    Lh = horizontal part of c_right - c_left, A = V x Lh.  Both are flipped where the symphysis centre lies
    posterior to the S1 centre (left/right labels swapped).  Also returns the boolean ``flipped`` (B,).
    """
    d = c_right - c_left
    h = d - (d @ vertical)[:, None] * vertical
    norm = np.linalg.norm(h, axis=1)
    if np.any(norm < 1e-9):
        raise ValueError("femoral-head centres coincide in the horizontal plane: no medio-lateral axis")
    lh = h / norm[:, None]
    a = np.cross(vertical, lh)
    flipped = np.einsum("bi,bi->b", symphysis - s1_centre, a) < 0
    sign = np.where(flipped, -1.0, 1.0)[:, None]
    return lh * sign, a * sign, flipped


def sag_deg(v: np.ndarray, anterior: np.ndarray, vertical: np.ndarray) -> np.ndarray:
    """Signed sagittal inclination atan2(v.A, v.V) in deg: 0 = up, positive = tilted anteriorly."""
    return np.degrees(np.arctan2(np.einsum("...i,...i->...", v, anterior), v @ vertical))


def cor_deg(v: np.ndarray, lateral: np.ndarray, vertical: np.ndarray) -> np.ndarray:
    """Signed coronal inclination atan2(v.Lh, v.V) in deg: 0 = up, positive = tilted to the patient's right."""
    return np.degrees(np.arctan2(np.einsum("...i,...i->...", v, lateral), v @ vertical))


# --------------------------------------------------------------------------------- per-parameter formulas


def sacral_slope_deg(n_s1, anterior, vertical):
    """SS = sag(n_S1sup): S1 plate vs horizontal, positive when it slopes down anteriorly (§2.1)."""
    return sag_deg(n_s1, anterior, vertical)


def pelvic_tilt_deg(s1_centre, hip_axis, anterior, vertical):
    """PT = -sag(S1mid - HA): positive when the S1 centre lies posterior to the hip axis (§2.2)."""
    return -sag_deg(s1_centre - hip_axis, anterior, vertical)


def pelvic_incidence_deg(ss_deg, pt_deg):
    """PI = SS + PT with signed SS and PT (§2.3); morphological, independent of the vertical."""
    return ss_deg + pt_deg


def unsigned_pelvic_incidence_deg(n_s1, s1_centre, hip_axis, anterior, vertical):
    """QC form of PI: unsigned angle between the sagittal projections of n_S1sup and S1mid - HA (deg)."""
    return np.abs(sag_deg(n_s1, anterior, vertical) - sag_deg(s1_centre - hip_axis, anterior, vertical))


def lordosis_deg(theta_upper_sup_deg, theta_lower_deg):
    """Sagittal Cobb between two cranially oriented endplates, positive = lordosis (theta_lower - theta_upper)."""
    return theta_lower_deg - theta_upper_sup_deg


def kyphosis_deg(theta_upper_sup_deg, theta_lower_inf_deg):
    """Sagittal Cobb between two cranially oriented endplates, positive = kyphosis (theta_upper - theta_lower)."""
    return theta_upper_sup_deg - theta_lower_inf_deg


def t1_spinopelvic_inclination_deg(t1_centre, hip_axis, anterior, vertical):
    """T1SPI = sag(T1c - HA), positive when T1 lies anterior to the hip axis (§3.4)."""
    return sag_deg(t1_centre - hip_axis, anterior, vertical)


def t1_pelvic_angle_deg(pt_deg, t1spi_deg):
    """TPA = PT + T1SPI: angle T1c-HA-S1mid (§3.4)."""
    return pt_deg + t1spi_deg


def global_tilt_deg(pt_deg, c7_centre, s1_centre, anterior, vertical):
    """GT = PT + C7VT, C7VT = sag(C7c - S1mid): angle C7c-S1mid-HA, positive = C7 anterior (§3.3)."""
    return pt_deg + sag_deg(c7_centre - s1_centre, anterior, vertical)


def sva_mm(plumb_centre, s1_posterosuperior, anterior):
    """Horizontal (A) offset of a plumb line from the S1 posterosuperior corner, positive = anterior (mm)."""
    return np.einsum("...i,...i->...", plumb_centre - s1_posterosuperior, anterior)


def disc_heights_mm(c_upper_inf, n_upper_inf, c_lower_sup, n_lower_sup, ant_upper, ant_lower, post_upper, post_lower):
    """Central, anterior and posterior disc heights (mm) along the mean endplate normal (§5).

    c_*: endplate centres; n_*: cranial unit normals; ant_/post_*: the rim points extreme in +A / -A of the
    upper vertebra's inferior and the lower vertebra's superior endplate.  All (B, 3).
    """
    m = n_upper_inf + n_lower_sup
    m = m / np.linalg.norm(m, axis=-1, keepdims=True)

    def along(p, q):
        return np.einsum("bi,bi->b", p - q, m)

    return along(c_upper_inf, c_lower_sup), along(ant_upper, ant_lower), along(post_upper, post_lower)


def cobb_angle(phi_sup_deg: np.ndarray, phi_inf_deg: np.ndarray, secondary_min_deg: float = 10.0) -> dict:
    """Coronal Cobb by exhaustive end-vertebra search (§3.7), vectorised over the batch.

    phi_sup_deg / phi_inf_deg: (B, L) coronal tilts of the superior / inferior endplates, cranial to caudal.
    Main curve (i*, j*) = argmax_{i <= j} |phi_sup[i] - phi_inf[j]|.  Apex = vertebra in [i*, j*] whose
    mid-plane tilt is closest to the mean of the two end tilts.  Convexity = +1 for a curve convex to the
    patient's right (+Lh), i.e. sign(phi_inf[j*] - phi_sup[i*]).  Secondary curve = the largest curve of the
    cranial block [0, i*] and the caudal block [j*, L-1] (shared end vertebrae allowed, the main pair
    excluded); NaN when below ``secondary_min_deg``.
    Returns arrays: cobb, upper, lower, apex (int indices), convexity, cobb2, upper2, lower2.
    """
    b, n = phi_sup_deg.shape
    diff = phi_sup_deg[:, :, None] - phi_inf_deg[:, None, :]
    mag = np.abs(diff)
    ii, jj = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    valid = ii <= jj
    main = np.where(valid, mag, -np.inf).reshape(b, -1)
    k = np.argmax(main, axis=1)
    up, lo = np.unravel_index(k, (n, n))
    rows = np.arange(b)
    cobb = main[rows, k]
    convexity = np.sign(-diff[rows, up, lo])
    convexity = np.where(convexity == 0, 1.0, convexity)
    mid = 0.5 * (phi_sup_deg + phi_inf_deg)
    target = 0.5 * (phi_sup_deg[rows, up] + phi_inf_deg[rows, lo])
    lv = np.arange(n)[None, :]
    in_curve = (lv >= up[:, None]) & (lv <= lo[:, None])
    apex = np.argmin(np.where(in_curve, np.abs(mid - target[:, None]), np.inf), axis=1)
    cranial = valid[None] & (jj[None] <= up[:, None, None])
    caudal = valid[None] & (ii[None] >= lo[:, None, None])
    same = (ii[None] == up[:, None, None]) & (jj[None] == lo[:, None, None])
    sec = np.where((cranial | caudal) & ~same, mag, -np.inf).reshape(b, -1)
    k2 = np.argmax(sec, axis=1)
    cobb2 = sec[rows, k2]
    up2, lo2 = np.unravel_index(k2, (n, n))
    keep = cobb2 >= secondary_min_deg
    return {
        "cobb": cobb,
        "upper": up,
        "lower": lo,
        "apex": apex,
        "convexity": convexity,
        "cobb2": np.where(keep, cobb2, np.nan),
        "upper2": np.where(keep, up2, -1),
        "lower2": np.where(keep, lo2, -1),
    }


# ------------------------------------------------------------------------------------------ measure


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
    DataFrame); the shard jobs keep them as arrays and never import pandas.
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
    centre, normal, rms = _plane_fits(pts, patches, origin_row, v)
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
