"""The extension stop from the bones: how far each inferior articular process (IAP) tip travels in extension
before it meets the vertebra below, on the model's own points.  Units: mm.

In extension the upper vertebra of a segment turns backwards about an axis near its disc, so its IAP tip starts
out along the tangent of a circle about that axis (`extension_path`): caudally and, the tip lying behind and
above the disc's centre, posteriorly.  The stop sits on that path (`tip_stops`): a compression-only strut along
it, closing once the tip has travelled the bone gap there (`ray_distances`: the first skin triangle of the lower
vertebra's posterior elements that the tip's path meets) less the soft tissue between the two bones (the tip's
cartilage and the fat pad of the capsule's inferior recess, `FacetContact.tip_soft_tissue_mm`).

Why per joint from the bones: one clearance for all levels either lets the lumbar segments extend more than
they flex or stops the thoracolumbar ones too early (docs/explanation/fe-model.md).  On the real-bone mean the
lumbar tips meet the lamina/pars below after 2.3-4.4 mm along their path, while the T7-T12 tips overhang the
lamina and meet nothing within 8 mm, which is the difference the two levels need.
"""

from __future__ import annotations

import numpy as np

from spinecohort.fe.connections import body_layer
from spinecohort.mesh.template import HexTemplate

#: the largest stop clearance (mm): a tip that meets no bone within it gets a stop that no 7.5 N·m extension
#: closes (a tip turned 10 deg about an axis 40 mm away travels 7 mm), and a 20 mm strut still has its
#: table's reach
MAX_CLEARANCE_MM = 8.0


def extension_path(tip: np.ndarray, centre: np.ndarray, lateral: np.ndarray, cranial: np.ndarray) -> np.ndarray:
    """(3,) unit direction in which the point ``tip`` starts to move when its vertebra turns about the axis
    ``lateral`` through ``centre``, in the sense that takes it caudally (extension for a point behind the axis)."""
    v = np.cross(lateral, tip - centre)
    n = np.linalg.norm(v)
    if n == 0:
        raise ValueError(f"the tip {tip} lies on the turning axis through {centre}: it has no path")
    v = v / n
    return -v if v @ cranial > 0 else v


def ray_distances(origins: np.ndarray, direction: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """(R,) distance along the unit ``direction`` from each of ``origins`` (R, 3) to the first of ``triangles``
    (T, 3, 3) it meets ahead, inf where it meets none (`spinecohort.mesh.radial.first_hits`)."""
    if not triangles.size:
        return np.full(len(origins), np.inf)
    from spinecohort.mesh.radial import first_hits

    faces = np.arange(3 * len(triangles)).reshape(-1, 3)
    return first_hits(origins, np.broadcast_to(direction, origins.shape), triangles.reshape(-1, 3), faces)


def tip_stops(
    template: HexTemplate,
    points: np.ndarray,
    pairs: np.ndarray,
    joints: list[tuple[str, str, float]],
    frames: dict[str, tuple[np.ndarray, np.ndarray]],
    soft_tissue_mm: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Per joint of ``pairs`` (IAP tip, SAP tip; ``joints``: upper, lower vertebra, side; ``frames``: each
    vertebra's anatomical frame and centre, `spinecohort.fe.facets.vertebra_frame`) the extension stop's strut
    direction (J, 3; from its node on the lower vertebra to the tip, i.e. against the tip's extension path) and
    its clearance (J,) mm: the bone gap along the path (`ray_distances` onto the lower vertebra's posterior skin,
    the sacrum's for S1, its articular surface left out: that contact is the joint's own) less ``soft_tissue_mm``, within
    0 .. `MAX_CLEARANCE_MM`.  The path turns about the lower vertebra's lateral axis through the disc's centre
    (the centroid of the two endplate node layers that bound the disc)."""
    if soft_tissue_mm < 0:
        raise ValueError(f"the extension stop's soft tissue must be >= 0 mm, got {soft_tissue_mm}")
    n2 = len(template.grid.nodes)
    direction, clearance = np.zeros((len(joints), 3)), np.zeros(len(joints))
    for j, ((iap, _), (up, lo, side)) in enumerate(zip(pairs, joints)):
        frame = frames[lo][0]
        disc = [body_layer(template, up, 0.0) * n2 + np.arange(n2), body_layer(template, lo, 1.0) * n2 + np.arange(n2)]
        centre = points[np.concatenate(disc)].mean(0)
        path = extension_path(points[iap], centre, frame[:, 0], frame[:, 2])
        skin = "SACRUM" if lo == "S1" else f"POST_{lo}"  # the sacrum is the lower side of an L5-S1 joint
        if skin not in template.elsets:
            raise ValueError(f"extension stop from the bones: the template has no skin {skin} for {lo}")
        tris = template.tris[template.elsets[skin]]
        surface = template.sites.get(f"facet_surface_sup_{'right' if side > 0 else 'left'}/{lo}")
        if surface is not None:
            tris = tris[~np.isin(tris, surface).all(axis=1)]
        gap = ray_distances(points[iap][None], path, points[tris])[0]
        direction[j] = -path
        clearance[j] = np.clip(gap - soft_tissue_mm, 0.0, MAX_CLEARANCE_MM)
    return direction, clearance
