"""The patient frame and the formula of every spinopelvic parameter from fitted geometry, vectorised over a
batch of models (the table of definitions: docs/explanation/measurement.md).  Millimetres and degrees.

Patient frame: V = the explicit vertical, Lh = horizontal part of cR - cL (femoral-head centres), A = V x Lh;
if the pubic symphysis lies posterior to the S1 centre, A and Lh are flipped (left/right labels swapped), which
makes every output invariant to axial rotation, translation and label swaps.  Signed in-plane angles
``sag(v) = atan2(v.A, v.V)`` and ``cor(v) = atan2(v.Lh, v.V)``, so the identities PI = PT + SS,
TPA = PT + T1SPI and GT = PT + C7VT hold for negative terms too.
"""

from __future__ import annotations

import numpy as np


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
    """SS = sag(n_S1sup): S1 plate vs horizontal, positive when it slopes down anteriorly."""
    return sag_deg(n_s1, anterior, vertical)


def pelvic_tilt_deg(s1_centre, hip_axis, anterior, vertical):
    """PT = -sag(S1mid - HA): positive when the S1 centre lies posterior to the hip axis."""
    return -sag_deg(s1_centre - hip_axis, anterior, vertical)


def pelvic_incidence_deg(ss_deg, pt_deg):
    """PI = SS + PT with signed SS and PT; morphological, independent of the vertical."""
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
    """T1SPI = sag(T1c - HA), positive when T1 lies anterior to the hip axis."""
    return sag_deg(t1_centre - hip_axis, anterior, vertical)


def t1_pelvic_angle_deg(pt_deg, t1spi_deg):
    """TPA = PT + T1SPI: angle T1c-HA-S1mid."""
    return pt_deg + t1spi_deg


def global_tilt_deg(pt_deg, c7_centre, s1_centre, anterior, vertical):
    """GT = PT + C7VT, C7VT = sag(C7c - S1mid): angle C7c-S1mid-HA, positive = C7 anterior."""
    return pt_deg + sag_deg(c7_centre - s1_centre, anterior, vertical)


def sva_mm(plumb_centre, s1_posterosuperior, anterior):
    """Horizontal (A) offset of a plumb line from the S1 posterosuperior corner, positive = anterior (mm)."""
    return np.einsum("...i,...i->...", plumb_centre - s1_posterosuperior, anterior)


def disc_heights_mm(c_upper_inf, n_upper_inf, c_lower_sup, n_lower_sup, ant_upper, ant_lower, post_upper, post_lower):
    """Central, anterior and posterior disc heights (mm) along the mean endplate normal.

    c_*: endplate centres; n_*: cranial unit normals; ant_/post_*: the rim points extreme in +A / -A of the
    upper vertebra's inferior and the lower vertebra's superior endplate.  All (B, 3).
    """
    m = n_upper_inf + n_lower_sup
    m = m / np.linalg.norm(m, axis=-1, keepdims=True)

    def along(p, q):
        return np.einsum("bi,bi->b", p - q, m)

    return along(c_upper_inf, c_lower_sup), along(ant_upper, ant_lower), along(post_upper, post_lower)


def cobb_angle(phi_sup_deg: np.ndarray, phi_inf_deg: np.ndarray, secondary_min_deg: float = 10.0) -> dict:
    """Coronal Cobb by exhaustive end-vertebra search, vectorised over the batch.

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
