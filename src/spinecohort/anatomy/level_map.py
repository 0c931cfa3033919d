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
* articular processes: turned about a vertical axis through the process's centroid by the level's facet
  rotation (the superior and the inferior process each by the turn of its joint, so each joint's two
  processes turn alike; one turn of the whole pillar where both turns are equal);
* spinous process: turned about the transverse axis through its base and stretched along its length so that
  its tip reaches ``spinous_tip`` (its direction, caudal inclination and length).

Weights: 1 on the region's vertices and falling to 0 at ``radius_mm`` from them (distance to the nearest
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
    elements in x, y, z; ``facet_sup_deg`` / ``facet_inf_deg``: rotation of the superior / inferior articular
    processes towards the coronal plane; ``spinous_tip``: the target tip (local, mm) or None to keep it;
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
    t: Template, shape: LevelShape, blend_mm: float = 6.0, radius_mm: float = 8.0, facet_radius_mm: float = 12.0
) -> np.ndarray:
    """(N, 3) local coordinates (mm) of the template moved onto ``shape`` (module docstring); the turn of an
    articular process fades out over ``facet_radius_mm``, the spinous process's over ``radius_mm``."""
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
    # one articular pillar per side turns as a whole when both processes turn alike (two overlapping turns
    # about different axes fold the pillar between them)
    if shape.facet_sup_deg == shape.facet_inf_deg:
        turns = ((("sup", "inf"), shape.facet_sup_deg),)
    else:
        turns = ((("sup",), shape.facet_sup_deg), (("inf",), shape.facet_inf_deg))
    for which, angle in turns:
        if angle == 0.0:
            continue
        for side, sign in (("left", -1.0), ("right", 1.0)):
            members = np.concatenate([t.regions[f"facet_{w}_{side}"] for w in which])
            wf = w * region_weight(p, members, facet_radius_mm)  # never into the body
            out = _rotate_in_plane(out, out[members].mean(0), sign * np.radians(angle) * wf, (0, 1))
    if shape.spinous_tip is not None:
        out = _aim_spinous(out, p, t, np.asarray(shape.spinous_tip, float), radius_mm, w)
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
