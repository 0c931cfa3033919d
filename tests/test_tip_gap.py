"""The extension stop from the bones (`spinecohort.fe.tip_gap`): the tip's path and the ray cast on closed forms,
the stops of the real-bone reference (the real cohort's shape and numbering) and the config switch."""

from __future__ import annotations

import numpy as np
import pytest

from spinecohort.fe.facets import FacetContact, _joints, facet_nodes, facet_pairs, tip_struts
from spinecohort.fe.tip_gap import MAX_CLEARANCE_MM, extension_path, ray_distances, tip_stops


def test_the_tip_starts_out_along_the_tangent_of_its_circle_caudally():
    # a tip 30 mm behind and 10 mm above the axis (x lateral, y anterior, z cranial): r = (0, -30, 10), the
    # tangent x cross r = (0, -10, -30), i.e. caudally and posteriorly, 18.4 deg off the caudal axis
    x, z = np.array([1.0, 0, 0]), np.array([0, 0, 1.0])
    path = extension_path(np.array([5.0, -30.0, 10.0]), np.zeros(3), x, z)
    assert path == pytest.approx(np.array([0.0, -1.0, -3.0]) / np.sqrt(10.0))
    assert np.degrees(np.arccos(-path @ z)) == pytest.approx(np.degrees(np.arctan(1 / 3)))
    # the sense does not depend on the sign of the lateral axis
    assert extension_path(np.array([5.0, -30.0, 10.0]), np.zeros(3), -x, z) == pytest.approx(path)
    with pytest.raises(ValueError, match="no path"):
        extension_path(np.array([7.0, 0.0, 0.0]), np.zeros(3), x, z)


def test_a_ray_meets_the_first_triangle_ahead_at_its_distance():
    tri = np.array([[[-1.0, -1.0, -5.0], [2.0, -1.0, -5.0], [-1.0, 2.0, -5.0]]])  # the plane z = -5
    two = np.concatenate([tri, tri + [0, 0, -3.0]])  # and z = -8 behind it
    down = np.array([0.0, 0.0, -1.0])
    got = ray_distances(np.array([[0.0, 0.0, 0.0], [0.0, 0.0, -6.0], [5.0, 5.0, 0.0]]), down, two)
    assert got[0] == pytest.approx(5.0) and got[1] == pytest.approx(2.0) and np.isinf(got[2])  # beside: a miss
    slant = np.array([0.0, 0.6, -0.8])  # 5 mm down along a slanted ray: 6.25 mm, met at y = 3.75
    assert ray_distances(np.zeros((1, 3)), slant, 10.0 * tri * [1, 1, 0.1])[0] == pytest.approx(6.25)
    assert np.isinf(ray_distances(np.zeros((1, 3)), -down, tri)[0])  # behind the origin: never met
    assert np.isinf(ray_distances(np.zeros((1, 3)), down, np.zeros((0, 3, 3)))[0])


def test_lumbar_tips_meet_the_bone_below_within_a_few_mm_and_the_thoracolumbar_ones_do_not(real_template):
    # the measured geometry the per-joint stop rests on: on the reference the lumbar IAP tips meet the lamina /
    # pars below after 0.9-3.9 mm along their extension path, while the T10-T11 and T11-T12 tips overhang the
    # lamina and meet nothing within 8 mm (docs/explanation/fe-model.md); bare bone (no soft tissue)
    t = real_template
    pairs = facet_pairs(t)
    frames, joints = _joints(t, t.nodes, pairs)
    direction, gap = tip_stops(t, t.nodes, pairs, joints, frames, 0.0)
    by = {(up, lo, side): (d, g) for (up, lo, side), d, g in zip(joints, direction, gap)}
    lumbar = [g for (up, _, _), (_, g) in by.items() if up in ("L1", "L2", "L3", "L4")]
    assert len(lumbar) == 8 and 0.5 < min(lumbar) and max(lumbar) < 5.0
    assert all(by[(up, lo, s)][1] == MAX_CLEARANCE_MM for up, lo in (("T10", "T11"), ("T11", "T12")) for s in (-1, 1))
    for (up, lo, side), (d, _) in by.items():
        cranial = frames[lo][0][:, 2]
        # the strut pushes the tip back up its path: cranially, within 35 deg of the lower vertebra's axis
        assert np.linalg.norm(d) == pytest.approx(1.0) and d @ cranial > np.cos(np.radians(35.0)), (up, side)
    # with soft tissue each clearance is the bone gap less it, never below 0; a tip that meets no bone keeps the
    # largest clearance
    _, soft = tip_stops(t, t.nodes, pairs, joints, frames, 1.0)
    near = gap < MAX_CLEARANCE_MM
    assert (
        soft[near] == pytest.approx(np.clip(gap[near] - 1.0, 0.0, None))
        and (soft[~near] >= MAX_CLEARANCE_MM - 1.0).all()
    )
    with pytest.raises(ValueError, match=">= 0 mm"):
        tip_stops(t, t.nodes, pairs, joints, frames, -0.5)


def test_the_config_switches_the_stop_from_one_clearance_to_the_bones(real_template):
    t = real_template
    pairs = facet_pairs(t)
    base = {"enabled": True, "clearance_mm": 0.79, "stiffness_n_per_mm": 1670.0, "tip_clearance_mm": 2.0}
    base |= {"transverse_deg": {"T1": 60.0}, "frontal_deg": {"T1": -27.5}, "strut_length_mm": 20.0}
    fixed = FacetContact.from_config(base)
    bones = FacetContact.from_config({**base, "tip_soft_tissue_mm": 1.0})
    assert fixed.tip_soft_tissue_mm is None and bones.tip_soft_tissue_mm == 1.0
    one = tip_struts(t, t.nodes, pairs, fixed)
    per_joint = tip_struts(t, t.nodes, pairs, bones)
    assert one.clearance_mm == pytest.approx(np.full(len(pairs), 2.0))
    assert per_joint.clearance_mm.std() > 1.0  # per joint: lumbar ~1-3 mm, thoracolumbar 8 mm
    # the deck's stop struts carry those clearances in their force tables (the closing elongation)
    fn = facet_nodes(t, t.nodes, pairs, bones)
    stops = [gap for gap, name in fn.sections if name.startswith("FACET_TIP_")]
    assert [g[0] for g in stops] == pytest.approx(list(per_joint.clearance_mm))
