"""Facet-joint contact of every spine model: compression-only contact struts (ccx/Abaqus SPRINGA with a
one-sided force table) between the articular processes of each joint, in the exported decks and in the ROM
sub-models alike.  Units: mm, N, degrees.

Each joint (the inferior articular process (IAP) tip of the upper vertebra and the superior articular process
(SAP) tip of the lower one: the template's ``facet_joints``, else the capsular-ligament anchors) gets

* **joint contacts**: where the template has the joint's articular surfaces (a real-bone cohort,
  `spinecohort.mesh.ligament_sites`), `FacetContact.struts_per_joint` struts spread over the part of the two
  surfaces that face each other, along the surfaces' own normal on the model's points
  (`spinecohort.fe.facet_geometry`), the joint's stiffness split equally; else one strut at the midpoint of the
  two tips along `FacetContact.normal` (the configured angles per level, the fallback).  A strut's node on the
  upper vertebra sits at the contact point, its node on the lower one `FacetContact.strut_length_mm` (20 mm)
  back along the normal; it pushes once the joint has closed by its clearance;
* optionally an **extension stop**: the same at the IAP tip, closing when the tip comes down onto the lower
  vertebra.  With `FacetContact.tip_soft_tissue_mm` set, per joint from the model's own bones
  (`spinecohort.fe.tip_gap`): along the tip's extension path, its clearance the bone gap there less the soft
  tissue; else along the lower vertebra's cranial axis with one clearance `FacetContact.tip_clearance_mm`.

Why a strut along the contact direction: a spring acts along the line between its nodes as they move, so
the contact turns with the joint and a rigid turn of the whole joint neither opens nor closes it.  The two
alternatives fail that: a gap between the two tips, 12 mm apart, closes under a rigid turn (the lumbar model
4x stiffer in extension than the same segment alone), and a GAPUNI between coincident nodes keeps its
direction fixed in space, wrong wherever the chain below has turned the joint (T11 turns 32 deg in the lumbar
model's flexion; T10-T11's extension comes out 1.90 deg there against 2.53 alone; docs/explanation/fe-model.md).
``strut_length_mm`` None writes the coincident GAPUNI.  The new nodes hang on their vertebra by the same stiff spring
truss as the arch (`spinecohort.fe.connections`).  A contact transmits force only when closed, so it never
makes a deck one body (`spinecohort.fe.connectivity`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from spinecohort.cohort.landmarks import LEVELS
from spinecohort.fe.connections import arch_owner, body_layer
from spinecohort.fe.facet_geometry import JointGeometry, joint_geometry
from spinecohort.mesh.template import HexTemplate, fit_endplate

Gap = tuple[float, tuple[float, float, float], float]  # clearance mm, unit direction, stiffness N/mm


@dataclass(frozen=True)
class FacetContact:
    """Facet-joint contact as compression-only struts or gaps (see the module docstring).

    Where the template has no articular surfaces, the joint gap acts along the outward normal of the SAP's joint
    surface, from the configured orientation of the facet plane: ``transverse_deg``, its angle to the transverse plane (White & Panjabi 1990: thoracic 60, lumbar
    90), and ``frontal_deg``, its angle to the frontal plane, positive when the SAP surface faces medially,
    negative when it faces laterally.  Normal = sin(t) (cos(f) posterior + sin(f) medial) + cos(t) cranial in
    the upper vertebra's anatomical frame.  Both angles are interpolated linearly between the anchor levels
    given (the upper vertebra of a segment).  The defaults are config/config.yaml's calibrated values (frontal
    angles inside Masharawi et al. 2004's ranges, docs/explanation/fe-model.md).  clearance_mm: the joint's initial gap;
    stiffness_n_per_mm: the closed joint; tip_clearance_mm (None = no extension stop) and
    tip_stiffness_n_per_mm: the IAP tip's gap to the lamina below and its stiffness when closed."""

    clearance_mm: float = 0.79
    stiffness_n_per_mm: float = 1670.0
    transverse_deg: tuple[tuple[str, float], ...] = (("T1", 60.0), ("T10", 60.0), ("T12", 90.0), ("L5", 90.0))
    frontal_deg: tuple[tuple[str, float], ...] = (
        ("T1", -27.5),
        ("T10", -27.5),
        ("T12", 64.0),
        ("L2", 64.0),
        ("L3", 50.0),
        ("L5", 50.0),
    )
    tip_clearance_mm: float | None = 2.0
    tip_stiffness_n_per_mm: float = 200.0
    #: None: every extension stop closes along the lower vertebra's cranial axis after ``tip_clearance_mm``; a
    #: thickness (mm): each stop acts along its IAP tip's extension path and closes after the bone gap measured
    #: there on the model's own points less this soft tissue (`spinecohort.fe.tip_gap`)
    tip_soft_tissue_mm: float | None = 1.0
    #: the contact element: a compression-only SPRINGA strut of this length (mm) along the contact direction,
    #: which turns with the joint (see `strut_table`); None = a GAPUNI between coincident nodes, whose
    #: direction stays fixed in space while the chain below turns the joint (docs/explanation/fe-model.md)
    strut_length_mm: float | None = 20.0
    #: width (mm of shortening past the clearance) over which a strut's stiffness rises from 0 to its closed
    #: value (`strut_table`'s rounded corner)
    blend_mm: float = 0.05
    #: struts per joint where the template has the joint's articular surfaces (`spinecohort.fe.facet_geometry`),
    #: spread over the part of the surfaces that face each other, the joint's stiffness split among them
    struts_per_joint: int = 4
    #: the initial gap (mm) of the lumbar joints L1-L2 ... L5-S1 where it differs from ``clearance_mm`` (None: the
    #: same): the gap of the model built on the same lumbar bones (config ``fe.facets.lumbar_clearance_mm``)
    lumbar_clearance_mm: float | None = 0.5

    def clearance_for(self, upper: str) -> float:
        """Initial gap (mm) of the joints of the segment whose upper vertebra is ``upper``."""
        if self.lumbar_clearance_mm is not None and upper.startswith("L"):
            return self.lumbar_clearance_mm
        return self.clearance_mm

    @staticmethod
    def _interp(anchors: tuple[tuple[str, float], ...], level: str) -> float:
        xs = [LEVELS.index(lv) for lv, _ in anchors]
        if xs != sorted(xs):
            raise ValueError(f"facet angle anchors must run cranial to caudal, got {anchors}")
        return float(np.interp(LEVELS.index(level), xs, [a for _, a in anchors]))

    def angles_deg(self, level: str) -> tuple[float, float]:
        """(transverse, frontal) angle (deg) of the joints of the segment whose upper vertebra is `level`."""
        return self._interp(self.transverse_deg, level), self._interp(self.frontal_deg, level)

    def normal(self, level: str, frame: np.ndarray, side: float) -> np.ndarray:
        """Unit normal (SAP -> IAP) of a joint on `side` (+1 right, -1 left) of vertebra `level`, whose frame
        has the columns lateral (right), anterior, cranial."""
        t, f = np.radians(self.angles_deg(level))
        medial = -side * frame[:, 0]
        n = np.sin(t) * (np.cos(f) * -frame[:, 1] + np.sin(f) * medial) + np.cos(t) * frame[:, 2]
        return n / np.linalg.norm(n)

    @classmethod
    def from_config(cls, cfg: dict | None) -> FacetContact | None:
        """From the config's ``fe.facets`` block (None or ``enabled: false`` -> no contact)."""
        if not cfg or not cfg.get("enabled", True):
            return None
        tip = cfg.get("tip_clearance_mm")

        def anchors(d: dict) -> tuple[tuple[str, float], ...]:
            # cranial to caudal whatever the mapping's order (a release's JSON has its keys sorted)
            return tuple(sorted(((str(k), float(v)) for k, v in d.items()), key=lambda a: LEVELS.index(a[0])))

        strut = cfg.get("strut_length_mm", None)  # absent: a release made before the struts (GAPUNI)
        soft = cfg.get("tip_soft_tissue_mm")  # absent: one clearance along the cranial axis
        return cls(
            float(cfg["clearance_mm"]),
            float(cfg["stiffness_n_per_mm"]),
            anchors(cfg["transverse_deg"]),
            anchors(cfg["frontal_deg"]),
            None if tip is None else float(tip),
            float(cfg.get("tip_stiffness_n_per_mm", 200.0)),
            None if soft is None else float(soft),
            None if strut is None else float(strut),
            float(cfg.get("blend_mm", cls.blend_mm)),
            int(cfg.get("struts_per_joint", cls.struts_per_joint)),
            None if cfg.get("lumbar_clearance_mm") is None else float(cfg["lumbar_clearance_mm"]),
        )


@dataclass
class FacetNodes:
    """The new nodes and contact elements of the facet joints of a model.

    points (M, 3) mm: the new nodes; gaps (G, 2): contact element node pairs as indices into `points` (node 1
    on the lower vertebra, node 2 on the upper); sections: (gap, element set name) per contact element; tied:
    vertebra -> indices into `points` of the new nodes that belong to it; strut_length_mm: the contact
    element (`FacetContact.strut_length_mm`: a SPRINGA strut, None = GAPUNI)."""

    points: np.ndarray
    gaps: np.ndarray
    sections: list[tuple[Gap, str]]
    tied: dict[str, np.ndarray]
    strut_length_mm: float | None = None
    blend_mm: float = 0.05

    @property
    def element_type(self) -> str:
        return "GAPUNI" if self.strut_length_mm is None else "SPRINGA"

    def section_list(self) -> list:
        """One `Section` per contact element: the GAPUNI gap, or the strut's compression-only table."""
        from spinecohort.fe.abaqus import Section

        if self.strut_length_mm is None:
            return [Section(elset=name, gap=gap) for gap, name in self.sections]
        return [
            Section(
                elset=name, spring_force_elongation=strut_table(gap[0], gap[2], self.strut_length_mm, self.blend_mm)
            )
            for gap, name in self.sections
        ]


def strut_table(
    clearance_mm: float, stiffness_n_per_mm: float, length_mm: float, blend_mm: float = 0.05, reach_mm: float = 5.0
) -> tuple[tuple[float, float], ...]:
    """(force N, elongation mm) table, ascending, of a compression-only contact strut: no force until it has
    shortened by `clearance_mm`, then `stiffness_n_per_mm` per mm of further shortening (negative force =
    compression), the corner rounded over `blend_mm` (a quadratic: continuous slope, so ccx's Newton iterations
    do not cycle between the two slopes) and the table carried `reach_mm` past contact (ccx holds the force
    beyond the ends; at most half the strut, which never inverts).  A SPRINGA acts along the line between its
    nodes as they move, so the strut turns with the joint; a GAPUNI between coincident nodes has no line and
    keeps its direction fixed in space, which is wrong wherever the chain below has turned the joint (in the
    lumbar model's flexion L5 turns 9 deg, T11 32 deg).  Sliding along the joint by s lengthens the strut
    by ~ s^2 / (2 length): 0.1 mm at s = 2 mm for a 20 mm strut."""
    if not (clearance_mm >= 0 and stiffness_n_per_mm > 0 and length_mm > 0 and blend_mm > 0):
        raise ValueError(
            f"contact strut needs clearance >= 0, stiffness > 0, length > 0 and blend > 0, got "
            f"{clearance_mm}, {stiffness_n_per_mm}, {length_mm}, {blend_mm}"
        )
    reach = min(reach_mm, 0.5 * length_mm - clearance_mm)
    if reach <= blend_mm:
        raise ValueError(f"contact strut of {length_mm} mm is too short for a clearance of {clearance_mm} mm")
    k, w = stiffness_n_per_mm, blend_mm
    depth = np.array([reach, w, 0.75 * w, 0.5 * w, 0.25 * w, 0.0])  # penetration past contact, mm
    force = np.where(depth <= w, -k * depth**2 / (2 * w), -k * (depth - 0.5 * w)) + 0.0  # no -0.0 in decks
    rows = [(float(f), float(-clearance_mm - d)) for f, d in zip(force, depth)]
    return tuple(rows + [(0.0, float(length_mm))])


def facet_pairs(template: HexTemplate, allowed: np.ndarray | None = None) -> np.ndarray:
    """(J, 2) template node ids (IAP tip of the upper vertebra, SAP tip of the lower) of every facet joint: the
    template's ``facet_joints`` (a template with articular surfaces, whose capsules are fibre bundles), else the
    capsular-ligament anchors; allowed: a node mask both ends must be in (a sub-model's nodes)."""
    cl = (
        template.sites["facet_joints"]
        if "facet_joints" in template.sites
        else template.ligaments[template.elsets["LIG_CL"]]
    )
    return cl if allowed is None else cl[allowed[cl].all(axis=1)]


def vertebra_frame(template: HexTemplate, points: np.ndarray, level: str) -> tuple[np.ndarray, np.ndarray]:
    """Anatomical frame (3, 3: columns lateral, anterior, cranial) of a vertebra, between its two endplate
    frames, and the centre (mm) of its endplate nodes."""
    n2 = len(template.grid.nodes)
    inf, sup = (body_layer(template, level, t) * n2 + np.arange(n2) for t in (0.0, 1.0))
    frame = mean_frame(fit_endplate(points[sup]).frame, fit_endplate(points[inf]).frame)
    return frame, points[np.concatenate([inf, sup])].mean(0)


def mean_frame(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Orthonormal frame (columns lateral, anterior, cranial) between two endplate frames."""
    n = a[:, 2] + b[:, 2]
    n /= np.linalg.norm(n)
    x = a[:, 0] + b[:, 0]
    x -= np.dot(x, n) * n
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(n, x), n], 1)


def _joints(
    template: HexTemplate, points: np.ndarray, pairs: np.ndarray
) -> tuple[dict[str, tuple[np.ndarray, np.ndarray]], list[tuple[str, str, float]]]:
    """The frames (`vertebra_frame`) of the vertebrae of `pairs` and, per joint, (upper vertebra, lower
    vertebra, side: +1 right / -1 left of the upper vertebra's frame)."""
    owner = arch_owner(template)
    frames = {v: vertebra_frame(template, points, v) for v in {owner[int(i)] for i in pairs.ravel()}}
    joints = []
    for iap, sap in pairs:
        up, lo = owner[int(iap)], owner[int(sap)]
        frame, centre = frames[up]
        joints.append((up, lo, 1.0 if (points[iap] - centre) @ frame[:, 0] > 0 else -1.0))
    return frames, joints


def joint_surfaces(template: HexTemplate, up: str, lo: str, side: float) -> tuple[np.ndarray, np.ndarray] | None:
    """Template node ids of a joint's articular surfaces (SAP of the lower vertebra `lo`, IAP of the upper `up`;
    side +1 right, -1 left), None when the template has none (a cohort without insertion sites)."""
    name = "right" if side > 0 else "left"
    sap, iap = f"facet_surface_sup_{name}/{lo}", f"facet_surface_inf_{name}/{up}"
    if sap not in template.sites or iap not in template.sites:
        return None
    return template.sites[sap], template.sites[iap]


def surface_normal(template: HexTemplate, points: np.ndarray, nodes: np.ndarray) -> np.ndarray:
    """Area-weighted normal (3,) of the skin triangles with all three nodes in `nodes` (the skin's outward side)."""
    tri = template.tris[np.isin(template.tris, nodes).all(1)]
    p = points[tri]
    return np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]).sum(0)


def joint_geometries(
    template: HexTemplate, points: np.ndarray, pairs: np.ndarray, n_points: int
) -> list[JointGeometry | None]:
    """Per joint of `pairs` its `JointGeometry` on the model's `points` (`spinecohort.fe.facet_geometry`), None
    where the template has no articular surfaces."""
    _, joints = _joints(template, points, pairs)
    out = []
    for up, lo, side in joints:
        surf = joint_surfaces(template, up, lo, side)
        if surf is None:
            out.append(None)
            continue
        sap, iap = surf
        out.append(
            joint_geometry(
                points[sap], points[iap], n_points, *(surface_normal(template, points, s) for s in (sap, iap))
            )
        )
    return out


@dataclass(frozen=True)
class Struts:
    """Contact struts: (S, 3) mm position of the node on the upper vertebra, (S, 3) unit direction (from the
    lower node to the upper), and per strut its clearance (mm), stiffness (N/mm), upper and lower vertebra and
    element set name."""

    at: np.ndarray
    direction: np.ndarray
    clearance_mm: np.ndarray
    stiffness_n_per_mm: np.ndarray
    upper: list[str]
    lower: list[str]
    names: list[str]


def joint_struts(template: HexTemplate, points: np.ndarray, pairs: np.ndarray, facets: FacetContact) -> Struts:
    """The joints' contact struts.  Where the template has the joint's articular surfaces: ``struts_per_joint``
    struts at the contact points of its `JointGeometry`, along the normal of the surfaces' own plane, the joint's
    stiffness split equally; else one strut at the midpoint of the two tips along `FacetContact.normal` (the
    configured angles)."""
    frames, joints = _joints(template, points, pairs)
    geos = joint_geometries(template, points, pairs, facets.struts_per_joint)
    at, direction, names, upper, lower, stiff = [], [], [], [], [], []
    for (iap, sap), (up, lo, side), geo in zip(pairs, joints, geos):
        tag = f"FACET_{up}{lo}_{'R' if side > 0 else 'L'}"
        if geo is None:
            pos, dirs = 0.5 * (points[iap] + points[sap])[None], facets.normal(up, frames[up][0], side)[None]
        else:
            pos, dirs = geo.points, np.broadcast_to(geo.normal, geo.points.shape)
        m = len(pos)
        at.append(pos)
        direction.append(dirs)
        names += [tag] if m == 1 else [f"{tag}{k + 1}" for k in range(m)]
        upper += [up] * m
        lower += [lo] * m
        stiff += [facets.stiffness_n_per_mm / m] * m
    s = len(names)
    return Struts(
        np.concatenate(at) if s else np.zeros((0, 3)),
        np.concatenate(direction) if s else np.zeros((0, 3)),
        np.array([facets.clearance_for(up) for up in upper], dtype=np.float64),
        np.asarray(stiff, dtype=np.float64),
        upper,
        lower,
        names,
    )


def tip_struts(template: HexTemplate, points: np.ndarray, pairs: np.ndarray, facets: FacetContact) -> Struts:
    """Each joint's extension stop: the IAP tip of the upper vertebra coming down onto the lower one.  With
    ``tip_soft_tissue_mm`` None along the lower vertebra's cranial axis (so the stop closes when the tip moves
    caudally) after ``tip_clearance_mm``; else along the tip's extension path, after the bone gap there less the
    soft tissue (`spinecohort.fe.tip_gap.tip_stops`)."""
    frames, joints = _joints(template, points, pairs)
    j = len(joints)
    if facets.tip_soft_tissue_mm is None:
        direction = np.array([frames[lo][0][:, 2] for _, lo, _ in joints]).reshape(-1, 3)
        clearance = np.full(j, float(facets.tip_clearance_mm or 0.0))
    else:
        from spinecohort.fe.tip_gap import tip_stops

        direction, clearance = tip_stops(template, points, pairs, joints, frames, facets.tip_soft_tissue_mm)
    return Struts(
        points[pairs[:, 0]] if j else np.zeros((0, 3)),
        direction,
        clearance,
        np.full(j, facets.tip_stiffness_n_per_mm),
        [up for up, _, _ in joints],
        [lo for _, lo, _ in joints],
        [f"FACET_TIP_{up}{lo}_{'R' if side > 0 else 'L'}" for up, lo, side in joints],
    )


def facet_nodes(template: HexTemplate, points: np.ndarray, pairs: np.ndarray, facets: FacetContact) -> FacetNodes:
    """The new nodes, contact elements and ties of the joints `pairs` (`facet_pairs`) of a model with coordinates
    `points` (template node order, mm): the joint struts (`joint_struts`), then the extension stops."""
    kinds = [joint_struts(template, points, pairs, facets)]
    if facets.tip_clearance_mm is not None:
        kinds.append(tip_struts(template, points, pairs, facets))
    h = facets.strut_length_mm or 0.0  # a strut's lower node lies `h` back along the contact direction
    blocks, gaps, sections = [], [], []
    tied: dict[str, list[int]] = {}
    first = 0
    for st in kinds:
        s = len(st.names)
        blocks += [st.at, st.at - h * st.direction]  # upper side, lower side
        gaps.append(np.stack([first + s + np.arange(s), first + np.arange(s)], 1))  # node 1 lower, node 2 upper
        sections += [
            ((float(c), tuple(map(float, d)), float(k)), name)
            for c, d, k, name in zip(st.clearance_mm, st.direction, st.stiffness_n_per_mm, st.names)
        ]
        for i in range(s):
            tied.setdefault(st.upper[i], []).append(first + i)
            tied.setdefault(st.lower[i], []).append(first + s + i)
        first += 2 * s
    return FacetNodes(
        np.concatenate(blocks) if first else np.zeros((0, 3)),
        np.concatenate(gaps).astype(np.int64) if first else np.zeros((0, 2), dtype=np.int64),
        sections,
        {v: np.asarray(ix, dtype=np.int64) for v, ix in tied.items()},
        facets.strut_length_mm,
        facets.blend_mm,
    )
