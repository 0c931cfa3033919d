"""A thoracic vertebra as a smooth map of the lumbar template (the remeshed Remus L1), in its body frame.

Every thoracic level of the reference is the vertex set of one template (the Remus L1 remeshed) moved by
:func:`map_vertebra`, so the template's region labels, endplate sets, anchors and ligament sites hold on it by
index.  The map acts in the template's frame
(``local``: x to the right, y anterior, z superior, mm, origin midway between the endplate centroids) and is
built from a partition of unity, every weight a smoothstep of a distance:

* vertebral body: scaled by ``width / L1 width`` in x and ``depth / L1 depth`` in y; in z by a factor that
  runs linearly from ``posterior height / L1's`` at the posterior wall to ``anterior height / L1's`` at the
  anterior wall (the wedge); optionally narrowed towards its anterior wall (``taper``, a heart shape);
* posterior elements (behind the posterior wall, blended in over ``blend_mm`` along the pedicles): scaled by
  the arch factors (``arch_xyz``) about the posterior wall, which stays attached to the scaled body;
* articular processes: a swirl about a vertical axis through the articular pillar (midway between the
  centroids of the superior and the inferior process of a side): every point turns about the axis by an angle
  that depends only on its distance from the axis and its height, the full turn within ``facet_core_mm``,
  none beyond ``facet_radius_mm``.  A map that turns each circle about the axis rigidly is one-to-one for any
  angle, so even a turn of 110 deg (the lumbar articular face, facing medially, turned to face posteriorly and
  laterally) folds no triangle where a rotation faded by the distance to the process folded beyond 25 deg.  The
  angle runs from the inferior process's turn (at and below a fifth of the pillar's height) to the superior
  process's turn (at and above four fifths) with the height, and falls to none midway between
  them (the pars, where the pedicle meets the lamina: a turned pars twists the pedicle, whose height falls by a
  quarter at T1 with a half turn there); each joint's two
  processes turn about nearly the same axis by the same angle, so the joint stays congruent;
* spinous process: turned about the transverse axis through its base and stretched along its length so that
  its tip reaches ``spinous_tip`` (its direction, caudal inclination and length).

The body and arch weights are smoothsteps of a coordinate; the spinous weight is 1 on the process's vertices
and falls to 0 at ``radius_mm`` from them (distance to the nearest
region vertex, a Lipschitz field in space), times the arch weight (0 in the body), so the map is continuous,
smooth away from the region boundaries, and leaves the body to the body map.  Millimetres and degrees.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree


@dataclass(frozen=True)
class LevelShape:
    """Per-level targets of :func:`map_vertebra` (mm, deg).

    ``body``: endplate width, depth, anterior and posterior body height; ``arch_xyz``: scale of the posterior
    elements in x, y, z; ``facet_sup_deg`` / ``facet_inf_deg``: the swirl's turn at the superior / inferior
    articular processes (positive turns a lumbar superior facet, facing medially, towards and past the coronal
    plane); ``spinous_tip``: the target tip (local, mm) or None to keep it;
    ``taper``: the fraction by which the body narrows from its middle to its anterior wall (a heart-shaped
    outline; 0 keeps the template's)."""

    width_mm: float
    depth_mm: float
    height_anterior_mm: float
    height_posterior_mm: float
    arch_xyz: tuple[float, float, float]
    facet_sup_deg: float = 0.0
    facet_inf_deg: float = 0.0
    spinous_tip: tuple[float, float, float] | None = None
    taper: float = 0.0


@dataclass(frozen=True)
class Template:
    """The template vertebra in its frame: ``local`` (N, 3) mm, its body dimensions (as
    `spinecohort.anatomy.morphometry.body_dimensions` measures them), the y of its anterior and posterior
    walls at the mid-line, and vertex indices per region name."""

    local: np.ndarray
    width_mm: float
    depth_mm: float
    height_anterior_mm: float
    height_posterior_mm: float
    y_anterior: float
    y_posterior: float
    regions: dict[str, np.ndarray]


def smoothstep(t: np.ndarray) -> np.ndarray:
    """0 below 0, 1 above 1, C1-smooth cubic between."""
    t = np.clip(t, 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def region_weight(points: np.ndarray, members: np.ndarray, radius_mm: float) -> np.ndarray:
    """(N,) weight 1 on ``points[members]`` falling smoothly to 0 at ``radius_mm`` from the nearest member."""
    d = cKDTree(points[members]).query(points)[0]
    return smoothstep(1.0 - d / radius_mm)


def _rotate_in_plane(p: np.ndarray, centre: np.ndarray, angle_rad: np.ndarray, axes: tuple[int, int]) -> np.ndarray:
    """Points turned by ``angle_rad`` (per point) in the plane of coordinates ``axes`` (i to j positive)
    about ``centre``: (0, 1) about the vertical axis, (1, 2) about the transverse axis."""
    i, j = axes
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    d = p - centre
    out = p.copy()
    out[:, i] = centre[i] + c * d[:, i] - s * d[:, j]
    out[:, j] = centre[j] + s * d[:, i] + c * d[:, j]
    return out


def map_vertebra(
    t: Template,
    shape: LevelShape,
    blend_mm: float = 6.0,
    radius_mm: float = 8.0,
    facet_core_mm: float = 4.5,
    facet_radius_mm: float = 13.5,
) -> np.ndarray:
    """(N, 3) local coordinates (mm) of the template moved onto ``shape`` (module docstring); the turn of an
    articular pillar is whole within ``facet_core_mm`` of its axis and fades out at ``facet_radius_mm`` (both
    times the arch's transverse scale), the spinous process's turn fades out over ``radius_mm``."""
    p = t.local
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    sx, sy = shape.width_mm / t.width_mm, shape.depth_mm / t.depth_mm
    sz_a = shape.height_anterior_mm / t.height_anterior_mm
    sz_p = shape.height_posterior_mm / t.height_posterior_mm
    ax, ay, az = shape.arch_xyz
    # the wedge: the vertical scale runs from the posterior to the anterior wall
    f = np.clip((y - t.y_posterior) / (t.y_anterior - t.y_posterior), 0.0, 1.0)
    sz_body = sz_p + (sz_a - sz_p) * f
    w = smoothstep((t.y_posterior - y) / blend_mm)  # 0 in the body, 1 in the arch behind the pedicles' base
    out = np.empty_like(p)
    # the heart shape: the body's width falls off towards its anterior wall, smoothly from the middle
    y_mid = 0.5 * (t.y_anterior + t.y_posterior)
    narrow = 1.0 - shape.taper * smoothstep((y - y_mid) / (t.y_anterior - y_mid))
    out[:, 0] = x * ((1 - w) * sx * narrow + w * ax)
    y_wall = sy * t.y_posterior
    out[:, 1] = (1 - w) * sy * y + w * (y_wall + ay * (y - t.y_posterior))
    out[:, 2] = z * ((1 - w) * sz_body + w * az)
    # the radii scale with the arch (the pillars of a narrower arch lie closer to the mid-line)
    out = _swirl_pillars(out, t, shape.facet_sup_deg, shape.facet_inf_deg, ax * facet_core_mm, ax * facet_radius_mm)
    if shape.spinous_tip is not None:
        out = _aim_spinous(out, p, t, np.asarray(shape.spinous_tip, float), radius_mm, w)
    return out


#: the swirl's angle midway between the two processes of a pillar (the pars), as a fraction of the processes'
#: turn: none, so the pedicle is not twisted
PARS_TURN = 0.0


def _swirl_pillars(
    out: np.ndarray, t: Template, sup_deg: float, inf_deg: float, core_mm: float, radius_mm: float
) -> np.ndarray:
    """Both articular pillars swirled about their vertical axes (module docstring): the left one clockwise
    seen from above by a positive turn, the right one anticlockwise (towards the coronal plane)."""
    if sup_deg == 0.0 and inf_deg == 0.0:
        return out
    for side, sign in (("left", -1.0), ("right", 1.0)):
        c_sup = out[t.regions[f"facet_sup_{side}"]].mean(0)
        c_inf = out[t.regions[f"facet_inf_{side}"]].mean(0)
        axis = 0.5 * (c_sup + c_inf)
        r = np.hypot(out[:, 0] - axis[0], out[:, 1] - axis[1])
        h = (out[:, 2] - c_inf[2]) / (c_sup[2] - c_inf[2])  # 0 at the inferior process, 1 at the superior
        profile = PARS_TURN + (1.0 - PARS_TURN) * smoothstep(np.abs(2.0 * h - 1.0) / 0.6)
        angle = np.radians(inf_deg + (sup_deg - inf_deg) * smoothstep((h - 0.2) / 0.6)) * profile
        out = _rotate_in_plane(out, axis, sign * angle * smoothstep((radius_mm - r) / (radius_mm - core_mm)), (0, 1))
    return out


def _aim_spinous(
    out: np.ndarray, p: np.ndarray, t: Template, tip: np.ndarray, radius_mm: float, arch: np.ndarray
) -> np.ndarray:
    """Turn the spinous process about the transverse axis through its base and stretch it along its axis so
    that its tip (its vertex farthest from the base) lands on ``tip``; the weight runs from 0 at the base to 1
    at a third of the process's length (so the lamina stays), times the region weight and the arch weight."""
    sp = t.regions["spinous"]
    base_y = out[sp, 1].max()
    base = np.array([0.0, base_y, out[sp][np.argmax(out[sp, 1]), 2]])
    k = sp[np.argmax(np.linalg.norm(out[sp] - base, axis=1))]
    now = out[k] - base
    want = tip - base
    length_now = np.hypot(now[1], now[2])
    angle = np.arctan2(want[2], -want[1]) - np.arctan2(now[2], -now[1])
    stretch = np.hypot(want[1], want[2]) / length_now
    along = smoothstep((base_y - out[:, 1]) / (0.33 * length_now))
    wt = along * region_weight(p, sp, radius_mm) * arch
    d = out - base
    axis = now / np.linalg.norm(now)
    axis[0] = 0.0
    axis /= np.linalg.norm(axis)
    proj = d @ axis
    moved = out + ((stretch - 1.0) * wt * np.maximum(proj, 0.0))[:, None] * axis
    return _rotate_in_plane(moved, base, -angle * wt, (1, 2))
