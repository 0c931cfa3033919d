"""Labels of the sacrum's posterior elements at the lumbosacral joint: the S1 superior articular surfaces, the
S1 laminae's cranial edge and the first tubercle of the median sacral crest, in the S1 frame.

S1 frame: origin at the centre of the S1 plate, z its outward normal (cranial), x the world x (patient's right)
made orthogonal to it, y = z x x (anterior); mm.  The rules follow the lumbar ones of
:mod:`spinecohort.anatomy.assemble` where the sacrum allows:

* **superior articular surface** (``facet_surface_sup_<side>``): the sacrum vertices within
  :data:`FACET_PATCH_MM` of the Remus S1 facet patch (``S1_PD<l|r>_a``) of that side, as for L2-L5; the
  capsule's insertion (``site_CL_sup_<side>``) is the surface's 1.5 mm boundary band, as for every level;
* **superior articular process** (SAP): the sacrum vertices behind the plate's posterior edge within
  :data:`SAP_RADIUS_MM` of the articular surface's centroid; its tip (``sap_tip_<L|R>``) is its highest vertex;
* **lamina** (per side): vertices behind the canal's front (the plate's posterior edge), between
  :data:`MIDLINE_MM` off the midline and :data:`LAMINA_INSET_MM` medial of the articular surface's centroid,
  no lower than :data:`SEGMENT_DEPTH_MM` below the articular surface's lowest vertex (the S1 segment); the
  ligamentum flavum inserts on its canal side (outward normal ``y > 0.3``), the cranial 30 % of it
  (``site_LF_sup_<side>``, the lumbar rule); ``lamina_upper_<L|R>`` is its highest vertex;
* **median crest** (the spinous process of S1): vertices within :data:`MIDLINE_MM` of the midline, behind the
  lamina band, facing posteriorly (``y < -0.3``), in the S1 segment; the interspinous ligament inserts on its
  cranial 20 % (``site_ISL_sup``, the lumbar rule), ``spinous_upper`` is its highest vertex, ``spinous_tip``
  its most posterior one and ``site_SSL`` the crest within 5 mm of it.

Anchors are single vertex ids (local to the sacrum's vertex array); sites and surfaces vertex-id arrays.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from spinecohort.anatomy import labeling

#: a sacrum vertex within this distance (mm) of the Remus S1 facet patch is articular surface (L2-L5: 1.5)
FACET_PATCH_MM = 1.5
#: radius (mm) about the articular surface's centroid that holds the superior articular process
SAP_RADIUS_MM = 14.0
#: half-width (mm) of the midline band: the median crest inside it, the laminae outside
MIDLINE_MM = 4.0
#: the lamina ends this far (mm) medial of the articular surface's centroid (the SAP's base)
LAMINA_INSET_MM = 6.0
#: depth (mm) below the articular surface's lowest vertex taken as the S1 segment (S1's laminae and crest)
SEGMENT_DEPTH_MM = 14.0


def s1_frame(points: np.ndarray, plate: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Centre (3,) and (3, 3) rows x (right), y (anterior), z (plate normal, cranial) of the S1 frame."""
    c = points[plate].mean(0)
    z = np.linalg.svd(points[plate] - c)[2][-1]
    z = z * np.sign(z[2])
    x = np.array([1.0, 0.0, 0.0]) - z[0] * z
    x /= np.linalg.norm(x)
    return c, np.stack([x, np.cross(z, x), z])


def articular_surface(points: np.ndarray, faces: np.ndarray, patch_points: np.ndarray) -> np.ndarray:
    """Vertex ids of the sacrum within `FACET_PATCH_MM` of a facet patch's points (mm), its largest patch."""
    near = np.flatnonzero(cKDTree(patch_points).query(points)[0] < FACET_PATCH_MM)
    if len(near) < 5:
        raise ValueError(f"the S1 facet patch lies more than {FACET_PATCH_MM} mm from the sacrum surface")
    return labeling._largest_component(near, faces)


def sacral_labels(points: np.ndarray, faces: np.ndarray, plate: np.ndarray, patches: dict) -> dict:
    """The sacrum's articular surfaces, insertion sites and anchors (module docstring): ``{"surfaces":
    {"sup_left", "sup_right"}, "sites": {"LF_sup_left", ..., "ISL_sup", "SSL"}, "anchors": {"sap_tip_L", ...}}``,
    vertex ids into `points` (the sacrum, mm); plate: the S1 plate's vertex ids; patches: ``"left"`` /
    ``"right"`` -> (P, 3) points of the Remus S1 facet patches."""
    centre, rows = s1_frame(points, plate)
    loc = (points - centre) @ rows.T
    nloc = labeling.vertex_normals(points, faces) @ rows.T
    y_front = loc[plate, 1].min()  # the plate's posterior edge: the canal's front
    out: dict = {"surfaces": {}, "sites": {}, "anchors": {}}
    lamina = {}
    for side, sgn in (("left", -1.0), ("right", 1.0)):
        surf = articular_surface(points, faces, patches[side])
        out["surfaces"][f"sup_{side}"] = surf
        c = loc[surf].mean(0)
        behind = loc[:, 1] < y_front - 2.0
        sap = np.flatnonzero(behind & (np.linalg.norm(loc - c, axis=1) < SAP_RADIUS_MM))
        out["anchors"][f"sap_tip_{side[0].upper()}"] = int(sap[np.argmax(loc[sap, 2])])
        z_low = loc[surf, 2].min() - SEGMENT_DEPTH_MM
        lam = np.flatnonzero(
            behind
            & (sgn * loc[:, 0] > MIDLINE_MM)
            & (sgn * loc[:, 0] < sgn * c[0] - LAMINA_INSET_MM)
            & (loc[:, 2] > z_low)
        )
        inner = lam[nloc[lam, 1] > 0.3]  # the canal side
        if len(inner) < 5:
            raise ValueError(f"the sacrum's {side} S1 lamina has no canal side ({len(inner)} vertices)")
        out["sites"][f"LF_sup_{side}"] = inner[loc[inner, 2] > np.quantile(loc[inner, 2], 0.7)]
        out["anchors"][f"lamina_upper_{side[0].upper()}"] = int(lam[np.argmax(loc[lam, 2])])
        lamina[side] = lam
    z_low = min(loc[s, 2].min() for s in out["surfaces"].values()) - SEGMENT_DEPTH_MM
    y_lam = min(loc[lam, 1].mean() for lam in lamina.values())
    crest = np.flatnonzero(
        (np.abs(loc[:, 0]) < MIDLINE_MM) & (loc[:, 1] < y_lam) & (nloc[:, 1] < -0.3) & (loc[:, 2] > z_low)
    )
    if len(crest) < 5:
        raise ValueError(f"the sacrum has no median crest behind its S1 laminae ({len(crest)} vertices)")
    tip = int(crest[np.argmin(loc[crest, 1])])
    out["anchors"].update({"spinous_upper": int(crest[np.argmax(loc[crest, 2])]), "spinous_tip": tip})
    out["sites"]["ISL_sup"] = crest[loc[crest, 2] > np.quantile(loc[crest, 2], 0.8)]
    out["sites"]["SSL"] = crest[np.linalg.norm(loc[crest] - loc[tip], axis=1) < 5.0]
    return out
