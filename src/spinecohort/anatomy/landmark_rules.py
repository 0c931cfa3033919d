"""Geometric rules that find the same 15 landmarks on any vertebra mesh given in its own frame.

Frame: x to the right, y anterior, z up (mm), the vertebra roughly upright.  The rules:

* midline = ``|x - median x| < 8 %`` of the width; ``ANT`` = the most anterior midline point; the spinous
  tip = the midline point farthest from ``ANT`` (posterior in the lumbar spine, postero-caudal in the thoracic);
* vertebral body: top and bottom = the extreme z of the midline points in the anterior 15 % of the
  antero-posterior extent; posterior wall = the first point behind the largest gap in the sorted y of the
  midline points at mid-body height (the gap is the body's interior, the next one the canal); left/right =
  the extreme x of the points between 20 % and 80 % of the body depth at mid-height;
* transverse-process tips = the extreme x of the whole vertebra; articular-process tips = the highest
  (superior) and lowest (inferior) points behind the body and more than 12 % of the width off the midline.

Order of the returned rows: the 8 corners of the body box (x, y, z each low/high, z fastest), spinous tip,
left and right transverse tips, left/right superior articular tips, left/right inferior articular tips.
"""

from __future__ import annotations

import numpy as np

N_LANDMARKS = 15


def _arg(mask: np.ndarray, values: np.ndarray) -> int:
    if not mask.any():
        raise ValueError("a landmark rule selected no vertex: is the vertebra in its own upright frame?")
    return int(np.flatnonzero(mask)[np.argmax(values[mask])])


def vertebra_landmarks(points: np.ndarray) -> np.ndarray:
    """(15, 3) landmark points of one vertebra (mm), in the order of the module docstring."""
    p = np.asarray(points, float)
    width = np.ptp(p[:, 0])
    x = p[:, 0] - np.median(p[:, 0])
    mid = np.abs(x) < 0.08 * width
    ant = _arg(mid, p[:, 1])
    dist = np.linalg.norm(p - p[ant], axis=1)
    spin = _arg(mid, dist)
    ap = p[ant, 1] - p[spin, 1]
    column = mid & (p[:, 1] > p[ant, 1] - 0.15 * ap)
    z_top, z_bot = p[column, 2].max(), p[column, 2].min()
    z_mid, half = 0.5 * (z_top + z_bot), 0.5 * (z_top - z_bot)
    band = mid & (np.abs(p[:, 2] - z_mid) < 0.6 * half)
    ys = np.sort(p[band, 1])[::-1]
    y_post = ys[np.argmax(-np.diff(ys)) + 1]
    depth = p[ant, 1] - y_post
    slab = (
        (p[:, 1] < p[ant, 1] - 0.2 * depth) & (p[:, 1] > y_post + 0.2 * depth) & (np.abs(p[:, 2] - z_mid) < 0.5 * half)
    )
    x_l, x_r = p[slab, 0].min(), p[slab, 0].max()
    corners = np.array([[a, b, c] for a in (x_l, x_r) for b in (y_post, p[ant, 1]) for c in (z_bot, z_top)])
    post = p[:, 1] < y_post - 2.0
    lat = np.abs(x) > 0.12 * width
    tips = [
        spin,
        int(np.argmin(x)),
        int(np.argmax(x)),
        _arg(post & lat & (x < 0), p[:, 2]),
        _arg(post & lat & (x > 0), p[:, 2]),
        _arg(post & lat & (x < 0), -p[:, 2]),
        _arg(post & lat & (x > 0), -p[:, 2]),
    ]
    return np.r_[corners, p[tips]]


def similarity_from_points(src: np.ndarray, dst: np.ndarray, with_scale: bool = True):
    """Least-squares ``dst ~ s R src + t`` (Umeyama 1991): returns R (3, 3), s, t (3,)."""
    mu_s, mu_d = src.mean(0), dst.mean(0)
    a, b = src - mu_s, dst - mu_d
    u, sig, vt = np.linalg.svd(b.T @ a)
    d = np.eye(3)
    d[2, 2] = np.sign(np.linalg.det(u @ vt))
    rot = u @ d @ vt
    s = float(np.trace(np.diag(sig) @ d) / np.sum(a**2)) if with_scale else 1.0
    return rot, s, mu_d - s * rot @ mu_s
