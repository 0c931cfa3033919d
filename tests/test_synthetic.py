"""The synthetic cohort: anatomy, correspondence, inclusion criteria and exactness of its construction."""

import numpy as np
import pytest

from spinecohort.cohort.landmarks import LEVELS
from spinecohort.cohort.surfaces import edge_check, signed_volume
from spinecohort.cohort.synthetic import (
    CRITERIA,
    RESOLUTIONS,
    build_chain,
    build_patient_mesh,
    coronal_endplate_tilts,
    draw_patient,
    generate_cohort,
    pos_inf,
    pos_sup,
)


def _sag(n):
    return np.degrees(np.arctan2(n[..., 1], n[..., 2]))


def _plane_normal(p):
    _, s, vt = np.linalg.svd(p - p.mean(0))
    n = vt[-1]
    return (n if n[2] > 0 else -n), s[-1] / np.sqrt(len(p))


def test_default_cohort_meets_inclusion_criteria():
    c = generate_cohort(42, resolution="coarse")
    t = c.table
    assert len(t) == 42 and list(t["ID"]) == [f"P{i:02d}" for i in range(1, 43)]
    assert (t["PI_minus_LL"] > CRITERIA["PI_minus_LL_min_deg"]).all()
    assert (t["PT"] > CRITERIA["PT_min_deg"]).all()
    assert (t["SVA_T1"] > CRITERIA["SVA_T1_min_mm"]).all()
    assert t["age"].between(50, 75).all()
    # PI = PT + SS holds exactly by construction
    assert np.allclose(t["PI"], t["PT"] + t["SS"], atol=1e-9)
    # anatomical plausibility of the drawn values (reference ranges, spinopelvic.md)
    assert t["PI"].between(35, 85).all() and t["HA_width"].between(130, 190).all()
    assert t["FH_radius_L"].between(19, 29).all()


def test_correspondence_and_reproducibility(small_cohort):
    c = small_cohort
    again = generate_cohort(3, seed=7, resolution="coarse")
    assert np.array_equal(again.faces, c.faces)
    assert np.array_equal(again.vertices, c.vertices[:3])  # same seed -> identical patients
    # vertices numbered by first use in the face list (the STL round-trip property)
    _, first = np.unique(c.faces.ravel(), return_index=True)
    assert np.all(np.diff(first) > 0)


def test_default_resolution_size():
    p = draw_patient(np.random.default_rng(0), "P01")
    v, f, lm, _ = build_patient_mesh(p, RESOLUTIONS["default"])
    assert len(v) == 81094 and 50_000 <= len(v) <= 150_000
    # Euler characteristic: F = 2V - 4 per closed sphere-like part (217 of them), F = 2V per torus (2)
    assert len(f) == 2 * len(v) - 4 * 217


def test_every_body_sacrum_and_head_is_a_closed_oriented_surface(small_cohort):
    c = small_cohort
    lm = c.landmarks
    v = c.vertices[0]
    assert edge_check(c.faces) == (True, True)
    for name in [f"body_{lv}" for lv in LEVELS] + ["sacrum", "femoral_head_L", "femoral_head_R"]:
        label = lm.part_names.index(name)
        faces = c.faces[np.all(lm.part[c.faces] == label, axis=1)]
        assert edge_check(faces) == (True, True), name
        assert signed_volume(v, faces) > 0, name
    # unique float32 coordinates: the STL vertex merge cannot fuse two vertices
    assert len(np.unique(v.astype(np.float32), axis=0)) == len(v)


def test_endplates_are_exact_planes_with_the_imposed_tilts():
    p = draw_patient(np.random.default_rng(11), "P01")
    chain = build_chain(p)
    v, f, lm, truth = build_patient_mesh(p, RESOLUTIONS["coarse"], noise_mm=1.0, rng=np.random.default_rng(3))
    # undo the rigid placement (rotation about z) to compare with the construction frame
    a = np.radians(p.axial_rotation_deg)
    rz = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    v0 = (v - p.translation) @ rz
    for i, lv in enumerate(LEVELS):
        for pos, idx in ((pos_sup(i), lm.endplate_sup[lv]), (pos_inf(i), lm.endplate_inf[lv])):
            n, rms = _plane_normal(v0[idx])
            assert rms < 1e-9  # the smooth noise never touches endplates
            assert abs(_sag(n) - chain.sag[pos]) < 1e-8
            assert abs(np.degrees(np.arctan2(n[0], n[2])) - chain.cor[pos]) < 1e-8
            assert np.allclose(v0[idx].mean(0), chain.centres[pos], atol=1e-9)
    n, _ = _plane_normal(v0[lm.endplate_sup["S1"]])
    assert abs(_sag(n) - truth["SS"]) < 1e-8
    for side, sgn in (("L", -1), ("R", 1)):
        r = np.linalg.norm(v0[lm.femoral_head[side]] - [sgn * p.hip_width / 2, 0, 0], axis=1)
        assert np.allclose(r, p.fh_radius, atol=1e-9)
    # posterior elements and pelvis are perturbed (noise is real): some vertex moved > 0.1 mm
    v_clean, *_ = build_patient_mesh(p, RESOLUTIONS["coarse"], noise_mm=0.0)
    assert np.abs(v - v_clean).max() > 0.1


def test_truth_is_the_sum_of_imposed_segment_angles():
    p = draw_patient(np.random.default_rng(5), "P01")
    chain = build_chain(p)
    _, _, _, t = build_patient_mesh(p, RESOLUTIONS["coarse"])
    assert t["LL"] == pytest.approx(p.LL, abs=1e-9)  # L1-S1 lordosis as drawn
    assert t["LDI"] == pytest.approx(p.LDI, abs=1e-9)
    assert t["TK_T4T12"] == pytest.approx(p.TK_T4T12, abs=1e-9)
    assert t["TK_T1T12"] == pytest.approx(p.TK_T4T12 + p.TK_T1T4, abs=1e-9)
    assert t["Cobb"] == pytest.approx(p.cobb, abs=1e-9)
    assert t["Cobb_upper"] == LEVELS[p.cobb_upper] and t["Cobb_lower"] == LEVELS[p.cobb_lower]
    # disc L4-L5 central height: the distance between the two endplate centres along their mean normal
    i4, i5 = LEVELS.index("L4"), LEVELS.index("L5")
    m = chain.normals[pos_inf(i4)] + chain.normals[pos_sup(i5)]
    h = (chain.centres[pos_inf(i4)] - chain.centres[pos_sup(i5)]) @ (m / np.linalg.norm(m))
    assert t["DH_L4-L5"] == pytest.approx(h, abs=1e-9)
    assert 6 < t["DH_L4-L5"] < 12


def test_coronal_profile_has_the_imposed_main_curve():
    p = draw_patient(np.random.default_rng(2), "P01")
    phi = coronal_endplate_tilts(p)
    assert phi[0] == 0.0  # S1 is level
    assert phi[pos_sup(p.cobb_upper)] - phi[pos_inf(p.cobb_lower)] == pytest.approx(p.cobb * p.cobb_sign)
