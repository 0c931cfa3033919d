"""Assemble the labeled reference from its remeshed parts: labels, landmarks, ligament sites, facet surfaces.

Order of the parts in the single surface: T1..T12, L1..L5, sacrum (``S1``), hip bones (``pelvis``), left and
right proximal femurs.  L1-L5 are labeled by :mod:`spinecohort.anatomy.labeling` in their own body frame;
T1-T12 are the vertex set of one thoracic template (the Remus L1 remeshed coarser, labeled by the same rules
as L1) moved by :func:`spinecohort.anatomy.level_map.map_vertebra`, so the template's region labels, endplate
patches and rims, anchors and ligament sites hold on every thoracic level by index
(:func:`carried_from_template`).
"""

from __future__ import annotations

import numpy as np
import pyvista as pv
from scipy.spatial import cKDTree

from spinecohort.anatomy import labeling
from spinecohort.anatomy.labels import cohort_part, cohort_part_names, region_id
from spinecohort.anatomy.landmark_rules import vertebra_landmarks
from spinecohort.anatomy.reference import Reference
from spinecohort.anatomy.sacrum import sacral_labels
from spinecohort.anatomy.surface import to_polydata
from spinecohort.cohort.landmarks import LEVELS, Landmarks

#: a vertex of a Remus vertebra is body when inside its ``*_body`` surface or within this distance of it (the
#: whole-vertebra surface lies up to ~2 mm outside the body-only one on the endplates)
BODY_TOLERANCE_MM = 2.5

THORACIC = LEVELS[:12]
LUMBAR = LEVELS[12:]


def body_frame(points: np.ndarray, normals: np.ndarray, is_body: np.ndarray) -> np.ndarray:
    """(3, 3) rows x (right), y (anterior), z (body axis, cranial) of a vertebra: z from the mean normals of
    the two endplates (the cranially and caudally facing body vertices), x the world x made orthogonal."""
    b = np.flatnonzero(is_body)
    up = normals[b][normals[b, 2] > 0.6].mean(0)
    down = normals[b][normals[b, 2] < -0.6].mean(0)
    z = up - down
    z /= np.linalg.norm(z)
    x = np.array([1.0, 0.0, 0.0]) - z[0] * z
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(z, x), z])


def inside_or_near(points: np.ndarray, v: np.ndarray, f: np.ndarray, tol_mm: float) -> np.ndarray:
    """Mask of ``points`` inside the closed surface (v, f) or within ``tol_mm`` of it."""
    d = pv.PolyData(points).compute_implicit_distance(to_polydata(v, f))["implicit_distance"]
    return np.asarray(d) < tol_mm


def _nearest(points: np.ndarray, idx: np.ndarray, target: np.ndarray) -> int:
    return int(idx[np.argmin(np.linalg.norm(points[idx] - target, axis=1))])


def label_vertebra(points, faces, is_body) -> dict:
    """Regions, endplates, anchors and ligament sites of one vertebra (indices local to it): the posterior
    regions follow from the landmark rules in the body frame."""
    normals = labeling.vertex_normals(points, faces)
    frame = body_frame(points, normals, is_body)
    centre = points[is_body].mean(0)
    loc = (points - centre) @ frame.T
    nloc = normals @ frame.T
    lmk = vertebra_landmarks(loc)
    region = labeling.posterior_regions(loc, is_body, lmk)
    out = {"region": region, "frame": frame, "centre": centre, "landmarks": lmk @ frame + centre}
    out.update(labeling.endplates(loc, nloc, faces, is_body))
    out.update(_sites(loc, nloc, region, lmk, out))
    return out


def _sites(loc, nloc, region, lmk, ep) -> dict:
    """Anchors (one vertex each) and ligament insertion sites (vertex sets) in the vertebra's local frame."""
    r = {name: np.flatnonzero(region == region_id(name)) for name in ("body", "spinous", "lamina")}
    for s in ("left", "right"):
        for name in (f"transverse_{s}", f"facet_sup_{s}", f"facet_inf_{s}", f"pedicle_{s}"):
            r[name] = np.flatnonzero(region == region_id(name))
    tips = dict(zip(("spinous", "tp_L", "tp_R", "sap_L", "sap_R", "iap_L", "iap_R"), lmk[8:]))
    a = {
        "spinous_tip": _nearest(loc, r["spinous"], tips["spinous"]),
        "tp_tip_L": _nearest(loc, r["transverse_left"], tips["tp_L"]),
        "tp_tip_R": _nearest(loc, r["transverse_right"], tips["tp_R"]),
        "sap_tip_L": _nearest(loc, r["facet_sup_left"], tips["sap_L"]),
        "sap_tip_R": _nearest(loc, r["facet_sup_right"], tips["sap_R"]),
        "iap_tip_L": _nearest(loc, r["facet_inf_left"], tips["iap_L"]),
        "iap_tip_R": _nearest(loc, r["facet_inf_right"], tips["iap_R"]),
    }
    sp = r["spinous"]
    a["spinous_upper"] = int(sp[np.argmax(loc[sp, 2])])
    a["spinous_lower"] = int(sp[np.argmin(loc[sp, 2])])
    lam = r["lamina"]
    for s, sgn in (("L", -1.0), ("R", 1.0)):
        side = lam[sgn * loc[lam, 0] > 2.0]
        a[f"lamina_upper_{s}"] = int(side[np.argmax(loc[side, 2])])
        a[f"lamina_lower_{s}"] = int(side[np.argmin(loc[side, 2])])
    body = r["body"]
    y_ant, y_post = loc[body, 1].max(), loc[body, 1].min()
    z_sup, z_inf = loc[ep["rim_sup"], 2].min(), loc[ep["rim_inf"], 2].max()
    midline = np.abs(loc[body, 0]) < 6.0
    sites = {
        "ALL_sup": body[midline & (loc[body, 1] > y_ant - 4.0) & (loc[body, 2] > z_sup - 6.0)],
        "ALL_inf": body[midline & (loc[body, 1] > y_ant - 4.0) & (loc[body, 2] < z_inf + 6.0)],
        "PLL_sup": body[midline & (loc[body, 1] < y_post + 4.0) & (loc[body, 2] > z_sup - 6.0)],
        "PLL_inf": body[midline & (loc[body, 1] < y_post + 4.0) & (loc[body, 2] < z_inf + 6.0)],
        "SSL": sp[np.linalg.norm(loc[sp] - loc[a["spinous_tip"]], axis=1) < 5.0],
        "ISL_sup": sp[loc[sp, 2] > np.quantile(loc[sp, 2], 0.8)],
        "ISL_inf": sp[loc[sp, 2] < np.quantile(loc[sp, 2], 0.2)],
    }
    inner = lam[nloc[lam, 1] > 0.3]  # the canal side of the laminae
    for s, sgn in (("left", -1.0), ("right", 1.0)):
        side = inner[sgn * loc[inner, 0] > 2.0]
        sites[f"LF_sup_{s}"] = side[loc[side, 2] > np.quantile(loc[side, 2], 0.7)]
        sites[f"LF_inf_{s}"] = side[loc[side, 2] < np.quantile(loc[side, 2], 0.3)]
        tp = r[f"transverse_{s}"]
        tip = a[f"tp_tip_{'L' if s == 'left' else 'R'}"]
        sites[f"ITL_{s}"] = tp[np.linalg.norm(loc[tp] - loc[tip], axis=1) < 5.0]
    return {"anchors": a, "sites": sites}


def facet_surfaces(vertebrae: dict, facets: dict, offsets: dict, points: np.ndarray) -> dict:
    """Articular surfaces: the superior ones of L2-L5 and S1 are the Remus facet patches (vertices within
    1.5 mm of them); the rest are the articular-process vertices within 4 mm of the partner process of the
    adjacent level (falling back to the closest 30 % of the process when none is that close)."""
    out: dict[str, dict[str, np.ndarray]] = {k: {} for k in ("sup_left", "sup_right", "inf_left", "inf_right")}
    levels = list(LEVELS) + ["S1"]
    for i, lv in enumerate(LEVELS):
        g = offsets[lv] + np.arange(len(vertebrae[lv]["region"]))
        reg = vertebrae[lv]["region"]
        for s in ("left", "right"):
            sup = g[reg == region_id(f"facet_sup_{s}")]
            inf = g[reg == region_id(f"facet_inf_{s}")]
            if f"{lv}_{s}" in facets:
                near = inside_or_near(points[sup], *facets[f"{lv}_{s}"], 1.5)
                out[f"sup_{s}"][lv] = sup[near]
            elif i > 0:
                above = LEVELS[i - 1]
                partner = offsets[above] + np.flatnonzero(vertebrae[above]["region"] == region_id(f"facet_inf_{s}"))
                out[f"sup_{s}"][lv] = _close_to(points, sup, partner)
            below = levels[i + 1]
            if f"{below}_{s}" in facets:
                near = inside_or_near(points[inf], *facets[f"{below}_{s}"], 4.0)
                out[f"inf_{s}"][lv] = (
                    inf[near] if near.any() else _close_to(points, inf, None, facets[f"{below}_{s}"][0])
                )
            elif below in vertebrae:
                partner = offsets[below] + np.flatnonzero(vertebrae[below]["region"] == region_id(f"facet_sup_{s}"))
                out[f"inf_{s}"][lv] = _close_to(points, inf, partner)
    for s in ("left", "right"):  # T1's superior facets have no partner in the model: the rule's tip cap
        t1 = offsets["T1"] + np.flatnonzero(vertebrae["T1"]["region"] == region_id(f"facet_sup_{s}"))
        out[f"sup_{s}"]["T1"] = t1[points[t1, 2] > np.quantile(points[t1, 2], 0.7)]
    return out


def _close_to(points, idx, partner, partner_points=None, within_mm: float = 4.0) -> np.ndarray:
    pp = points[partner] if partner is not None else partner_points
    d = cKDTree(pp).query(points[idx])[0]
    near = idx[d < within_mm]
    return near if len(near) >= 5 else idx[d <= np.quantile(d, 0.3)]


def carried_from_template(tpl: dict, tpl_part: tuple, part: tuple, name: str) -> dict:
    """The labels of a thoracic level that is the template's vertex set moved (same count and order, same
    triangles): the template's regions, endplate sets, anchors and sites by index; its frame and centre from
    its own body vertices, its landmarks at the moved positions of the vertices nearest the template's."""
    points, faces = part
    if len(points) != len(tpl_part[0]) or not np.array_equal(faces, tpl_part[1]):
        raise ValueError(
            f"{name}: not the thoracic template's vertex set and triangles ({len(points)} vs {len(tpl_part[0])})"
        )
    is_body = tpl["region"] == region_id("body")
    frame = body_frame(points, labeling.vertex_normals(points, faces), is_body)
    lmk_vertices = cKDTree(tpl_part[0]).query(tpl["landmarks"])[1]
    out = dict(tpl)
    out.update({"frame": frame, "centre": points[is_body].mean(0), "landmarks": points[lmk_vertices]})
    return out


def assemble(parts: dict, template: tuple, bodies: dict, facets: dict, heads: dict, log: dict) -> Reference:
    """The Reference of the parts (see the module docstring for the order); every thoracic part is the
    vertex set and triangles of ``template`` (points, faces, body mask: the thoracic template the levels were
    mapped from, labeled here by the lumbar rules), moved."""
    order = list(LEVELS) + ["S1", "pelvis", "femur_L", "femur_R"]
    offsets, start = {}, 0
    for k in order:
        offsets[k] = start
        start += len(parts[k][0])
    points = np.concatenate([parts[k][0] for k in order])
    faces = np.concatenate([parts[k][1] + offsets[k] for k in order])
    n = len(points)
    region = np.full(n, -1, np.int16)
    level = np.full(n, -1, np.int8)
    side = np.zeros(n, np.int8)

    vert = {
        lv: label_vertebra(*parts[lv], inside_or_near(parts[lv][0], *bodies[lv], BODY_TOLERANCE_MM)) for lv in LUMBAR
    }
    tpl = label_vertebra(*template)
    for lv in THORACIC:
        vert[lv] = carried_from_template(tpl, template[:2], parts[lv], lv)
    lm_sets: dict[str, dict] = {k: {} for k in ("endplate_sup", "endplate_inf", "rim_sup", "rim_inf", "body")}
    anchors: dict[str, list] = {}
    sites: dict[str, dict] = {}
    full_endplates: dict[str, dict] = {"sup": {}, "inf": {}}
    for i, lv in enumerate(LEVELS):
        o, v = offsets[lv], vert[lv]
        g = o + np.arange(len(v["region"]))
        region[g] = v["region"]
        level[g] = i
        for key in ("sup", "inf"):
            lm_sets[f"endplate_{key}"][lv] = o + v[f"rim_band_{key}"]
            lm_sets[f"rim_{key}"][lv] = o + v[f"rim_{key}"]
            full_endplates[key][lv] = o + v[f"endplate_{key}"]
        lm_sets["body"][lv] = g[v["region"] == region_id("body")]
        for name, idx in v["anchors"].items():
            anchors.setdefault(name, []).append(o + idx)
        for name, idx in v["sites"].items():
            sites.setdefault(f"site_{name}", {})[lv] = o + idx
    for r in ("pedicle_left", "transverse_left", "facet_sup_left", "facet_inf_left"):
        side[np.isin(region, [region_id(r)])] = -1
        side[np.isin(region, [region_id(r.replace("left", "right"))])] = 1

    # sacrum: the S1 plate is the part of the S1 body that faces L5's inferior endplate across the disc
    so = offsets["S1"]
    sp_, sf_ = parts["S1"]
    sn = labeling.vertex_normals(sp_, sf_)
    s_body = inside_or_near(sp_, *bodies["S1"], BODY_TOLERANCE_MM)
    l5_inf = parts["L5"][0][vert["L5"]["endplate_inf"]]
    u = np.linalg.svd(l5_inf - l5_inf.mean(0))[2][-1]
    u *= np.sign(u[2])
    near_l5 = cKDTree(l5_inf).query(sp_)[0] < 20.0
    plate = np.flatnonzero(s_body & (sn @ u > 0.6) & near_l5)
    plate = labeling._largest_component(plate, sf_)
    band, edge = labeling.boundary_band(plate, sf_, sp_, 3.0)
    g = so + np.arange(len(sp_))
    region[g] = region_id("sacrum")
    region[so + plate] = region_id("s1_plate")
    lm_sets["endplate_sup"]["S1"] = so + band
    lm_sets["rim_sup"]["S1"] = so + edge
    full_endplates["sup"]["S1"] = so + plate
    # the lumbosacral joint's posterior elements: S1's articular surfaces, lamina edges, median crest, anchors
    sacral = sacral_labels(sp_, sf_, plate, {s: facets[f"S1_{s}"][0] for s in ("left", "right")})
    for name, idx in sacral["sites"].items():
        sites.setdefault(f"site_{name}", {})["S1"] = so + idx

    # hip bones: pubis = anterior and caudal of the acetabular centres, the rest ilium (with ischium)
    po = offsets["pelvis"]
    pp_ = parts["pelvis"][0]
    g = po + np.arange(len(pp_))
    ac = np.array([log["acetabulum_L"]["centre_mm"], log["acetabulum_R"]["centre_mm"]])
    pubis = (pp_[:, 1] > ac[:, 1].mean() + 15.0) & (pp_[:, 2] < ac[:, 2].mean() + 5.0)
    region[g] = np.where(pubis, region_id("pubis"), region_id("ilium"))
    side[g] = np.where(pp_[:, 0] < 0, -1, 1)
    front = pp_[:, 1] > pp_[:, 1].max() - 12.0
    symphysis = g[front & (np.abs(pp_[:, 0]) < 10.0)]

    fh = {}
    for s, sgn in (("L", -1), ("R", 1)):
        o = offsets[f"femur_{s}"]
        g = o + np.arange(len(parts[f"femur_{s}"][0]))
        region[g] = region_id("femoral_head")
        side[g] = sgn
        fh[s] = o + heads[s]
    sets = {"endplate_full_sup": full_endplates["sup"], "endplate_full_inf": full_endplates["inf"]}
    sets.update(sites)
    surf = facet_surfaces(vert, facets, offsets, points)
    for key, idx in sacral["surfaces"].items():
        surf[key]["S1"] = so + idx
    for key, per_level in surf.items():
        sets[f"facet_surface_{key}"] = per_level
        sets[f"site_CL_{key}"] = {
            lv: labeling.boundary_band(idx, faces, points, 1.5)[0] for lv, idx in per_level.items() if len(idx)
        }
    # the sacrum's anchors, one vertex each: sets ``anchor_<name>`` -> {"S1": [vertex]} (``Landmarks.anchors``
    # hold one vertex per level T1..L5)
    sets.update({f"anchor_{name}": {"S1": np.array([so + v])} for name, v in sacral["anchors"].items()})
    part = cohort_part(region, level, side)
    lm = Landmarks(
        part=part,
        part_names=cohort_part_names(),
        endplate_sup=lm_sets["endplate_sup"],
        endplate_inf=lm_sets["endplate_inf"],
        rim_sup=lm_sets["rim_sup"],
        rim_inf=lm_sets["rim_inf"],
        femoral_head=fh,
        body=lm_sets["body"],
        pubic_symphysis=symphysis,
        meta={"generator": "spinecohort.anatomy reference", "endplate_plane": "least-squares plane of the rim band"},
        anchors={k: np.array(v) for k, v in anchors.items()},
    )
    lm.validate(n, "reference")
    log["vertex_counts"] = {k: int(len(parts[k][0])) for k in order}
    log["total_vertices"] = int(n)
    return Reference(points, faces, region.astype(np.int8), level, side, lm, sets, log)
