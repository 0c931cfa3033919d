"""Ligaments at their anatomical insertions, as fibre bundles, and the facet articular surfaces, on the hex
template of a cohort whose landmarks carry insertion sites (`Landmarks.sites`, the real-bone cohort).

A ligament whose insertion is wide (ALL, PLL, ligamentum flavum, facet capsule) is ``k`` fibres spread across
its insertion instead of one spring between two anchor points, so it resists a turn about its own long axis
(a lateral bend or an axial turn of the segment) by the spread of its fibres, as the tissue does; the group's
area is split across the fibres (`spinecohort.fe.materials.fibre_law`), so a uniform stretch gives the single
spring's force.  ISL, SSL and ITL are narrow or short: one spring each.

The posterior ligaments and facet joints join every two adjacent levels of T1..L5 and, where the landmarks carry
the sacrum's anchors (``anchor_<name>/S1``), L5 and the sacrum (`posterior_joints`): L5-S1's lower ends are on
the sacrum's skin (S1's superior articular processes, laminae and median crest); the iliolumbar ligament, which
takes the ITL's place there, is not modelled.

* ALL / PLL: the hex column's outer-ring nodes across the arc of the site (``site_ALL_inf`` of the upper vertebra,
  ``site_ALL_sup`` of the lower one, the arc's ends averaged), on the upper vertebra's inferior and the lower
  one's superior endplate layer: vertical fibres, the same O-grid node at both ends.
* LF: skin nodes of the two laminae's edges (``site_LF_inf_<side>`` upper, ``site_LF_sup_<side>`` lower), at
  ``k`` evenly spaced positions along the bundle's width (the first principal axis of both sites), the upper
  and lower end of a fibre at the same position.
* CL: the capsule is a sleeve round the joint, so its insertions (the rims of the two articular surfaces,
  ``site_CL_inf_<side>`` upper, ``site_CL_sup_<side>`` lower) are sampled at ``k`` evenly spaced angles about the
  joint's centre in its plane, the two ends of a fibre at the same angle.

Each selection is an assignment (`distinct_nearest`), so a bundle has ``k`` distinct nodes at each end when its
site has them.  Units: mm, degrees.
"""

from __future__ import annotations

import numpy as np

#: the ligaments that can be fibre bundles, and the template's default fibre count of each (config
#: ``fe.ligaments.<group>.fibres``); the others stay one spring
BUNDLE_GROUPS = ("ALL", "PLL", "LF", "CL")
#: facet articular surfaces carried to the template: (Landmarks site name, template key prefix)
FACET_SURFACES = (
    "facet_surface_sup_left",
    "facet_surface_sup_right",
    "facet_surface_inf_left",
    "facet_surface_inf_right",
)
#: the labeled pedicles carried to the template (`spinecohort.fe.pedicles`)
PEDICLES = ("pedicle_left", "pedicle_right")


#: the sacrum's anchors (``Landmarks.sites`` ``anchor_<name>/S1``, one vertex each) that L5-S1's posterior
#: ligaments and facet joints need (`spinecohort.anatomy.sacrum`)
SACRAL_ANCHORS = ("spinous_tip", "spinous_upper", "lamina_upper_L", "lamina_upper_R", "sap_tip_L", "sap_tip_R")


def has_sites(sites: dict) -> bool:
    """Whether landmark sites (`Landmarks.sites`) carry what bundles and articular surfaces need."""
    return any(k.startswith("facet_surface_") for k in sites) and any(k.startswith("site_CL_") for k in sites)


def distinct_nearest(candidates: np.ndarray, targets: np.ndarray, period: float | None = None) -> np.ndarray:
    """Index into `candidates` (C,) of a distinct candidate for each of the `targets` (K,) scalars, the total
    distance least (an assignment); `period`: distances wrap (angles).  Fewer candidates than targets: each
    candidate once, the targets nearest to them."""
    from scipy.optimize import linear_sum_assignment  # here: the shard jobs import this module, never call it

    d = np.abs(candidates[None, :] - np.asarray(targets)[:, None])
    if period is not None:
        d = np.minimum(d, period - d)
    rows, cols = linear_sum_assignment(d)
    return cols[np.argsort(rows)]


def width_axis(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Unit first principal axis (mm-weighted) of the two point sets together: the bundle's width."""
    p = np.concatenate([a, b])
    _, _, vt = np.linalg.svd(p - p.mean(0), full_matrices=False)
    return vt[0]


def across_width(upper: np.ndarray, lower: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Indices into `upper` (U, 3) and `lower` (L, 3) points (mm) of `k` fibres spread along the bundle's
    width: fibre j at the position j / (k - 1) of each site's own extent along the common width axis."""
    axis = width_axis(upper, lower)
    out = []
    for p in (upper, lower):
        t = p @ axis
        targets = np.linspace(t.min(), t.max(), k) if k > 1 else np.array([np.median(t)])
        out.append(distinct_nearest(t, targets))
    return out[0], out[1]


def plane_frame(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Centre (3,) and (3, 3) orthonormal rows (in-plane u, in-plane v, normal) of the total-least-squares
    plane of `points` (mm)."""
    c = points.mean(0)
    _, _, vt = np.linalg.svd(points - c, full_matrices=False)
    return c, vt


def around_ring(upper: np.ndarray, lower: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Indices into `upper` (U, 3) and `lower` (L, 3) rim points (mm) of `k` fibres at evenly spaced angles
    about the joint's centre in the plane fitted to both rims, the two ends of a fibre at the same angle."""
    c, rows = plane_frame(np.concatenate([upper, lower]))
    targets = np.linspace(-np.pi, np.pi, k, endpoint=False)
    out = []
    for p in (upper, lower):
        ang = np.arctan2((p - c) @ rows[1], (p - c) @ rows[0])
        out.append(distinct_nearest(ang, targets, period=2 * np.pi))
    return out[0], out[1]


def ring_arc(angles_deg: np.ndarray) -> tuple[float, float]:
    """(start, end) deg of the shortest arc holding the angles (unwrapped about their circular mean)."""
    a = np.radians(angles_deg)
    mean = np.arctan2(np.sin(a).mean(), np.cos(a).mean())
    rel = np.angle(np.exp(1j * (a - mean)))
    return float(np.degrees(mean + rel.min())), float(np.degrees(mean + rel.max()))


def site_angles_deg(points: np.ndarray, centre: np.ndarray, frame: np.ndarray, half_axes: np.ndarray) -> np.ndarray:
    """Angles (deg) of points (mm) about an endplate's centre in its frame (columns lateral, anterior, normal),
    in the O-grid's unit cross-section (each axis divided by the endplate's half extent)."""
    local = (points - centre) @ frame[:, :2] / half_axes
    return np.degrees(np.arctan2(local[:, 1], local[:, 0]))


def arc_nodes(outer_deg: np.ndarray, arcs: list[tuple[float, float]], k: int) -> np.ndarray:
    """Indices into the outer ring (angles `outer_deg`, deg) of `k` fibres across the mean of the `arcs`
    (start, end deg): targets at the centres of k equal parts of the arc."""
    start = float(np.degrees(np.angle(np.mean([np.exp(1j * np.radians(a)) for a, _ in arcs]))))
    width = float(np.mean([(b - a) % 360.0 for a, b in arcs]))
    targets = start + width * (np.arange(k) + 0.5) / k
    return distinct_nearest(outer_deg % 360.0, targets % 360.0, period=360.0)


def posterior_bundle(
    pts: np.ndarray, upper: np.ndarray, lower: np.ndarray, group: str, k: int
) -> tuple[np.ndarray, np.ndarray]:
    """Vertex ids (of `pts`, mm) of the `k` fibres of an LF or CL bundle between the site `upper` (vertex ids on
    the upper vertebra) and `lower`: (k,) upper ends, (k,) lower ends (`across_width`, `around_ring`)."""
    if min(len(upper), len(lower)) < k:
        raise ValueError(
            f"a {group} insertion site has {min(len(upper), len(lower))} vertices, fewer than its {k} fibres"
        )
    pick = around_ring if group == "CL" else across_width
    iu, il = pick(pts[upper], pts[lower], k)
    return upper[iu], lower[il]


def site_vertices(sites: dict, group: str, where: str, level: str) -> np.ndarray | None:
    """The landmark site ``site_<group>_<where>`` of `level` (vertex ids), None if absent."""
    return sites.get(f"site_{group}_{where}/{level}")


def template_sites(sites: dict[str, np.ndarray], remap: np.ndarray) -> dict[str, np.ndarray]:
    """The facet articular surfaces and the labeled pedicles of `sites` (`Landmarks.sites`) as template node ids
    (`remap`: vertex -> template node, -1 where none): the facet contacts are fitted on the surfaces
    (`spinecohort.fe.facet_geometry`), the hex pedicles on the pedicles (`spinecohort.fe.pedicles`)."""
    out = {}
    for key, v in sites.items():
        name = key.split("/")[0]
        if name in PEDICLES:  # the pedicle's root inside the body's labels is the hex body's; its skin is the rest
            nodes = remap[v][remap[v] >= 0]
            if len(nodes):
                out[key] = np.sort(nodes)
        elif name in FACET_SURFACES:
            nodes = remap[v]
            if np.any(nodes < 0):
                raise ValueError(f"landmark site {key} has vertices on no surface part of the template")
            out[key] = np.sort(nodes)
    return out


def _endplate_layer(layers: list[dict], level: str, t: float) -> int:
    return next(i for i, ly in enumerate(layers) if ly["kind"] == "body" and ly["level"] == level and ly["t"] == t)


def posterior_joints(landmarks) -> list[tuple[str, str]]:
    """The (upper, lower) vertebra pairs that get posterior ligaments and facet joints: every two adjacent levels
    of T1..L5 when the landmarks have anchors, and L5-S1 when they also have the sacrum's anchors
    (``anchor_<name>/S1`` sites: S1's superior articular process and laminae, the median crest)."""
    from spinecohort.cohort.landmarks import LEVELS

    if not landmarks.anchors:
        return []
    pairs = list(zip(LEVELS[:-1], LEVELS[1:]))
    if all(landmarks.site(f"anchor_{n}", "S1") is not None for n in SACRAL_ANCHORS):
        pairs.append((LEVELS[-1], "S1"))
    return pairs


def template_ligaments(
    landmarks, remap: np.ndarray, pts: np.ndarray, grid, layers: list[dict], eps: dict, fibres: dict
):
    """The template's ligament elements between adjacent levels: (list of (node, node), list of groups, the
    template's `sites` ({} without landmark sites), fibres per ligament of each group).

    Without landmark sites (or for a group with 1 fibre): one spring per ligament and side between the landmark
    anchors (SSL, ISL, LF, CL, ITL), PLL / ALL at the posterior / anterior midline node of the outer ring.
    With sites, ALL, PLL, LF and CL are bundles of ``fibres[group]`` fibres (module docstring).  Fibres of one
    ligament are consecutive.  remap: surface vertex -> template node (-1: none); eps: (level, 'sup'|'inf') ->
    `Endplate` of the shape `pts` (mm); layers: the template's node-layer plan."""
    from spinecohort.cohort.landmarks import LEVELS

    a, n2 = landmarks.anchors, len(grid.nodes)
    bundled = has_sites(landmarks.sites)
    k_of = {g: int(fibres.get(g, 1)) if bundled else 1 for g in BUNDLE_GROUPS}
    lig: list[tuple[int, int]] = []
    groups: list[str] = []

    def add(group, u, v):
        lig.extend(zip(np.atleast_1d(u).tolist(), np.atleast_1d(v).tolist()))
        groups.extend([group] * np.size(u))

    def anchor(name: str, level: str) -> int:
        # T1..L5: the landmark anchors (one vertex per level); S1: the sacrum's ``anchor_<name>`` site
        if level == "S1":
            return int(landmarks.site(f"anchor_{name}", "S1")[0])
        return int(a[name][LEVELS.index(level)])

    joints = []
    for up, lo in posterior_joints(landmarks):
        add("SSL", remap[anchor("spinous_tip", up)], remap[anchor("spinous_tip", lo)])
        add("ISL", remap[anchor("spinous_lower", up)], remap[anchor("spinous_upper", lo)])
        for s, side in (("L", "left"), ("R", "right")):
            for g, anchor_up, anchor_lo, where_up, where_lo in (
                ("LF", "lamina_lower", "lamina_upper", f"inf_{side}", f"sup_{side}"),
                ("CL", "iap_tip", "sap_tip", f"inf_{side}", f"sup_{side}"),
            ):
                site_up = site_vertices(landmarks.sites, g, where_up, up)
                site_lo = site_vertices(landmarks.sites, g, where_lo, lo)
                if k_of[g] > 1 and site_up is not None and site_lo is not None:
                    u, v = posterior_bundle(pts, site_up, site_lo, g, k_of[g])
                    add(g, remap[u], remap[v])
                elif k_of[g] > 1:  # a group's fibres share its area equally: every ligament needs its sites
                    raise ValueError(f"landmark sites lack site_{g}_{where_up}/{up} or site_{g}_{where_lo}/{lo}")
                else:
                    add(g, remap[anchor(f"{anchor_up}_{s}", up)], remap[anchor(f"{anchor_lo}_{s}", lo)])
            joints.append((remap[anchor(f"iap_tip_{s}", up)], remap[anchor(f"sap_tip_{s}", lo)]))
            if lo != "S1":  # L5-S1: the iliolumbar ligament takes the ITL's place (not modelled)
                add("ITL", remap[anchor(f"tp_tip_{s}", up)], remap[anchor(f"tp_tip_{s}", lo)])
    # PLL / ALL: the outer ring, from each vertebra's inferior endplate to the superior endplate (or S1 plate) below
    outer_xy = grid.nodes[grid.outer]
    outer_deg = np.degrees(np.arctan2(outer_xy[:, 1], outer_xy[:, 0]))
    midline = {
        "PLL": grid.outer[np.argmin(outer_xy[:, 1] + 1e-6 * np.abs(outer_xy[:, 0]))],
        "ALL": grid.outer[np.argmax(outer_xy[:, 1] - 1e-6 * np.abs(outer_xy[:, 0]))],
    }
    for vert, lv in enumerate(LEVELS):
        below = LEVELS[vert + 1] if vert + 1 < len(LEVELS) else "S1"
        inf_layer = _endplate_layer(layers, lv, 0.0)
        below_layer = _endplate_layer(layers, below, 1.0) if below != "S1" else 0
        for g in ("PLL", "ALL"):
            ring = np.atleast_1d(midline[g])
            arcs = []
            for level, where in ((lv, "inf"), (below, "sup")):
                v = site_vertices(landmarks.sites, g, where, level)
                if v is not None and k_of[g] > 1:
                    ep = eps[(level, where)]
                    arcs.append(ring_arc(site_angles_deg(pts[v], ep.centre, ep.frame, ep.half_axes)))
            if arcs:
                ring = grid.outer[arc_nodes(outer_deg, arcs, k_of[g])]
            add(g, inf_layer * n2 + ring, below_layer * n2 + ring)
    if not bundled:
        return lig, groups, {}, {}
    sites = template_sites(landmarks.sites, remap)
    if joints:
        sites["facet_joints"] = np.asarray(joints, dtype=np.int64)
    return lig, groups, sites, {g: k for g, k in k_of.items() if k > 1}


def fibres_per_ligament(ligaments: dict) -> dict[str, int]:
    """Fibres per ligament group from the config's ``fe.ligaments`` block (``fibres``, default 1): what
    `spinecohort.mesh.template.build_template` bundles at the insertion sites."""
    return {group: int(law.get("fibres", 1)) for group, law in ligaments.items()}
