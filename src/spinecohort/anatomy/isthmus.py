"""Pedicle isthmus and vertebral canal measured by chords of the closed bone surface, without part labels.

A chord is the segment of a straight line inside the bone: the line crosses a closed triangulated surface an
even number of times, and the crossings, sorted, alternate entry and exit.  Everything here is in the
vertebra frame (anterior, right, superior; mm), on the vertebra's own closed surface:

* **canal** (mid-sagittal line at a given height): from the body centre posteriorly, the body's exit is the
  posterior body wall, the next entry the inner face of the lamina; the gap between them is the canal depth;
* **pedicle** of one side: for every coronal position ``a`` between the posterior body wall and the lamina,
  a transverse line from the canal mid-line outwards enters the bone at the pedicle's medial wall and leaves
  it at its lateral wall (the transverse chord), and the vertical line through that chord's middle gives the
  pedicle's height chord; the two are re-centred on each other twice, so the lines pass through the pedicle's
  centre.  The **isthmus** is the position of least transverse chord (the pedicle width of an axial CT
  slice), the pedicle height the least vertical chord (that of a sagittal slice).  A pedicle converging anteriorly at
  the medial angle theta is cut obliquely by a transverse line: its width across its own axis is the chord x
  cos(theta), theta being the slope of the chord midpoints along ``a`` near the isthmus.

The labels play no part: a thin labeled strip at the pedicle base measures the same pedicle as a whole one.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: crossings closer than this along a line (mm) are one crossing (a line through a shared edge or vertex)
_SAME_MM = 1e-6


def line_crossings(triangles: np.ndarray, origins: np.ndarray, direction: np.ndarray) -> list[np.ndarray]:
    """Sorted line parameters (mm along the unit ``direction``) where each line ``origin + t d`` crosses the
    triangles ((F, 3, 3) mm); one array per origin ((R, 3) mm).  Moller-Trumbore, edges inclusive,
    coincident crossings merged."""
    d = np.asarray(direction, float)
    d = d / np.linalg.norm(d)
    v0, e1, e2 = triangles[:, 0], triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0]
    p = np.cross(d, e2)  # (F, 3)
    det = np.einsum("ij,ij->i", e1, p)
    ok = np.abs(det) > 1e-12
    v0, e1, e2, p, inv = v0[ok], e1[ok], e2[ok], p[ok], 1.0 / det[ok]
    s = np.asarray(origins, float)[:, None, :] - v0[None]  # (R, F, 3)
    u = np.einsum("rfj,fj->rf", s, p) * inv
    qv = np.cross(s, e1[None])
    v = (qv @ d) * inv
    t = np.einsum("rfj,fj->rf", qv, e2) * inv
    hit = (u >= 0) & (v >= 0) & (u + v <= 1)
    out = []
    for row_t, row_hit in zip(t, hit):
        ts = np.sort(row_t[row_hit])
        if ts.size:
            ts = ts[np.r_[True, np.diff(ts) > _SAME_MM]]
        out.append(ts)
    return out


def chord_through(ts: np.ndarray) -> tuple[float, float]:
    """(entry, exit) of the chord containing the line's origin (t = 0); (nan, nan) if the origin is outside."""
    k = int(np.searchsorted(ts, 0.0))
    if k % 2 == 1 and k < len(ts):
        return float(ts[k - 1]), float(ts[k])
    return float("nan"), float("nan")


def first_chord_ahead(ts: np.ndarray) -> tuple[float, float]:
    """(entry, exit) of the first chord ahead of an origin outside the bone; (nan, nan) if inside or none."""
    k = int(np.searchsorted(ts, 0.0))
    if k % 2 == 0 and k + 1 < len(ts):
        return float(ts[k]), float(ts[k + 1])
    return float("nan"), float("nan")


@dataclass(frozen=True)
class Isthmus:
    """A pedicle's isthmus (mm, deg): width across the pedicle axis, height, the transverse chord it came
    from, the medial angle of the pedicle axis to the mid-sagittal plane, its centre (frame coordinates) and
    the medial wall's transverse coordinate there."""

    width: float
    height: float
    chord: float
    medial_angle_deg: float
    centre: np.ndarray
    medial_wall: float


def canal_midline(
    triangles: np.ndarray, origin: np.ndarray, reach_mm: float = 60.0, search_mm: float = 12.0, step_mm: float = 0.5
) -> tuple[float, float, float]:
    """(posterior body wall, inner face of the lamina, height): anterior coordinates (mm) where the mid-sagittal
    line through ``origin`` (a point inside the body) leaves the body and next enters bone.  Where that line
    passes between two laminae (nothing behind within ``reach_mm``) the nearest height within ``search_mm``
    above or below whose line meets the lamina is used; its superior coordinate is the third value."""
    origin = np.asarray(origin, float)
    dz = np.arange(0.0, search_mm + step_mm / 2, step_mm)
    dz = np.r_[0.0, np.ravel(np.column_stack([dz[1:], -dz[1:]]))]
    starts = origin + dz[:, None] * np.array([0.0, 0.0, 1.0])
    for z_off, ts in zip(dz, line_crossings(triangles, starts, np.array([-1.0, 0.0, 0.0]))):
        _, exit_ = chord_through(ts)
        if not np.isfinite(exit_):
            continue
        behind = ts[ts > exit_ + _SAME_MM]
        if behind.size and behind[0] - exit_ <= reach_mm:
            return float(origin[0] - exit_), float(origin[0] - behind[0]), float(origin[2] + z_off)
    raise ValueError(
        f"no canal found: no mid-sagittal line within {search_mm} mm of the pedicles' height runs from the body "
        "to a lamina"
    )


def pedicle_isthmus(
    triangles: np.ndarray,
    side: float,
    height_mm: float,
    a_wall: float,
    a_back: float,
    step_mm: float = 0.5,
    reach_mm: float = 40.0,
    fit_mm: float = 3.0,
) -> Isthmus:
    """The isthmus of the pedicle on ``side`` (+1 right, -1 left) (module docstring).

    ``height_mm``: a first guess of the pedicle's mid-height; coronal positions ``a`` run every ``step_mm``
    from ``a_wall`` (the posterior body wall) back to ``a_back`` (the lamina's inner face); a transverse chord
    counts only when it starts within ``reach_mm`` of the mid-line; the medial angle is fitted over the chord
    midpoints within ``fit_mm`` of the isthmus."""
    a_all = np.arange(a_wall, a_back, -abs(step_mm))
    if a_all.size < 2:
        raise ValueError(f"no room for a pedicle between the body wall (a = {a_wall:.1f} mm) and the lamina")
    right = np.array([0.0, float(np.sign(side)), 0.0])
    z = np.full(a_all.size, float(height_mm))
    rows = np.full((a_all.size, 4), np.nan)  # r_in, r_out, s_lo, s_hi
    for _ in range(3):
        starts = np.stack([a_all, np.zeros_like(a_all), z], 1)
        lat = np.array([first_chord_ahead(ts) for ts in line_crossings(triangles, starts, right)])
        lat[lat[:, 0] > reach_mm] = np.nan
        # a re-centred height whose line starts inside bone (the body, a lamina) keeps the previous section
        good = np.isfinite(lat[:, 0])
        if not good.any():
            break
        r_mid = np.sign(side) * 0.5 * (lat[good, 0] + lat[good, 1])
        vert_o = np.stack([a_all[good], r_mid, z[good]], 1)
        vert = np.array([chord_through(ts) for ts in line_crossings(triangles, vert_o, np.array([0.0, 0.0, 1.0]))])
        rows[good] = np.column_stack([lat[good], z[good, None] + vert])
        z = np.where(np.isfinite(rows[:, 2]), 0.5 * (rows[:, 2] + rows[:, 3]), z)
    if not np.isfinite(rows[:, 0]).any():
        raise ValueError(f"no pedicle found on side {side:+.0f}: no bone lateral to the canal")
    rows = np.column_stack([rows, rows[:, 1] - rows[:, 0]])
    valid = np.isfinite(rows).all(axis=1)
    if not valid.any():
        raise ValueError(f"no pedicle section found on side {side:+.0f}")
    k = int(np.flatnonzero(valid)[np.argmin(rows[valid, 4])])
    height = float(np.min(rows[valid, 3] - rows[valid, 2]))
    r_centre = np.sign(side) * 0.5 * (rows[:, 0] + rows[:, 1])
    near = valid & (np.abs(a_all - a_all[k]) <= fit_mm)
    slope = np.polyfit(a_all[near], r_centre[near], 1)[0] if near.sum() >= 3 else 0.0
    theta = float(np.degrees(np.arctan(abs(slope))))
    centre = np.array([a_all[k], r_centre[k], 0.5 * (rows[k, 2] + rows[k, 3])])
    return Isthmus(
        width=float(rows[k, 4] * np.cos(np.radians(theta))),
        height=height,
        chord=float(rows[k, 4]),
        medial_angle_deg=theta,
        centre=centre,
        medial_wall=float(np.sign(side) * rows[k, 0]),
    )
