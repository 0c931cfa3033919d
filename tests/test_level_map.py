"""The per-level map of the thoracic template (`spinecohort.anatomy.level_map`) and the thoracic levels of the
vendored reference it builds."""

from __future__ import annotations

import numpy as np
import pytest

from spinecohort.anatomy import level_map as L
from spinecohort.anatomy.assemble import carried_from_template
from spinecohort.anatomy.labels import VERTEBRA_REGIONS
from spinecohort.cohort.landmarks import LEVELS


def _template() -> L.Template:
    """A grid 'vertebra': body box x in [-20, 20], y in [-15, 15] (anterior wall +15, posterior -15), z in
    [-12, 12]; arch points behind it (y -20..-60), two facet blocks and a spinous rod at the mid-line."""
    g = np.linspace(-1.0, 1.0, 9)
    body = np.array([[20 * a, 15 * b, 12 * c] for a in g for b in g for c in g])
    arch = np.array([[15 * a, -20 - 40 * (b + 1) / 2, 10 * c] for a in g for b in g for c in g])
    pts = np.concatenate([body, arch])
    n_body = len(body)
    regions = {name: np.array([], int) for name in VERTEBRA_REGIONS}
    regions["body"] = np.arange(n_body)
    arch_idx = n_body + np.arange(len(arch))
    x, y = pts[arch_idx, 0], pts[arch_idx, 1]
    regions["spinous"] = arch_idx[(np.abs(x) < 2) & (y < -45)]
    for side, sign in (("left", -1.0), ("right", 1.0)):
        block = arch_idx[(sign * x > 10) & (y > -35) & (y < -25)]
        regions[f"facet_sup_{side}"] = block[pts[block, 2] > 0]
        regions[f"facet_inf_{side}"] = block[pts[block, 2] <= 0]
    return L.Template(pts, 40.0, 30.0, 24.0, 24.0, 15.0, -15.0, regions)


def test_smoothstep_and_region_weight_are_a_smooth_cutoff():
    t = np.array([-1.0, 0.0, 0.25, 0.5, 1.0, 2.0])
    assert np.allclose(L.smoothstep(t), [0.0, 0.0, 0.15625, 0.5, 1.0, 1.0])  # 3t^2 - 2t^3
    pts = np.array([[0.0, 0, 0], [2.0, 0, 0], [4.0, 0, 0], [9.0, 0, 0]])
    w = L.region_weight(pts, np.array([0]), radius_mm=4.0)
    assert np.allclose(w, [1.0, 0.5, 0.0, 0.0])


def test_the_template_at_its_own_size_is_not_moved():
    t = _template()
    same = L.LevelShape(40.0, 30.0, 24.0, 24.0, (1.0, 1.0, 1.0))
    assert np.allclose(L.map_vertebra(t, same), t.local)


def test_the_body_is_scaled_and_wedged_exactly():
    t = _template()
    shape = L.LevelShape(28.0, 21.0, 16.0, 18.0, (0.8, 0.8, 0.7))
    out = L.map_vertebra(t, shape)
    body = t.regions["body"]
    assert np.ptp(out[body, 0]) == pytest.approx(28.0)  # width 40 -> 28
    assert np.ptp(out[body, 1]) == pytest.approx(21.0)  # depth 30 -> 21
    front = body[t.local[body, 1] == 15.0]
    back = body[t.local[body, 1] == -15.0]
    assert np.ptp(out[front, 2]) == pytest.approx(16.0)  # anterior height 24 -> 16
    assert np.ptp(out[back, 2]) == pytest.approx(18.0)  # posterior height 24 -> 18 (a 2 mm wedge)
    # behind the blend zone the arch takes its own scales about the posterior wall, which stays attached
    far = np.flatnonzero(t.local[:, 1] < -15.0 - 6.0)
    assert np.allclose(out[far, 0], 0.8 * t.local[far, 0])
    assert np.allclose(out[far, 1], 0.7 * -15.0 + 0.8 * (t.local[far, 1] + 15.0))
    assert np.allclose(out[far, 2], 0.7 * t.local[far, 2])


def test_the_taper_narrows_the_body_towards_its_anterior_wall_only():
    t = _template()
    out = L.map_vertebra(t, L.LevelShape(40.0, 30.0, 24.0, 24.0, (1.0, 1.0, 1.0), taper=0.25))
    body = t.regions["body"]
    for y, width in ((15.0, 30.0), (7.5, 35.0), (0.0, 40.0), (-15.0, 40.0)):  # 1 - 0.25 * smoothstep(y / 15)
        row = body[t.local[body, 1] == y]
        assert np.ptp(out[row, 0]) == pytest.approx(width), y


def test_the_facet_turn_swirls_the_pillar_about_its_axis_and_spares_the_body():
    t = _template()
    shape = L.LevelShape(40.0, 30.0, 24.0, 24.0, (1.0, 1.0, 1.0), facet_sup_deg=110.0, facet_inf_deg=110.0)
    out = L.map_vertebra(t, shape)
    # the left pillar's axis: midway between its processes' centroids (the blocks: x -11.25 and -15, y -30,
    # so x -13.125, y -30); every block point lies within 1.9 mm of it, inside the 6 mm core
    pillar = np.concatenate([t.regions["facet_sup_left"], t.regions["facet_inf_left"]])
    axis = np.array([-13.125, -30.0])
    assert np.allclose(
        0.5 * (t.local[t.regions["facet_sup_left"]].mean(0) + t.local[t.regions["facet_inf_left"]].mean(0))[:2], axis
    )
    before, after = t.local[pillar, :2] - axis, out[pillar, :2] - axis
    # a swirl moves every point on its circle about the axis and keeps its height
    assert np.allclose(np.linalg.norm(after, axis=1), np.linalg.norm(before, axis=1))
    assert np.allclose(out[pillar, 2], t.local[pillar, 2])
    turn = np.degrees(np.arctan2(after[:, 1], after[:, 0]) - np.arctan2(before[:, 1], before[:, 0]))
    turn = (turn + 180.0) % 360.0 - 180.0
    # the processes' articular ends (height fraction beyond 0.2 from the pars: z >= 4 or z <= -2.75) turn by
    # the whole 110 deg, clockwise seen from above on the left (towards and past the coronal plane)
    ends = (out[pillar, 2] >= 4.0) | (out[pillar, 2] <= -2.75)
    assert np.allclose(turn[ends], -110.0)
    # at z = 0 (height fraction h = 5 / 11.25 between the centroids' heights -5 and 6.25) the angle is
    # PARS_TURN + (1 - PARS_TURN) * smoothstep(|2h - 1| / 0.6) of the turn: with PARS_TURN 0, smoothstep(0.185)
    # = 0.0902 of it (9.92 deg), the pars nearly unturned
    h = 5.0 / 11.25
    expected = 110.0 * (L.PARS_TURN + (1.0 - L.PARS_TURN) * L.smoothstep(abs(2.0 * h - 1.0) / 0.6))
    assert expected == pytest.approx(9.92, abs=0.01)
    assert np.allclose(turn[out[pillar, 2] == 0.0], -expected)
    assert np.allclose(out[t.regions["body"]], t.local[t.regions["body"]])  # the body is not touched
    tip = np.array([0.0, -70.0, -25.0])
    aimed = L.map_vertebra(t, L.LevelShape(40.0, 30.0, 24.0, 24.0, (1.0, 1.0, 1.0), spinous_tip=tuple(tip)))
    sp = t.regions["spinous"]
    assert np.linalg.norm(aimed[sp] - tip, axis=1).min() < 1e-6


def test_labels_are_carried_by_index_and_a_foreign_vertex_set_is_refused():
    # an octahedron (closed, outward triangles) as the template, all body; moved by a similarity
    tpl_points = np.array([[1.0, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]]) * 10.0
    faces = np.array([[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4], [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]])
    tpl = {"region": np.zeros(6, np.int8), "landmarks": tpl_points[[1, 4]], "anchors": {"a": 5}}
    moved = tpl_points * 0.7 + 3.0
    out = carried_from_template(tpl, (tpl_points, faces), (moved, faces), "T4")
    assert out["region"] is tpl["region"] and out["anchors"] == {"a": 5}
    assert np.allclose(out["landmarks"], moved[[1, 4]])
    assert np.allclose(out["centre"], [3.0, 3.0, 3.0])  # the moved body's centroid
    assert np.allclose(out["frame"], np.eye(3))  # right, anterior, cranial: unchanged by a similarity
    with pytest.raises(ValueError, match="T4: not the thoracic template"):
        carried_from_template(tpl, (tpl_points, faces), (moved[:-1], faces), "T4")


def test_reference_thoracic_levels_share_the_template_labels_and_measure_their_targets():
    from spinecohort.anatomy.morphometry_table import measure_reference
    from spinecohort.anatomy.reference import load_reference

    ref = load_reference()
    first = ref.vertebra(0)
    for i in range(1, 12):
        idx = ref.vertebra(i)
        assert np.array_equal(ref.region[idx], ref.region[first]), LEVELS[i]
        lv = LEVELS[i]
        assert np.array_equal(ref.landmarks.endplate_sup[lv] - idx[0], ref.landmarks.endplate_sup["T1"] - first[0])
    wide = measure_reference(ref).pivot(index="level", columns="quantity", values="value")
    # built to Panjabi 1991's posterior body heights (T1 14.3, T12 22.7 mm) and endplate widths (T11 35.2,
    # T12 39.2 mm), and the typical-thoracic mean width 27.02 mm at T2-T5
    assert wide.loc["T1", "body_height_posterior"] == pytest.approx(14.3, abs=0.2)
    assert wide.loc["T12", "body_height_posterior"] == pytest.approx(22.7, abs=0.2)
    assert wide.loc["T11", "endplate_width_upper"] == pytest.approx(35.2, abs=0.2)
    assert wide.loc["T12", "endplate_width_upper"] == pytest.approx(39.2, abs=0.2)
    assert np.allclose(wide.loc[["T2", "T3", "T4", "T5"], "endplate_width_upper"], 27.02, atol=0.2)
    # thoracic bodies are smaller and shorter than lumbar ones, growing caudally
    heights = wide.loc[list(LEVELS), "body_height_posterior"]
    assert (np.diff(heights[:12]) > 0).all() and heights["T12"] < heights["L1"]


def test_reference_thoracic_superior_facets_face_backwards_and_laterally_and_fold_nothing():
    """Thoracic superior articular facets face posteriorly, a little laterally and upwards (Gray's Anatomy;
    Masharawi 2004: 25-30 deg from the frontal plane at T1-T11), lumbar ones medially (T12 26-34 deg to the
    mid-sagittal plane: the thoracolumbar transition at T11-T12).  On the vendored reference's articular
    surfaces (the process within 4 mm of its partner), in each vertebra's own frame."""
    from spinecohort.anatomy import morphometry as M
    from spinecohort.anatomy.labeling import vertex_normals
    from spinecohort.anatomy.labels import REGIONS
    from spinecohort.anatomy.morphometry_table import measure_reference
    from spinecohort.anatomy.reference import load_reference
    from spinecohort.anatomy.surface import self_intersections

    ref = load_reference()
    normals = vertex_normals(ref.vertices, ref.faces)
    facing = {}
    for i, lv in enumerate(LEVELS[:13]):
        parts = M.parts_of_vertebra(ref.region, REGIONS, ref.level == i)
        frame = M.vertebra_frame(
            ref.vertices,
            ref.landmarks.endplate_sup[lv],
            ref.landmarks.endplate_inf[lv],
            parts["body"],
            M.canal_centre(ref.vertices, parts),
        )
        for side, sign in (("left", -1.0), ("right", 1.0)):
            ids = ref.sets[f"facet_surface_sup_{side}"][lv]
            outward = normals[ids].sum(0) @ frame.axes.T
            facing[lv, side] = M.facet_facing(frame.local(ref.vertices[ids]), outward, sign)
        # every thoracic level is one closed surface without self-intersections (the swirl folds nothing)
        idx = ref.vertebra(i)
        if i < 12:
            tri = ref.faces[np.isin(ref.faces, idx).all(1)] - idx[0]
            assert self_intersections(ref.vertices[idx], tri) == 0, lv
    # T2-T11 (the joints T1-T2 ... T10-T11; T1's patch is the tip cap of a process without partner) face
    # laterally, 10-35 deg from the frontal plane (Masharawi's 25-30 with room for the patches, which lag the
    # turned articular face by a few degrees)
    for lv in LEVELS[1:11]:
        for side in ("left", "right"):
            assert -35.0 <= facing[lv, side] <= -10.0, (lv, side, facing[lv, side])
    # in Masharawi's unsigned transverse angle (morphometry's, the mean of both sides): the published 60-65 deg,
    # at most 7 deg more coronal
    wide = measure_reference(ref).pivot(index="level", columns="quantity", values="value")
    assert wide.loc[list(LEVELS[1:11]), "facet_sup_transverse"].between(60.0, 72.0).all()
    # T12's superior facets face medially (lumbar), 26-34 deg to the mid-sagittal plane: 56-64 deg frontal
    for side in ("left", "right"):
        assert 50.0 <= facing["T12", side] <= 70.0, side
    assert 26.0 <= wide.loc["T12", "facet_sup_transverse"] <= 34.0
