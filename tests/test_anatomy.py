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
