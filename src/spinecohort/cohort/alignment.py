"""Sagittal and coronal alignment of a generated patient and the ground truth it implies.

A patient is drawn as clinical parameters (PI, PT, LL and its distribution, TK, a coronal curve, sizes); the
column is then a chain of 35 endplates stacked from the S1 plate upwards, each with an imposed sagittal and
coronal tilt and an imposed centre.  Every true parameter follows from these imposed angles and positions in
the construction frame (V = +z, A = +y), with no plane or sphere fit, i.e. independently of
:mod:`spinecohort.measure.spinopelvic`.  The mesh generators (:mod:`spinecohort.cohort.synthetic`) put bone
surfaces on this chain.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from spinecohort.cohort.landmarks import DISCS, LEVELS, disc_name

#: Inclusion criteria of the seed (sign of LL-PI corrected: deformity means PI - LL > 10 deg).
CRITERIA = {"PI_minus_LL_min_deg": 10.0, "PT_min_deg": 20.0, "SVA_T1_min_mm": 50.0}

# Level-wise anatomy (T1..L5 index 0..16), linearly interpolated between knots; adult male sizes in mm,
# in the published ranges (bodies and discs growing caudally).
_KNOTS = np.array([0.0, 11.0, 16.0])  # T1, T12, L5


def level_interp(values: tuple[float, float, float], idx: np.ndarray | float) -> np.ndarray:
    return np.interp(idx, _KNOTS, values)


LEVEL_IDX = np.arange(len(LEVELS), dtype=float)
BODY_HALF_WIDTH = level_interp((14.0, 20.0, 25.0), LEVEL_IDX)
BODY_HALF_DEPTH = level_interp((9.0, 14.5, 17.5), LEVEL_IDX)
BODY_HEIGHT = np.array([14, 15, 16, 17, 18, 18.5, 19, 20, 21, 21.5, 22, 23, 25, 26, 27, 27, 27], float)
#: Central disc heights T1-T2 ... L5-S1 (healthy; patients get a degeneration factor).
DISC_HEIGHT = np.array([4.0, 4.2, 4.4, 4.6, 4.8, 5.0, 5.2, 5.4, 5.7, 6.0, 6.5, 7.0, 8.5, 9.5, 10.5, 11.0, 10.0])
S1_HALF_WIDTH, S1_HALF_DEPTH = 24.0, 17.0
ENDPLATE_EXPONENT = 2.6  # superellipse exponent: rounded-rectangle endplates, centrally symmetric


@dataclass
class PatientParameters:
    """Clinical and size parameters drawn for one patient (degrees, mm)."""

    ID: str
    age: float
    sex: str
    scale: float
    PI: float
    PT: float
    LL: float
    LDI: float  # percent of LL at L4-S1
    TK_T4T12: float
    TK_T1T4: float
    TL_junction: float  # T12-L1 disc wedge, + kyphotic
    cobb: float  # imposed main coronal curve, deg
    cobb_upper: int  # level index of upper end vertebra (0 = T1)
    cobb_lower: int
    cobb_sign: int  # +1: superior endplate of upper end vertebra tilted right
    disc_factor: np.ndarray  # (17,) multiplies DISC_HEIGHT
    fh_radius: float
    hip_width: float  # inter femoral-head-centre distance
    pelvic_radius: float  # hip axis to S1 midpoint
    axial_rotation_deg: float  # rigid placement of the whole patient about z
    translation: np.ndarray  # (3,) rigid placement, mm

    @property
    def SS(self) -> float:
        return self.PI - self.PT


def draw_patient(rng: np.random.Generator, pid: str) -> PatientParameters:
    """One candidate patient of an adult-spine-deformity cohort (inclusion is checked by the caller)."""
    sex = "F" if rng.random() < 0.5 else "M"
    scale = rng.normal(0.94 if sex == "F" else 1.0, 0.04)
    pi = float(np.clip(rng.normal(58.0, 9.0), 38.0, 85.0))
    pt = float(np.clip(rng.normal(27.0, 6.0), 12.0, pi - 12.0))
    mismatch = rng.normal(20.0, 8.0)
    ll = float(np.clip(pi - mismatch, 4.0, 75.0))
    span_half = int(rng.integers(2, 4))
    apex = int(rng.integers(6, 15))  # T7 .. L3
    return PatientParameters(
        ID=pid,
        age=float(rng.uniform(50.0, 75.0)),
        sex=sex,
        scale=float(scale),
        PI=pi,
        PT=pt,
        LL=ll,
        LDI=float(np.clip(rng.normal(66.0, 10.0), 40.0, 92.0)),
        TK_T4T12=float(np.clip(rng.normal(34.0, 11.0), 10.0, 70.0)),
        TK_T1T4=float(np.clip(rng.normal(6.0, 3.0), 0.0, 14.0)),
        TL_junction=float(rng.normal(3.0, 3.0)),
        cobb=float(rng.uniform(4.0, 40.0)),
        cobb_upper=max(apex - span_half - int(rng.integers(0, 2)), 1),
        cobb_lower=min(apex + span_half, 16),
        cobb_sign=int(rng.choice([-1, 1])),
        disc_factor=rng.uniform(0.75, 1.0) * rng.normal(1.0, 0.06, size=17),
        fh_radius=float(rng.normal(23.5 if sex == "F" else 25.0, 1.2) * scale),
        hip_width=float(rng.normal(160.0, 8.0) * scale),
        pelvic_radius=float(rng.normal(115.0, 7.0) * scale),
        axial_rotation_deg=float(rng.uniform(-8.0, 8.0)),
        translation=rng.normal(0.0, 15.0, size=3),
    )


# ----------------------------------------------------------------------------------------------------------
# The column as a chain of endplates.  Position p (0..34): 0 = S1 superior; vertebra i (0 = L5 ... 16 = T1)
# has its inferior endplate at 1 + 2i and superior at 2 + 2i.  Joint j links p = j to j + 1: even j is the
# disc below vertebra j/2, odd j the body of vertebra (j-1)/2.
N_POS = 35


def _vertebra_from_bottom(level_index: int) -> int:
    """Level index (0 = T1 ... 16 = L5) -> chain vertebra index (0 = L5 ... 16 = T1)."""
    return 16 - level_index


def pos_sup(level_index: int) -> int:
    return 2 + 2 * _vertebra_from_bottom(level_index)


def pos_inf(level_index: int) -> int:
    return 1 + 2 * _vertebra_from_bottom(level_index)


def sagittal_joint_angles(p: PatientParameters) -> np.ndarray:
    """(34,) increase of the sagittal endplate tilt across each joint going cranially, deg.

    Lordosis makes the tilt decrease cranially; kyphosis makes it increase.
    """
    d = np.zeros(N_POS - 1)
    l4s1 = p.LL * p.LDI / 100.0
    upper = p.LL - l4s1
    # L5-S1 and L4-L5 segments carry L4-S1 lordosis (58/42 %), the disc 75 % of each segment.
    for vert, share, disc_share in ((0, 0.58, 0.75), (1, 0.42, 0.75)):
        seg = l4s1 * share
        d[2 * vert] = -seg * disc_share
        d[2 * vert + 1] = -seg * (1 - disc_share)
    for vert, share in ((2, 0.45), (3, 0.33), (4, 0.22)):  # L3, L2, L1 segments
        seg = upper * share
        d[2 * vert] = -seg * 0.7
        d[2 * vert + 1] = -seg * 0.3
    d[10] = p.TL_junction  # T12-L1 disc
    # T4-T12 kyphosis over joints 11 (T12 body) .. 27 (T4 body): smooth profile peaking mid-thorax,
    # vertebral wedging slightly larger than disc wedging.
    j = np.arange(11, 28)
    w = np.sin(np.pi * (j - 10) / 18.0) * np.where(j % 2 == 1, 1.2, 1.0)
    d[11:28] = p.TK_T4T12 * w / w.sum()
    d[28:34] = p.TK_T1T4 / 6.0
    return d


def coronal_endplate_tilts(p: PatientParameters) -> np.ndarray:
    """(35,) coronal tilt of every endplate, deg, positive tilted to the right.

    Linear from +C/2 (superior endplate of the upper end vertebra) to -C/2 (inferior endplate of the lower
    end vertebra), returning linearly to 0 at S1 below and over four levels above: the main curve is C.
    """
    half = 0.5 * p.cobb * p.cobb_sign
    top, bottom = pos_sup(p.cobb_upper), pos_inf(p.cobb_lower)
    phi = np.zeros(N_POS)
    pos = np.arange(N_POS)
    inside = (pos >= bottom) & (pos <= top)
    phi[inside] = -half + (pos[inside] - bottom) * (2 * half) / (top - bottom)
    below = pos < bottom
    phi[below] = -half * pos[below] / bottom if bottom > 0 else 0.0
    above = pos > top
    phi[above] = half * np.clip(1.0 - (pos[above] - top) / 8.0, 0.0, 1.0)
    return phi


def endplate_normal(sag_deg: np.ndarray, cor_deg: np.ndarray) -> np.ndarray:
    """Unit normal (..., 3) whose sagittal and coronal projected tilts are exactly the given angles."""
    n = np.stack([np.tan(np.radians(cor_deg)), np.tan(np.radians(sag_deg)), np.ones_like(sag_deg)], -1)
    return n / np.linalg.norm(n, axis=-1, keepdims=True)


def endplate_frame(normal: np.ndarray) -> np.ndarray:
    """(3, 3) rotation whose columns are lateral, anterior and the normal (no axial rotation)."""
    ex = np.array([1.0, 0.0, 0.0]) - normal[0] * normal
    ex /= np.linalg.norm(ex)
    return np.stack([ex, np.cross(normal, ex), normal], axis=1)


def endplate_frames(normals: np.ndarray) -> np.ndarray:
    """(K, 3, 3) :func:`endplate_frame` of every unit normal of ``normals`` (K, 3) at once."""
    ex = np.array([1.0, 0.0, 0.0]) - normals[:, :1] * normals
    ex /= np.linalg.norm(ex, axis=1, keepdims=True)
    return np.stack([ex, np.cross(normals, ex), normals], axis=2)


def rot_x(angle_deg: float) -> np.ndarray:
    """Rotation about +x (the medio-lateral axis); positive tilts +z towards -y (posteriorly)."""
    a = np.radians(angle_deg)
    c, s = np.cos(a), np.sin(a)
    return np.array([[1.0, 0, 0], [0, c, -s], [0, s, c]])


@dataclass
class Chain:
    sag: np.ndarray  # (35,) sagittal endplate tilts, deg
    cor: np.ndarray  # (35,) coronal endplate tilts, deg
    normals: np.ndarray  # (35, 3)
    centres: np.ndarray  # (35, 3) endplate centres, mm
    frames: np.ndarray  # (35, 3, 3)
    lengths: np.ndarray  # (34,) central heights of the joints (discs and bodies), mm


def build_chain(
    p: PatientParameters, body_height_mm: np.ndarray | None = None, disc_height_mm: np.ndarray | None = None
) -> Chain:
    """Stack the column on the S1 plate of the tilted pelvis.

    body_height_mm / disc_height_mm: (17,) central body heights T1..L5 and disc heights T1-T2..L5-S1 before
    the patient's scale and disc factor; the generic tables by default."""
    body = BODY_HEIGHT if body_height_mm is None else np.asarray(body_height_mm, float)
    disc = DISC_HEIGHT if disc_height_mm is None else np.asarray(disc_height_mm, float)
    sag = p.SS + np.concatenate([[0.0], np.cumsum(sagittal_joint_angles(p))])
    cor = coronal_endplate_tilts(p)
    normals = endplate_normal(sag, cor)
    frames = endplate_frames(normals)
    lengths = np.empty(N_POS - 1)
    lengths[0::2] = (disc * p.disc_factor)[::-1] * p.scale  # disc below L5 first
    lengths[1::2] = body[::-1] * p.scale
    centres = np.empty((N_POS, 3))
    centres[0] = rot_x(p.PT) @ np.array([0.0, 0.0, p.pelvic_radius])
    for j in range(N_POS - 1):
        m = normals[j] + normals[j + 1]
        centres[j + 1] = centres[j] + lengths[j] * m / np.linalg.norm(m)
    return Chain(sag, cor, normals, centres, frames, lengths)


def _sag(v: np.ndarray) -> float:
    """Sagittal inclination in the construction frame (A = +y, V = +z), deg."""
    return float(np.degrees(np.arctan2(v[1], v[2])))


def true_parameters(p: PatientParameters, chain: Chain, s1_rim: np.ndarray) -> dict[str, float | str]:
    """Every parameter the generator imposed, in the construction frame (before rigid placement).

    s1_rim: (K, 3) rim vertices of the constructed S1 plate (their most posterior one is the S1
    posterosuperior corner).
    """
    th = {lv: (chain.sag[pos_sup(i)], chain.sag[pos_inf(i)]) for i, lv in enumerate(LEVELS)}
    ss = chain.sag[0]
    ll = ss - th["L1"][0]
    ll_l4s1 = ss - th["L4"][0]
    s1mid = chain.centres[0]
    bc = {lv: 0.5 * (chain.centres[pos_sup(i)] + chain.centres[pos_inf(i)]) for i, lv in enumerate(LEVELS)}
    c7 = 2 * bc["T1"] - bc["T2"]
    s1ps = s1_rim[np.argmin(s1_rim[:, 1])]
    gt = p.PT + _sag(c7 - s1mid)
    out: dict[str, float | str] = {
        "PI": p.PI,
        "PT": p.PT,
        "SS": ss,
        "LL": ll,
        "LL_L4S1": ll_l4s1,
        "LL_L1L5": th["L5"][1] - th["L1"][0],
        "PI_minus_LL": p.PI - ll,
        "LL_minus_PI": ll - p.PI,
        "GT": gt,
        "GT_T1": p.PT + _sag(bc["T1"] - s1mid),
        "T1SPI": _sag(bc["T1"]),  # hip axis at the origin
        "TPA": p.PT + _sag(bc["T1"]),
        "TK_T1T12": th["T1"][0] - th["T12"][1],
        "TK_T4T12": th["T4"][0] - th["T12"][1],
        "TK_T5T12": th["T5"][0] - th["T12"][1],
        "SVA_T1": float(bc["T1"][1] - s1ps[1]),
        "SVA_C7est": float(c7[1] - s1ps[1]),
    }
    # Coronal Cobb by its definition over the imposed tilts (upper end vertebra i <= lower j).
    phis = np.array([chain.cor[pos_sup(i)] for i in range(17)])
    phii = np.array([chain.cor[pos_inf(i)] for i in range(17)])
    diff = np.abs(phis[:, None] - phii[None, :])
    diff[np.tril_indices(17, -1)] = -1.0
    i, j = np.unravel_index(np.argmax(diff), diff.shape)
    out.update({"Cobb": float(diff[i, j]), "Cobb_upper": LEVELS[i], "Cobb_lower": LEVELS[j]})
    for k, (upper, lower) in enumerate(DISCS):
        out[f"DH_{disc_name(upper, lower)}"] = float(chain.lengths[2 * (16 - k)])
    out.update(
        {
            "FH_radius_L": p.fh_radius,
            "FH_radius_R": p.fh_radius,
            "HA_width": p.hip_width,
            "RPV": ss - (0.59 * p.PI + 9.0),
            "RLL": ll - (0.62 * p.PI + 29.0),
            "LDI": 100.0 * ll_l4s1 / ll,
            "RSA": gt - (0.48 * p.PI - 15.0),
        }
    )
    return out


def meets_criteria(truth: dict, criteria: dict = CRITERIA) -> bool:
    return (
        truth["PI_minus_LL"] > criteria["PI_minus_LL_min_deg"]
        and truth["PT"] > criteria["PT_min_deg"]
        and truth["SVA_T1"] > criteria["SVA_T1_min_mm"]
    )
