"""Pedicle isthmus and vertebral canal measured by chords of the closed bone surface, without part labels.

A chord is the segment of a straight line inside the bone: the line crosses a closed triangulated surface an
even number of times, and the crossings, sorted, alternate entry and exit.  Everything here is in the
vertebra frame (anterior, right, superior; mm), on the vertebra's own closed surface:

* **canal** (mid-sagittal line at a given height): from the body centre posteriorly, the body's exit is the
  posterior body wall, the next entry the inner face of the lamina; the gap between them is the canal depth;
* **pedicle** of one side: for every coronal position ``a`` between the posterior body wall and the lamina,
  a line from the canal mid-line outwards, turned anteriorly by an angle phi, enters the bone at the
  pedicle's medial wall and leaves it at its lateral wall (the pedicle chord), and the vertical line through
  that chord's middle gives the pedicle's height chord; the two are re-centred on each other twice, so the
  lines pass through the pedicle's centre.  A pedicle converging anteriorly at the angle theta is crossed at
  its true width by the line turned by phi = theta and more obliquely (longer, width / cos(phi - theta)) by
  every other line, so the **isthmus width** is the shortest chord over positions and angles (the caliper
  at the narrowest place), the **height** the shortest vertical chord (the pedicle height of a sagittal
  slice), the **canal width** the largest distance between the two medial walls met by transverse lines.

The labels play no part: a thin labeled strip at the pedicle base measures the same pedicle as a whole one.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: crossings closer than this along a line (mm) are one crossing (a line through a shared edge or vertex)
_SAME_MM = 1e-6


def line_crossings(
    triangles: np.ndarray, origins: np.ndarray, direction: np.ndarray, with_faces: bool = False
) -> list[np.ndarray] | list[tuple[np.ndarray, np.ndarray]]:
    """Sorted line parameters (mm along the unit ``direction``) where each line ``origin + t d`` crosses the
    triangles ((F, 3, 3) mm); one array per origin ((R, 3) mm), or (parameters, crossed triangle indices)
    with ``with_faces``.  Moller-Trumbore, edges inclusive, coincident crossings merged."""
    d = np.asarray(direction, float)
    d = d / np.linalg.norm(d)
    v0, e1, e2 = triangles[:, 0], triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0]
    p = np.cross(d, e2)  # (F, 3)
    det = np.einsum("ij,ij->i", e1, p)
    ok = np.flatnonzero(np.abs(det) > 1e-12)
    v0, e1, e2, p, inv = v0[ok], e1[ok], e2[ok], p[ok], 1.0 / det[ok]
    s = np.asarray(origins, float)[:, None, :] - v0[None]  # (R, F, 3)
    u = np.einsum("rfj,fj->rf", s, p) * inv
    qv = np.cross(s, e1[None])
    v = (qv @ d) * inv
    t = np.einsum("rfj,fj->rf", qv, e2) * inv
    hit = (u >= 0) & (v >= 0) & (u + v <= 1)
    out = []
    for row_t, row_hit in zip(t, hit):
        order = np.argsort(row_t[row_hit])
        ts, faces = row_t[row_hit][order], ok[row_hit][order]
        if ts.size:
            keep = np.r_[True, np.diff(ts) > _SAME_MM]
            ts, faces = ts[keep], faces[keep]
        out.append((ts, faces) if with_faces else ts)
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
    """A pedicle's isthmus (mm, deg): its width (the shortest chord), height (the shortest vertical chord),
    the angle the shortest chord's line is turned anteriorly from the transverse axis (the pedicle's
    convergence), its centre (frame coordinates), and the medial wall's distance from the mid-line along the
    transverse lines from the mid-line at ``positions_mm`` (their anterior coordinates; nan: no pedicle)."""

    width: float
    height: float
    medial_angle_deg: float
    centre: np.ndarray
    positions_mm: np.ndarray
    medial_wall_mm: np.ndarray


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


def _scan(triangles, direction, a_all, height_mm, reach_mm, min_chord_mm, wall_cos):
    """Per coronal position: (entry, exit) of the first chord along ``direction`` from the mid-line, and the
    (low, high) superior coordinates of the vertical chord through its middle, re-centred twice; nan where the
    line starts inside bone, meets nothing within ``reach_mm``, grazes a wall (chord < ``min_chord_mm``) or
    cuts a corner (a crossed face whose normal is farther than arccos(``wall_cos``) from the transverse axis:
    a pedicle is entered through its medial wall and left through its lateral wall)."""
    up = np.array([0.0, 0.0, 1.0])
    normals = np.cross(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0])
    lateral_cos = np.abs(normals[:, 1]) / np.maximum(np.linalg.norm(normals, axis=1), 1e-30)
    z = np.full(a_all.size, float(height_mm))
    rows = np.full((a_all.size, 4), np.nan)
    for _ in range(3):
        starts = np.stack([a_all, np.zeros_like(a_all), z], 1)
        lat = np.full((a_all.size, 2), np.nan)
        for i, (ts, faces) in enumerate(line_crossings(triangles, starts, direction, with_faces=True)):
            k = int(np.searchsorted(ts, 0.0))
            if k % 2 == 0 and k + 1 < len(ts) and min(lateral_cos[faces[k]], lateral_cos[faces[k + 1]]) >= wall_cos:
                lat[i] = ts[k], ts[k + 1]
        lat[(lat[:, 0] > reach_mm) | (lat[:, 1] - lat[:, 0] < min_chord_mm)] = np.nan
        # a re-centred height whose line starts inside bone (the body, a lamina) keeps the previous section
        good = np.isfinite(lat[:, 0])
        if not good.any():
            break
        mids = starts[good] + 0.5 * (lat[good, 0] + lat[good, 1])[:, None] * direction
        vert = np.array([chord_through(ts) for ts in line_crossings(triangles, mids, up)])
        rows[good] = np.column_stack([lat[good], z[good, None] + vert])
        z = np.where(np.isfinite(rows[:, 2]), 0.5 * (rows[:, 2] + rows[:, 3]), z)
    return rows


def pedicle_isthmus(
    triangles: np.ndarray,
    side: float,
    height_mm: float,
    a_wall: float,
    a_back: float,
    step_mm: float = 0.5,
    reach_mm: float = 40.0,
    angles_deg: tuple[float, ...] = (0.0, -10.0, 10.0, 20.0, 30.0, 40.0),
    min_chord_mm: float = 2.0,
    wall_cos: float = 0.5,
) -> Isthmus:
    """The isthmus of the pedicle on ``side`` (+1 right, -1 left) (module docstring).

    ``height_mm``: a first guess of the pedicle's mid-height; coronal positions ``a`` run every ``step_mm``
    from ``a_wall`` (the posterior body wall) back to ``a_back``; the lines from the mid-line run laterally,
    turned anteriorly by each of ``angles_deg`` (a pedicle converging anteriorly at the angle theta is crossed
    at its true width by the line turned by theta); a chord counts when it starts within ``reach_mm`` of the
    mid-line, is at least ``min_chord_mm`` long (shorter ones graze the posterior body wall) and crosses two
    faces within arccos(``wall_cos``) of facing transversely (`_scan`)."""
    a_all = np.arange(a_wall - step_mm, a_back, -abs(step_mm))
    if a_all.size < 2:
        raise ValueError(f"no room for a pedicle between the body wall (a = {a_wall:.1f} mm) and the lamina")
    sign = float(np.sign(side))
    best = None
    heights = []
    medial = np.full(a_all.size, np.nan)
    for phi in angles_deg:
        direction = np.array([np.sin(np.radians(phi)), sign * np.cos(np.radians(phi)), 0.0])
        rows = _scan(triangles, direction, a_all, height_mm, reach_mm, min_chord_mm, wall_cos)
        valid = np.isfinite(rows).all(axis=1)
        if not valid.any():
            continue
        heights.append(np.min(rows[valid, 3] - rows[valid, 2]))
        # the medial wall as a transverse line meets it; turned lines fill the positions it misses
        wall = np.where(valid, rows[:, 0] * np.cos(np.radians(phi)), np.nan)
        medial = np.where(np.isfinite(medial), medial, wall)
        chord = rows[:, 1] - rows[:, 0]
        k = int(np.flatnonzero(valid)[np.argmin(chord[valid])])
        if best is None or chord[k] < best[0]:
            start = np.array([a_all[k], 0.0, 0.5 * (rows[k, 2] + rows[k, 3])])
            best = (chord[k], phi, start + 0.5 * (rows[k, 0] + rows[k, 1]) * direction, k)
    if best is None:
        raise ValueError(f"no pedicle found on side {side:+.0f}: no bone lateral to the canal")
    return Isthmus(
        width=float(best[0]),
        height=float(min(heights)),
        medial_angle_deg=float(best[1]),
        centre=best[2],
        positions_mm=a_all,
        medial_wall_mm=medial,
    )
