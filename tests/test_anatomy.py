"""The labeled reference spine (vendored) and the geometry behind its build."""

from __future__ import annotations

import numpy as np
import pytest

from spinecohort.anatomy import contacts, labels
from spinecohort.anatomy.landmark_rules import similarity_from_points
from spinecohort.anatomy.reference import load_reference
from spinecohort.anatomy.surface import (
    check_surface,
    from_polydata,
    intersections_between,
    remesh_isotropic,
    self_intersections,
    sphere_fit,
)
from spinecohort.cohort.landmarks import LEVELS


@pytest.fixture(scope="module")
def ref():
    return load_reference()


def _sphere(radius=10.0, centre=(0.0, 0.0, 0.0), res=40):
    import pyvista as pv

    return from_polydata(pv.Sphere(radius=radius, center=centre, theta_resolution=res, phi_resolution=res).clean())


# --- geometry used by the build -------------------------------------------------------------------------


def test_remesh_gives_the_requested_edge_length_on_a_closed_surface():
    v, f = remesh_isotropic(*_sphere(20.0), edge_mm=2.0)
    c = check_surface(v, f)
    assert c["open_edges"] == 0 and c["manifold"] and c["self_intersections"] == 0
    # ACVD's clusters are area-equal, so edges average near the target (within 10 %) with a narrow spread
    assert c["edge_mean_mm"] == pytest.approx(2.0, rel=0.10)
    assert c["edge_sd_mm"] < 0.25 * c["edge_mean_mm"]


def test_self_intersections_count_crossing_triangles_only():
    v, f = _sphere()
    assert self_intersections(v, f) == 0  # neighbours share vertices: not counted
    v2, f2 = _sphere(centre=(5.0, 0.0, 0.0))
    both_v, both_f = np.vstack([v, v2]), np.vstack([f, f2 + len(v)])
    assert self_intersections(both_v, both_f) > 0
    assert intersections_between(v, f, v2, f2) > 0
    v3, f3 = _sphere(centre=(25.0, 0.0, 0.0))
    assert intersections_between(v, f, v3, f3) == 0  # 5 mm apart


def test_sphere_fit_and_similarity_recover_known_values():
    rng = np.random.default_rng(0)
    d = rng.normal(size=(200, 3))
    pts = np.array([1.0, -2.0, 3.0]) + 24.0 * d / np.linalg.norm(d, axis=1, keepdims=True)
    c, r = sphere_fit(pts)
    assert np.allclose(c, [1.0, -2.0, 3.0], atol=1e-9) and r == pytest.approx(24.0, abs=1e-9)
    q = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    q *= np.sign(np.linalg.det(q))
    src = rng.normal(size=(15, 3)) * 20
    rot, s, t = similarity_from_points(src, 1.3 * src @ q.T + [5.0, 6.0, 7.0])
    assert np.allclose(rot, q, atol=1e-9) and s == pytest.approx(1.3) and np.allclose(t, [5, 6, 7])


def test_push_out_separates_overlapping_bones_to_the_clearance():
    a, b = _sphere(10.0), _sphere(10.0, centre=(17.0, 0.0, 0.0))  # 3 mm overlap
    assert intersections_between(*a, *b) > 0
    va, left = contacts.push_out(a, b, gap_mm=0.5)
    assert left == 0
    gap = np.linalg.norm(va - [17.0, 0.0, 0.0], axis=1).min() - 10.0
    assert gap > 0.3  # the moved vertices sit 0.5 mm outside b's polygonal surface (inscribed in r = 10)


def test_open_disc_spaces_reaches_the_minimum_gap():
    a = _sphere(10.0, centre=(0.0, 0.0, 18.0))[0]
    b = _sphere(10.0)[0]
    pts = [a.copy(), b.copy()]
    gaps = contacts.open_disc_spaces(pts, [np.ones(len(a), bool), np.ones(len(b), bool)], min_disc_mm=3.0)
    assert gaps[0] >= 3.0 - 1e-9
    assert np.allclose(pts[1], b)  # the caudal level stays


# --- the vendored reference ------------------------------------------------------------------------------


def test_reference_is_one_closed_labelled_surface(ref):
    n = len(ref.vertices)
    assert 40_000 < n < 70_000  # the node budget of the cohort (README: command 1 within 5 min)
    assert set(np.unique(ref.region)) == set(range(len(labels.REGIONS)))
    assert set(np.unique(ref.level[ref.level >= 0])) == set(range(len(LEVELS)))
    ref.landmarks.validate(n, "reference")
    edges = np.sort(np.concatenate([ref.faces[:, [0, 1]], ref.faces[:, [1, 2]], ref.faces[:, [2, 0]]]), axis=1)
    _, count = np.unique(edges, axis=0, return_counts=True)
    assert np.all(count == 2)  # closed and edge-manifold: every edge between exactly two triangles
    assert ref.build["checks"]["L3"]["self_intersections"] == 0


def test_every_vertebra_has_every_region_and_sides_follow_ras(ref):
    for i, lv in enumerate(LEVELS):
        idx = ref.vertebra(i)
        present = set(ref.region[idx].tolist())
        assert present == set(range(len(labels.VERTEBRA_REGIONS))), lv
        body_x = ref.vertices[idx][ref.region[idx] == 0, 0].mean()
        for name, sign in (("pedicle_left", -1), ("transverse_right", 1), ("facet_inf_left", -1)):
            sel = idx[ref.region[idx] == labels.region_id(name)]
            assert sign * (ref.vertices[sel, 0].mean() - body_x) > 5.0, (lv, name)  # x is the patient's right


def test_cohort_parts_match_the_regions(ref):
    lm = ref.landmarks
    names = np.array(lm.part_names)[lm.part]
    assert np.all((names == "body_L3") == ((ref.level == 16 - 2) & (ref.region == 0)))
    assert np.all(np.char.startswith(names[ref.region == labels.region_id("femoral_head")], "femoral_head_"))
    with pytest.raises(ValueError, match="unknown anatomical region"):
        labels.region_id("rib")


def test_femoral_heads_are_exact_spheres_at_the_acetabula(ref):
    for side in ("L", "R"):
        c, r = sphere_fit(ref.vertices[ref.landmarks.femoral_head[side]])
        res = np.abs(np.linalg.norm(ref.vertices[ref.landmarks.femoral_head[side]] - c, axis=1) - r)
        assert res.max() < 1e-3  # projected onto the sphere (float32 storage)
        acetab = ref.build[f"acetabulum_{side}"]
        assert np.allclose(c, acetab["centre_mm"], atol=0.01)
        assert r == pytest.approx(acetab["radius_mm"] - ref.build["args"]["joint_space_mm"], abs=1e-3)
        assert 21.0 < r < 28.0  # adult femoral-head radius


def test_reference_measures_as_an_upright_adult_spine(ref):
    from spinecohort.measure.spinopelvic import measure

    t = measure(ref.vertices[None], ref.landmarks).iloc[0]
    assert t["PI_identity_err"] < 1e-6
    # Visible Human Male lumbosacral pose: sacral slope and lordosis in the asymptomatic ranges (SS 30-50 deg,
    # L1-S1 lordosis 40-70 deg), pelvic tilt small, hip-centre distance 160 +/- 8 mm (x2 SD)
    assert 25.0 < t["SS"] < 50.0 and 35.0 < t["LL"] < 70.0 and -5.0 < t["PT"] < 20.0
    assert 144.0 < t["HA_width"] < 176.0
    assert t["endplate_rms_max"] < 3.0  # rim bands are near planar
    for disc in ("L4-L5", "L5-S1"):
        assert 6.0 < t[f"DH_{disc}"] < 15.0  # lumbar central disc heights (Zhang 2018: 7-15 mm)


def test_reference_bones_do_not_cross(ref):
    c = contacts.adjacent_contacts(ref.vertices, ref.faces, ref.level, ref.region)
    # the build separated every joint (push-out to a 0.5 mm clearance, rigid opening where the push-out could
    # not): no neighbouring pair crosses; the closest vertex gap is 0.37 mm (T2-T3, not crossing, left as built)
    for pair, val in c.items():
        assert val["crossings"] == 0, pair
        assert val["min_gap_mm"] > 0.3, (pair, val)
    # nor does any triangle of the whole reference cross another (each bone closed and unfolded, no overlap)
    assert self_intersections(ref.vertices, ref.faces) == 0
    assert all(ch["self_intersections"] == 0 for ch in ref.build["checks"].values())


def test_the_sacrum_carries_the_lumbosacral_joint_labels(ref):
    """S1's superior articular surfaces, capsule rims, lamina edges, median crest and anchors
    (`spinecohort.anatomy.sacrum`): on the sacrum, of sane size, on the right side, and facing the way the
    published lumbosacral facets face.  Expected orientation: the superior facets of L5-S1 stand 49.1 +- 12.4 deg
    to the mid-sagittal plane (599 Hamann-Todd spines, Spine 2016;41(19):E1138), more coronal than L4-L5's;
    the reference's S1 articular surfaces (the Remus ``S1_PD*_a`` patches) face 52.5 deg (left) and 41.1 deg
    (right), inside that range, and L5's superior ones (the L4-L5 joint) 33.5 and 29.5 deg."""
    from spinecohort.anatomy.sacrum import s1_frame

    sacrum = np.isin(ref.region, [labels.region_id("sacrum"), labels.region_id("s1_plate")])
    plate = ref.sets["endplate_full_sup"]["S1"]
    centre, rows = s1_frame(ref.vertices, plate)
    loc = (ref.vertices - centre) @ rows.T  # x right, y anterior, z the plate's normal
    sizes = {}
    for name in (
        "facet_surface_sup_left",
        "facet_surface_sup_right",
        "site_CL_sup_left",
        "site_CL_sup_right",
        "site_LF_sup_left",
        "site_LF_sup_right",
        "site_ISL_sup",
        "site_SSL",
    ):
        idx = ref.sets[name]["S1"]
        assert sacrum[idx].all(), name
        sizes[name] = len(idx)
    # the 3.5 mm sacrum remesh: an articular surface of ~150 mm2 holds 40-60 vertices, its rim band ~25
    assert all(30 <= sizes[f"facet_surface_sup_{s}"] <= 80 for s in ("left", "right")), sizes
    assert all(10 <= sizes[f"site_CL_sup_{s}"] <= sizes[f"facet_surface_sup_{s}"] for s in ("left", "right"))
    assert all(4 <= sizes[k] <= 30 for k in ("site_LF_sup_left", "site_LF_sup_right", "site_ISL_sup", "site_SSL"))
    # sides, and everything behind the plate's posterior edge (the posterior elements)
    y_post = loc[plate, 1].min()
    for s, sgn in (("left", -1.0), ("right", 1.0)):
        for name in (f"facet_surface_sup_{s}", f"site_LF_sup_{s}"):
            assert np.all(sgn * loc[ref.sets[name]["S1"], 0] > 0) and np.all(loc[ref.sets[name]["S1"], 1] < y_post)
    anchors = {k[len("anchor_") :]: v["S1"] for k, v in ref.sets.items() if k.startswith("anchor_")}
    assert set(anchors) == {
        "sap_tip_L",
        "sap_tip_R",
        "lamina_upper_L",
        "lamina_upper_R",
        "spinous_upper",
        "spinous_tip",
    }
    assert all(len(v) == 1 and sacrum[v].all() for v in anchors.values())
    # the SAP tips rise above the plate (they reach up behind L5's inferior processes); the crest is midline
    assert loc[anchors["sap_tip_L"], 2] > 0 and loc[anchors["sap_tip_R"], 2] > 0
    assert (
        abs(loc[anchors["spinous_tip"], 0]) < 4.0 and loc[anchors["spinous_tip"], 1] < loc[anchors["spinous_upper"], 1]
    )
    # orientation: the angle to the mid-sagittal plane of the articular surface's mean outward normal's transverse
    # trace (the facing of the curved, shrink-wrapped surface; a plane fit to its cupped patch is unstable), S1 in
    # its plate frame, L5's superior facets (the L4-L5 joint) in L5's body frame
    from spinecohort.anatomy.assemble import body_frame
    from spinecohort.anatomy.labeling import vertex_normals

    normals = vertex_normals(ref.vertices, ref.faces)

    def facing(idx, frame):
        m = normals[idx].sum(0) @ frame.T
        return m / np.linalg.norm(m), float(np.degrees(np.arctan2(abs(m[1]), abs(m[0]))))

    l5 = ref.vertebra(LEVELS.index("L5"))
    l5_frame = body_frame(ref.vertices[l5], normals[l5], ref.region[l5] == labels.region_id("body"))
    for s, sgn in (("left", -1.0), ("right", 1.0)):
        m, s1_deg = facing(ref.sets[f"facet_surface_sup_{s}"]["S1"], rows)
        _, l5_deg = facing(ref.sets[f"facet_surface_sup_{s}"]["L5"], l5_frame)
        assert s1_deg == pytest.approx({"left": 52.5, "right": 41.1}[s], abs=1.0)
        assert 49.1 - 12.4 <= s1_deg <= 49.1 + 12.4  # inside the published mean +- SD
        assert s1_deg > l5_deg + 5.0  # more coronal than L4-L5 (L5's: 33.5 left, 29.5 right)
        assert m[1] < -0.3 and -sgn * m[0] > 0.3  # facing posteriorly and medially
