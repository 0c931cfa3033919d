"""Vertebral morphometry measured on a labeled vertebra surface, and its comparison with published values.

The quantities are those of Panjabi's cadaver studies (thoracic 1991, lumbar 1992; facets 1993), measured
here on a triangulated surface instead of with a 3-D digitiser on the dry bone:

=========================  =====  ==========================================================================
quantity                   unit   definition (Panjabi's abbreviation)
=========================  =====  ==========================================================================
endplate_width_upper       mm     transverse width of the superior endplate rim (EPWu)
endplate_width_lower       mm     transverse width of the inferior endplate rim (EPWl)
endplate_depth_upper       mm     antero-posterior depth of the superior endplate in the mid-sagittal plane (EPDu)
endplate_depth_lower       mm     the same for the inferior endplate (EPDl)
body_height_anterior       mm     superior to inferior rim at the anterior mid-line (VBHa)
body_height_posterior      mm     superior to inferior rim at the posterior mid-line (VBHp)
pedicle_width[_left/right] mm     width of the pedicle at its isthmus, across the pedicle in the transverse
                                  plane: the shortest chord from the medial to the lateral wall (PDW)
pedicle_height[...]        mm     the pedicle's shortest cranio-caudal chord (PDH)
canal_width                mm     largest transverse distance between the medial walls of the pedicles (SCW)
canal_depth                mm     posterior body wall to the inner face of the lamina, mid-line (SCD)
spinous_length             mm     inner face of the lamina at the mid-line to the spinous tip (SPL)
facet_<sup|inf>_transverse deg    angle between the facet plane's trace in the transverse plane and the
                                  mid-sagittal plane: 0 sagittal facet (lumbar-like), 90 coronal (thoracic-like)
facet_<sup|inf>_sagittal   deg    angle between the facet plane's trace in the sagittal plane and the
                                  transverse plane: 0 horizontal facet, 90 vertical
=========================  =====  ==========================================================================

Without a side suffix the pedicle and facet values are the mean of left and right, as the published tables
that pool sides.  The facet angles follow the plane-angle idea of Panjabi 1993 but use the conventions in the
table above (folded into 0..90 deg); Panjabi's own angle origins are not reproduced, so facet orientation is
compared with ranges stated in these conventions (Masharawi 2004: facet to the mid-sagittal plane).

Pedicles and canal are measured by chords of the closed bone surface (`spinecohort.anatomy.isthmus`), so a
labeled pedicle region that covers only part of the pedicle does not change them.
Everything is measured in the vertebra's own frame (`vertebra_frame`): superior = the mean normal of the two
endplate planes, anterior = body centre minus canal centre (or a hint for a body alone), right = anterior x
superior.  The part labels are the region names of ``spinecohort.anatomy.labels`` (``PARTS``).
Millimetres and degrees throughout.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from importlib import resources

import numpy as np
import pandas as pd

from spinecohort.anatomy import isthmus

#: Vertebra part labels (the anatomy labels' vertebral regions).
PARTS: tuple[str, ...] = (
    "body",
    "pedicle_left",
    "pedicle_right",
    "lamina",
    "spinous",
    "transverse_left",
    "transverse_right",
    "facet_sup_left",
    "facet_sup_right",
    "facet_inf_left",
    "facet_inf_right",
)

#: Unit of every measured quantity (a suffix ``_left`` / ``_right`` keeps its quantity's unit).
UNITS: dict[str, str] = {
    "endplate_width_upper": "mm",
    "endplate_width_lower": "mm",
    "endplate_depth_upper": "mm",
    "endplate_depth_lower": "mm",
    "body_height_anterior": "mm",
    "body_height_posterior": "mm",
    "pedicle_width": "mm",
    "pedicle_height": "mm",
    "canal_width": "mm",
    "canal_depth": "mm",
    "spinous_length": "mm",
    "facet_sup_transverse": "deg",
    "facet_sup_sagittal": "deg",
    "facet_inf_transverse": "deg",
    "facet_inf_sagittal": "deg",
}

REFERENCE_CSV = "data/morphometry/panjabi.csv"


@dataclass(frozen=True)
class VertebraFrame:
    """Orthonormal vertebra frame: ``origin`` (mm) and unit ``anterior``, ``right``, ``superior`` axes."""

    origin: np.ndarray
    anterior: np.ndarray
    right: np.ndarray
    superior: np.ndarray

    @property
    def axes(self) -> np.ndarray:
        """(3, 3) rows anterior, right, superior."""
        return np.stack([self.anterior, self.right, self.superior])

    def local(self, points_mm: np.ndarray) -> np.ndarray:
        """(N, 3) coordinates (anterior, right, superior) in mm of (N, 3) points."""
        return (np.asarray(points_mm, float) - self.origin) @ self.axes.T


def _unit(v: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(v)
    if not n > 0:
        raise ValueError("cannot normalise a zero vector (degenerate vertebra geometry)")
    return v / n


def _indices(sel, n: int, name: str) -> np.ndarray:
    """Vertex indices of a selection given as indices or an (n,) boolean mask; a clear error when empty."""
    sel = np.asarray(sel)
    idx = np.flatnonzero(sel) if sel.dtype == bool else sel.astype(np.int64).ravel()
    if idx.size == 0:
        raise ValueError(f"vertex set {name!r} is empty")
    if idx.min() < 0 or idx.max() >= n:
        raise ValueError(f"vertex set {name!r} indexes outside the {n} vertices")
    return idx


def plane_fit(points_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Total-least-squares plane of (N >= 3) points: (centroid mm, unit normal); normal sign arbitrary."""
    p = np.asarray(points_mm, float)
    if p.shape[0] < 3:
        raise ValueError(f"a plane needs at least 3 points, got {p.shape[0]}")
    c = p.mean(axis=0)
    _, _, vt = np.linalg.svd(p - c, full_matrices=False)
    return c, vt[-1]


def vertex_normals(points_mm: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(N, 3) area-weighted unit vertex normals of a consistently oriented triangle mesh."""
    p = np.asarray(points_mm, float)
    f = np.asarray(faces, np.int64)
    fn = np.cross(p[f[:, 1]] - p[f[:, 0]], p[f[:, 2]] - p[f[:, 0]])  # length = 2 x area
    vn = np.zeros_like(p)
    for k in range(3):
        np.add.at(vn, f[:, k], fn)
    norm = np.linalg.norm(vn, axis=1, keepdims=True)
    return np.divide(vn, norm, out=np.zeros_like(vn), where=norm > 0)


def endplate_sets(
    points_mm: np.ndarray,
    faces: np.ndarray,
    up_hint: np.ndarray,
    cone_deg: float = 45.0,
    band_fraction: float = 0.35,
    iterations: int = 3,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Superior and inferior endplate vertices of a vertebral body surface without labels, and its superior axis.

    Start from the body's shortest principal axis oriented along ``up_hint``; an endplate vertex faces within
    ``cone_deg`` of +-up and lies in the top (bottom) ``band_fraction`` of the body's height.  The axis is then
    the mean normal of the two fitted endplate planes, and the selection is repeated ``iterations`` times.
    Returns (superior indices, inferior indices, unit superior axis).
    """
    p = np.asarray(points_mm, float)
    normals = vertex_normals(p, faces)
    centred = p - p.mean(axis=0)
    up = np.linalg.svd(centred, full_matrices=False)[2][-1]
    up = up if up @ np.asarray(up_hint, float) > 0 else -up
    cos_cone = np.cos(np.radians(cone_deg))
    for _ in range(max(1, iterations)):
        h = centred @ up
        lo, hi = h.min(), h.max()
        band = band_fraction * (hi - lo)
        sup = np.flatnonzero((normals @ up > cos_cone) & (h > hi - band))
        inf = np.flatnonzero((normals @ up < -cos_cone) & (h < lo + band))
        if sup.size < 3 or inf.size < 3:
            raise ValueError("no endplate found: too few up/down-facing vertices near the top or bottom of the body")
        n_sup = plane_fit(p[sup])[1]
        n_inf = plane_fit(p[inf])[1]
        up = _unit((n_sup if n_sup @ up > 0 else -n_sup) + (n_inf if n_inf @ up > 0 else -n_inf))
    return sup, inf, up


def canal_centre(points_mm: np.ndarray, parts: Mapping[str, np.ndarray]) -> np.ndarray:
    """Centre of the vertebral canal (mm): the mean of the centroids of both pedicles and the lamina."""
    p = np.asarray(points_mm, float)
    return np.mean(
        [p[_indices(parts[k], len(p), k)].mean(axis=0) for k in ("pedicle_left", "pedicle_right", "lamina")], 0
    )


def vertebra_frame(
    points_mm: np.ndarray,
    superior_endplate,
    inferior_endplate,
    body,
    canal_centre_mm: np.ndarray | None = None,
    anterior_hint: np.ndarray | None = None,
) -> VertebraFrame:
    """The vertebra frame (module docstring): superior = mean of the two endplate-plane normals (oriented from
    the inferior towards the superior endplate), anterior = body centroid minus ``canal_centre_mm`` (or
    ``anterior_hint`` for a body alone) made perpendicular to superior, origin midway between the endplate
    centroids."""
    p = np.asarray(points_mm, float)
    sup = p[_indices(superior_endplate, len(p), "superior_endplate")]
    inf = p[_indices(inferior_endplate, len(p), "inferior_endplate")]
    c_sup, n_sup = plane_fit(sup)
    c_inf, n_inf = plane_fit(inf)
    up0 = c_sup - c_inf
    superior = _unit((n_sup if n_sup @ up0 > 0 else -n_sup) + (n_inf if n_inf @ up0 > 0 else -n_inf))
    body_c = p[_indices(body, len(p), "body")].mean(axis=0)
    if canal_centre_mm is not None:
        a = body_c - np.asarray(canal_centre_mm, float)
    elif anterior_hint is not None:
        a = np.asarray(anterior_hint, float)
    else:
        raise ValueError("the anterior direction needs the canal centre (posterior parts) or an anterior_hint")
    anterior = _unit(a - (a @ superior) * superior)
    right = np.cross(anterior, superior)
    return VertebraFrame(origin=0.5 * (c_sup + c_inf), anterior=anterior, right=right, superior=superior)


def _rim_band(p: np.ndarray, body: np.ndarray, endplate: np.ndarray, outward: np.ndarray, slab_mm: float):
    """Body vertices within ``slab_mm`` below the endplate's outermost point along ``outward`` (its rim)."""
    c, n = plane_fit(p[endplate])
    n = n if n @ outward > 0 else -n
    d_body = (p[body] - c) @ n
    return body[d_body >= ((p[endplate] - c) @ n).max() - slab_mm]


def body_dimensions(
    local_mm: np.ndarray,
    body,
    superior_endplate,
    inferior_endplate,
    slab_mm: float = 2.0,
    strip_mm: float = 3.0,
    max_widen: int = 4,
) -> dict[str, float]:
    """Endplate widths and depths and the anterior / posterior body heights (mm), Panjabi's EPW, EPD, VBH.

    ``local_mm``: all vertices in the vertebra frame (`VertebraFrame.local`).  The rim band of an endplate is
    the body vertices within ``slab_mm`` of its outermost point (`_rim_band`; the slab is widened in steps of
    ``slab_mm`` when the band misses the mid-line strip); its width is the band's
    transverse extent, its depth the antero-posterior extent of the band within ``strip_mm`` of the mid-line.
    A height is the superior distance between the superior and the inferior rim corners at the anterior
    (posterior) mid-line: in each rim's mid-line strip the vertex extreme along the 45-deg diagonal between
    anterior (posterior) and superior (inferior), so a sharp corner is found exactly and a rounded rim at the
    middle of its bend.
    """
    q = np.asarray(local_mm, float)
    n = len(q)
    body = _indices(body, n, "body")
    sup = _indices(superior_endplate, n, "superior_endplate")
    inf = _indices(inferior_endplate, n, "inferior_endplate")
    s_axis = np.array([0.0, 0.0, 1.0])
    mid = 0.5 * (q[body, 1].min() + q[body, 1].max())
    out: dict[str, float] = {}
    rims = {}
    for name, ep, outward in (("upper", sup, s_axis), ("lower", inf, -s_axis)):
        # a saddle-shaped rim (its mid-line lower than its lateral corners) leaves the mid-line out of a thin
        # slab: widen the slab in steps of slab_mm, at most max_widen times, until the mid-line strip is reached
        for k in range(1, max_widen + 1):
            b = q[_rim_band(q, body, ep, outward, k * slab_mm)]
            strip = b[np.abs(b[:, 1] - mid) <= strip_mm]
            if len(strip):
                break
        else:
            raise ValueError(
                f"the {name} endplate rim has no vertex within {strip_mm} mm of the mid-sagittal plane "
                f"within {max_widen * slab_mm} mm of its outermost point"
            )
        out[f"endplate_width_{name}"] = float(np.ptp(b[:, 1]))
        out[f"endplate_depth_{name}"] = float(np.ptp(strip[:, 0]))
        rims[name] = strip
    for side, sign in (("anterior", 1.0), ("posterior", -1.0)):
        top = rims["upper"][np.argmax(rims["upper"][:, 2] + sign * rims["upper"][:, 0]), 2]
        bottom = rims["lower"][np.argmax(-rims["lower"][:, 2] + sign * rims["lower"][:, 0]), 2]
        out[f"body_height_{side}"] = float(top - bottom)
    return out


def vertebra_triangles(local_mm: np.ndarray, faces: np.ndarray, parts: Mapping[str, np.ndarray]) -> np.ndarray:
    """(F, 3, 3) triangles (mm, frame coordinates) of the faces whose three vertices belong to the vertebra
    (the union of ``parts``): the closed surface the chords of `spinecohort.anatomy.isthmus` cut."""
    q = np.asarray(local_mm, float)
    mask = np.zeros(len(q), bool)
    for name, sel in parts.items():
        mask[_indices(sel, len(q), name)] = True
    f = np.asarray(faces, np.int64)
    f = f[mask[f].all(axis=1)]
    if len(f) == 0:
        raise ValueError("the vertebra's vertices contain no whole triangle")
    return q[f]


def arch_dimensions(
    local_mm: np.ndarray, faces: np.ndarray, parts: Mapping[str, np.ndarray], zone: float = 0.67
) -> dict[str, float]:
    """Pedicle isthmus width and height per side (Panjabi's PDW, PDH), canal width and depth (SCW, SCD), mm,
    from chords of the vertebra's closed surface (`spinecohort.anatomy.isthmus`), in the vertebra frame.

    The pedicle labels give only the first guess of the pedicles' mid-height (the mean superior coordinate of
    their vertices); the measured places come from the bone surface.  The pedicles are searched in the anterior
    ``zone`` of the canal depth (behind it the articular pillar, not the pedicle, bounds the canal).  Canal
    depth: the mid-sagittal gap between the posterior body wall and the lamina's inner face at the pedicles'
    mid-height (or the nearest height where the mid-line meets a lamina, `isthmus.canal_midline`); canal
    width: the largest transverse distance between the two pedicles' medial walls over the coronal positions
    where both bound the canal (the canal's transverse diameter between the pedicles, as CT measures it)."""
    q = np.asarray(local_mm, float)
    tri = vertebra_triangles(q, faces, parts)
    n = len(q)
    ped = np.concatenate([_indices(parts[k], n, k) for k in ("pedicle_left", "pedicle_right")])
    z0 = float(q[ped, 2].mean())
    a_wall, a_lam, _ = isthmus.canal_midline(tri, np.array([0.0, 0.0, z0]))
    a_back = a_wall - zone * (a_wall - a_lam)
    out: dict[str, float] = {}
    walls = []
    for side, sign in (("left", -1.0), ("right", 1.0)):
        ist = isthmus.pedicle_isthmus(tri, sign, z0, a_wall, a_back)
        out[f"pedicle_width_{side}"], out[f"pedicle_height_{side}"] = ist.width, ist.height
        walls.append(ist.medial_wall_mm)
    for k in ("pedicle_width", "pedicle_height"):
        out[k] = 0.5 * (out[f"{k}_left"] + out[f"{k}_right"])
    both = walls[0] + walls[1]
    if not np.isfinite(both).any():
        raise ValueError("no coronal position where transverse lines from the canal meet both pedicles")
    out["canal_width"] = float(np.nanmax(both))
    out["canal_depth"] = a_wall - a_lam
    return out


def _lamina_inner_point(
    q: np.ndarray, parts: Mapping[str, np.ndarray], strip_mm: float, depth_mm: float = 1.0
) -> np.ndarray:
    """The canal's posterior mid-line point: among the lamina vertices within ``strip_mm`` of the mid-line, the
    most anterior coordinate, at the transverse and vertical centre of those within ``depth_mm`` of it (a flat
    inner face has no single most anterior vertex); the spinous process's if the lamina has none there."""
    for name in ("lamina", "spinous"):
        pts = q[_indices(parts[name], len(q), name)]
        pts = pts[np.abs(pts[:, 1]) <= strip_mm]
        if len(pts):
            front = pts[:, 0].max()
            point = pts[pts[:, 0] >= front - depth_mm].mean(axis=0)
            point[0] = front
            return point
    raise ValueError(f"neither lamina nor spinous process has a vertex within {strip_mm} mm of the mid-line")


def spinous_length(local_mm: np.ndarray, parts: Mapping[str, np.ndarray], strip_mm: float = 3.0) -> float:
    """Panjabi's SPL (mm): from the canal's posterior mid-line point (`_lamina_inner_point`) to the spinous
    tip, the spinous vertex farthest from it (thoracic processes point caudally, lumbar ones posteriorly)."""
    q = np.asarray(local_mm, float)
    base = _lamina_inner_point(q, parts, strip_mm)
    tip = q[_indices(parts["spinous"], len(q), "spinous")]
    return float(np.linalg.norm(tip - base, axis=1).max())


def facet_angles(local_mm: np.ndarray) -> tuple[float, float]:
    """(transverse, sagittal) plane angles in degrees of the plane fitted to facet points (module docstring):
    transverse = atan2(|n_a|, |n_r|), sagittal = atan2(|n_a|, |n_s|) of the plane's unit normal n."""
    n = plane_fit(local_mm)[1]
    a, r, s = np.abs(n)
    return float(np.degrees(np.arctan2(a, r))), float(np.degrees(np.arctan2(a, s)))


def facet_angles_deg(normal: np.ndarray, frame: np.ndarray, side: float) -> tuple[float, float]:
    """(transverse, frontal) angle (deg) of a joint plane with unit `normal` (SAP -> IAP) on `side` (+1 right,
    -1 left) of a vertebra with `frame` (columns lateral right, anterior, cranial), in the convention of
    `spinecohort.fe.facets.FacetContact.normal` and of the facet rows of the morphometry table: transverse = the plane's angle to the transverse plane
    (the normal's to the cranial axis), frontal = the plane's angle to the frontal plane, positive when the SAP
    faces medially, negative when laterally (atan2 of the medial and posterior components)."""
    medial = -side * frame[:, 0]
    t = float(np.degrees(np.arccos(np.clip(normal @ frame[:, 2], -1.0, 1.0))))
    f = float(np.degrees(np.arctan2(normal @ medial, normal @ -frame[:, 1])))
    return t, f


#: the vertebra frame's axes (columns: lateral right, anterior, cranial) in its local coordinates (anterior, right,
#: superior; `VertebraFrame.local`)
LOCAL_AXES = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])


def facet_facing(local_mm: np.ndarray, outward: np.ndarray, side: float) -> float:
    """Frontal angle (deg, `facet_angles_deg`) of the plane fitted to facet points ``local_mm`` (N, 3) in the
    vertebra frame (anterior, right, superior), its normal turned to the side of ``outward`` (3,) (the articular
    surface's outward direction): positive when the facet faces medially, negative laterally (``side`` +1 right,
    -1 left); the signed counterpart of the transverse angle (90 minus its magnitude, for a facet facing
    backwards)."""
    n = plane_fit(local_mm)[1]
    n = n if n @ np.asarray(outward, float) >= 0 else -n
    return facet_angles_deg(n, LOCAL_AXES, side)[1]


def measure_vertebra(
    points_mm: np.ndarray,
    faces: np.ndarray,
    parts: Mapping[str, np.ndarray],
    superior_endplate,
    inferior_endplate,
    facet_surfaces: Mapping[str, np.ndarray] | None = None,
    anterior_hint: np.ndarray | None = None,
) -> dict[str, float]:
    """Every quantity of the module table that the labels allow, for one vertebra.

    ``parts``: region name -> vertex indices or mask (at least ``body``); ``facet_surfaces``: ``sup_left`` ...
    -> articular-surface vertices (defaults to the whole ``facet_*`` regions).  Without pedicles and lamina only
    the body is measured, with ``anterior_hint`` giving the anterior direction.
    """
    p = np.asarray(points_mm, float)
    posterior = all(k in parts for k in ("pedicle_left", "pedicle_right", "lamina"))
    canal = canal_centre(p, parts) if posterior else None
    frame = vertebra_frame(p, superior_endplate, inferior_endplate, parts["body"], canal, anterior_hint)
    q = frame.local(p)
    out = body_dimensions(q, parts["body"], superior_endplate, inferior_endplate)
    if posterior:
        out.update(arch_dimensions(q, faces, parts))
    if "spinous" in parts and ("lamina" in parts):
        out["spinous_length"] = spinous_length(q, parts)
    surfaces = dict(facet_surfaces or {})
    for which in ("sup", "inf"):
        angles = []
        for side in ("left", "right"):
            sel = surfaces.get(f"{which}_{side}", parts.get(f"facet_{which}_{side}"))
            if sel is None:
                continue
            t, s = facet_angles(q[_indices(sel, len(q), f"facet_{which}_{side}")])
            out[f"facet_{which}_transverse_{side}"], out[f"facet_{which}_sagittal_{side}"] = t, s
            angles.append((t, s))
        if angles:
            out[f"facet_{which}_transverse"], out[f"facet_{which}_sagittal"] = np.mean(angles, axis=0).tolist()
    return out


def parts_of_vertebra(region: np.ndarray, region_names, vertebra: np.ndarray) -> dict[str, np.ndarray]:
    """``parts`` for `measure_vertebra` from per-vertex region labels: name -> vertex indices of the vertices
    of one vertebra (``vertebra``: (N,) mask) whose ``region`` index names a `PARTS` region in
    ``region_names`` (the label order, e.g. ``spinecohort.anatomy.labels.REGIONS``); absent parts are left out."""
    region = np.asarray(region)
    vertebra = np.asarray(vertebra, bool)
    names = list(region_names)
    out = {}
    for name in PARTS:
        if name in names:
            idx = np.flatnonzero(vertebra & (region == names.index(name)))
            if idx.size:
                out[name] = idx
    if "body" not in out:
        raise ValueError("the vertebra has no vertex labeled 'body'")
    return out


def measure_spine(
    points_mm: np.ndarray,
    faces: np.ndarray,
    region: np.ndarray,
    level: np.ndarray,
    region_names,
    level_names,
    endplates: Mapping[str, tuple[np.ndarray, np.ndarray]],
) -> pd.DataFrame:
    """Long table (level, quantity, value) of `measure_vertebra` for every level that has endplates.

    ``region``, ``level``: (N,) per-vertex indices into ``region_names`` / ``level_names`` (-1: no level);
    ``endplates``: level name -> (superior, inferior) endplate vertex indices.  The input of
    `compare_with_reference`."""
    level = np.asarray(level)
    names = list(level_names)
    rows = []
    for lv, (sup, inf) in endplates.items():
        parts = parts_of_vertebra(region, region_names, level == names.index(lv))
        for quantity, value in measure_vertebra(points_mm, faces, parts, sup, inf).items():
            rows.append({"level": lv, "quantity": quantity, "value": value})
    return pd.DataFrame(rows, columns=["level", "quantity", "value"])


def measure_body(points_mm: np.ndarray, faces: np.ndarray, up_hint, anterior_hint) -> dict[str, float]:
    """Endplate widths/depths and body heights (mm) of an unlabeled vertebral body surface (closed, welded):
    endplates found by `endplate_sets`, the frame by `vertebra_frame` with ``anterior_hint``."""
    sup, inf, _ = endplate_sets(points_mm, faces, np.asarray(up_hint, float))
    body = np.arange(len(points_mm))
    return measure_vertebra(points_mm, faces, {"body": body}, sup, inf, anterior_hint=np.asarray(anterior_hint, float))


def reference_table() -> pd.DataFrame:
    """The published morphometry (``spinecohort/data/morphometry/panjabi.csv``; provenance in its README):
    one row per level, quantity and source with mean, sd, sem, n, low, high, unit, source, locator, provenance."""
    with resources.files("spinecohort").joinpath(REFERENCE_CSV).open("r", encoding="utf-8") as fh:
        table = pd.read_csv(fh, comment="#")
    bad = sorted(set(table["quantity"]) - set(UNITS))
    if bad:
        raise ValueError(f"{REFERENCE_CSV}: unknown quantities {bad}")
    return table


def reference_interval(row: Mapping, k_sd: float = 2.0) -> tuple[float, float, str]:
    """(low, high, criterion) of one reference row: its published range if it has one, else mean +- k_sd SD,
    with SD = SEM x sqrt(n) when only the standard error is published; (nan, nan, 'no interval') otherwise."""

    def val(key):
        v = row.get(key)
        return float(v) if v is not None and not pd.isna(v) else float("nan")

    low, high, mean, sd, sem, n = (val(k) for k in ("low", "high", "mean", "sd", "sem", "n"))
    if np.isfinite(low) and np.isfinite(high):
        return low, high, "published range"
    if not np.isfinite(sd) and np.isfinite(sem) and np.isfinite(n):
        sd = sem * np.sqrt(n)
        label = f"mean ± {k_sd:g} SD (SD = SEM·√{n:g})"
    else:
        label = f"mean ± {k_sd:g} SD"
    if np.isfinite(mean) and np.isfinite(sd):
        return mean - k_sd * sd, mean + k_sd * sd, label
    return float("nan"), float("nan"), "no interval"


def compare_with_reference(measured: pd.DataFrame, reference: pd.DataFrame, k_sd: float = 2.0) -> pd.DataFrame:
    """Verdict per (level, quantity, source) cell: the measured ``value`` against the reference interval
    (`reference_interval`): ``inside``, ``outside``, ``no interval`` (a mean without dispersion) or
    ``not measured``.  ``measured`` has columns level, quantity, value; a measured cell with no reference is
    listed with verdict ``no reference``."""
    missing = {"level", "quantity", "value"} - set(measured.columns)
    if missing:
        raise ValueError(f"the measured table lacks columns {sorted(missing)}")
    values = {(lv, qn): float(v) for lv, qn, v in zip(measured["level"], measured["quantity"], measured["value"])}
    rows = []
    for row in reference.to_dict("records"):
        low, high, crit = reference_interval(row, k_sd)
        v = values.get((row["level"], row["quantity"]), float("nan"))
        if not np.isfinite(v):
            verdict = "not measured"
        elif not (np.isfinite(low) and np.isfinite(high)):
            verdict = "no interval"
        else:
            verdict = "inside" if low <= v <= high else "outside"
        rows.append(
            {
                "level": row["level"],
                "quantity": row["quantity"],
                "value": v,
                "unit": row["unit"],
                "ref_mean": row.get("mean", float("nan")),
                "ref_low": low,
                "ref_high": high,
                "criterion": crit,
                "verdict": verdict,
                "source": row["source"],
            }
        )
    referenced = {(r["level"], r["quantity"]) for r in rows}
    for (lv, qn), v in values.items():
        if (lv, qn) not in referenced:
            base = qn.removesuffix("_left").removesuffix("_right")
            rows.append(
                {"level": lv, "quantity": qn, "value": v, "unit": UNITS.get(base, ""), "verdict": "no reference"}
            )
    return pd.DataFrame(rows)
