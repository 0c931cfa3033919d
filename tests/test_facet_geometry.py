"""Facet joints from the bones' articular surfaces and ligaments as fibre bundles at their insertion sites
(`spinecohort.fe.facet_geometry`, `spinecohort.mesh.ligament_sites`), on closed forms and on the real-bone
reference (the real cohort's shape and vertex numbering)."""

from __future__ import annotations

import shutil
from dataclasses import replace

import numpy as np
import pytest

from spinecohort.anatomy.morphometry import facet_angles_deg
from spinecohort.fe.facet_geometry import joint_geometry, kmeans_points, plane_normal
from spinecohort.fe.facets import FacetContact, facet_nodes, facet_pairs, joint_surfaces
from spinecohort.fe.materials import DEFAULT_LIGAMENTS, fibre_law, ligament_force_n, ligament_table
from spinecohort.mesh.ligament_sites import across_width, around_ring, distinct_nearest

needs_ccx = pytest.mark.skipif(shutil.which("ccx") is None, reason="CalculiX 'ccx' not installed")


def planar_patch(normal, centre, n=60, seed=0, size=8.0):
    """n points (mm) spread over a size x size square in the plane through `centre` with unit `normal`."""
    rng = np.random.default_rng(seed)
    a = np.cross(normal, [1.0, 0.0, 0.0] if abs(normal[0]) < 0.9 else [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(normal, a)
    uv = rng.uniform(-size / 2, size / 2, (n, 2))
    return centre + uv[:, :1] * a + uv[:, 1:] * b


def test_plane_fit_recovers_the_normal_of_a_planar_patch():
    n = np.array([0.3, -0.8, 0.5])
    n /= np.linalg.norm(n)
    c, got = plane_normal(planar_patch(n, np.array([10.0, -40.0, 5.0])))
    assert abs(got @ n) == pytest.approx(1.0, abs=1e-12)  # a planar patch: exact up to the sign
    assert c == pytest.approx(planar_patch(n, np.array([10.0, -40.0, 5.0])).mean(0))


def test_two_parallel_facets_give_their_normal_their_gap_and_the_configured_angles():
    # the joint of a FacetContact at 60 deg to the transverse plane, 27.5 deg to the frontal plane facing
    # laterally (the fallback's thoracic values): SAP patch, IAP patch 1.4 mm further along the normal.  The
    # geometry must give that normal (SAP -> IAP), the gap 1.4 mm at every contact point and back the two angles.
    frame = np.eye(3)  # lateral (right), anterior, cranial
    fc = FacetContact(transverse_deg=(("T1", 60.0), ("L5", 60.0)), frontal_deg=(("T1", -27.5), ("L5", -27.5)))
    n = fc.normal("T6", frame, -1.0)
    sap = planar_patch(n, np.zeros(3), seed=1)
    shift = np.array([0.5, 0.0, 0.0]) - 0.5 * n[0] * n  # in the plane: the patches overlap, not coincide
    iap = planar_patch(n, 1.4 * n + shift, seed=2)
    geo = joint_geometry(sap, iap, 4, sap_outward=n, iap_outward=-n)
    assert geo.normal @ n == pytest.approx(1.0, abs=1e-9)
    assert geo.gaps == pytest.approx(np.full(4, 1.4), abs=1e-9)
    assert (geo.points - sap.mean(0)) @ n == pytest.approx(np.full(4, 0.7), abs=1e-9)  # midway
    assert facet_angles_deg(geo.normal, frame, -1.0) == pytest.approx((60.0, -27.5), abs=1e-6)
    # the contact points spread over the facing part: four k-means centres of a square are its quadrants'
    cells = -1.0 + 0.1 * (np.arange(20) + 0.5)  # cell centres of a 2 x 2 square
    xy = np.array([[x, y] for x in cells for y in cells])
    centres = kmeans_points(xy, 4)
    assert np.abs(centres) == pytest.approx(np.full((4, 2), 0.5), abs=1e-12)


def test_bundle_fibres_under_a_uniform_stretch_carry_the_single_ligaments_force():
    # k fibres, each with 1/k of the area, at the same strain: k x the fibre force = the one spring's force,
    # at every strain of the law (toe, linear, transition, beyond); and so do their force tables
    strain = np.array([0.0, 0.005, 0.03, 0.1, 0.25, 0.6])
    for group, law in DEFAULT_LIGAMENTS.items():
        for k in (2, 3, 5):
            assert k * ligament_force_n(fibre_law(law, k), strain) == pytest.approx(ligament_force_n(law, strain))
            one, fib = np.array(ligament_table(law, 12.0)), np.array(ligament_table(fibre_law(law, k), 12.0))
            assert fib[:, 1] == pytest.approx(one[:, 1]) and k * fib[:, 0] == pytest.approx(one[:, 0]), group
    with pytest.raises(ValueError, match="at least one fibre"):
        fibre_law(DEFAULT_LIGAMENTS["LF"], 0)


def test_bundle_sampling_spreads_the_fibres_and_matches_their_ends():
    # LF: two parallel edges 10 mm apart, 20 mm wide: fibres at both ends and the middle, each vertical
    t = np.linspace(-10, 10, 41)
    upper = np.c_[t, np.zeros_like(t), np.full_like(t, 10.0)]
    lower = np.c_[t[::-1], np.zeros_like(t), np.zeros_like(t)]  # numbered the other way round
    iu, il = across_width(upper, lower, 3)
    assert upper[iu, 0] == pytest.approx(lower[il, 0]) and np.sort(upper[iu, 0]) == pytest.approx([-10, 0, 10])
    # CL: two rings (rims) round a joint, 3 mm apart: 4 fibres 90 deg apart, each end at the same angle
    a = np.linspace(0, 2 * np.pi, 36, endpoint=False)
    ring = np.c_[5 * np.cos(a), 5 * np.sin(a), np.zeros_like(a)]
    iu, il = around_ring(ring + [0, 0, 3.0], ring[::-1], 4)
    assert len(set(iu)) == 4 and (ring + [0, 0, 3.0])[iu, :2] == pytest.approx(ring[::-1][il, :2], abs=1e-9)
    # distinct: 3 targets nearest the same candidate still get three different ones
    assert sorted(distinct_nearest(np.array([0.0, 1.0, 2.0, 9.0]), np.array([1.0, 1.1, 0.9]))) == [0, 1, 2]


def test_every_real_joint_pushes_from_its_superior_onto_its_inferior_facet(real_template):
    from spinecohort.fe.connections import arch_owner
    from spinecohort.fe.facets import _joints

    t, pts = real_template, real_template.nodes
    fc = FacetContact(tip_clearance_mm=None)
    pairs = facet_pairs(t)
    assert len(pairs) == 34  # 17 segments T1-T2 .. L4-L5 and L5-S1 (the sacrum's SAPs), left and right
    fn = facet_nodes(t, pts, pairs, fc)
    owner = arch_owner(t)
    _, joints = _joints(t, pts, pairs)
    m = fc.struts_per_joint
    assert len(fn.gaps) == m * len(pairs)
    for j, (up, lo, side) in enumerate(joints):
        assert (owner[int(pairs[j, 0])], owner[int(pairs[j, 1])]) == (up, lo)
        sap, iap = joint_surfaces(t, up, lo, side)
        assert {owner[int(i)] for i in sap} == {lo} and {owner[int(i)] for i in iap} == {up}
        for k in range(m * j, m * (j + 1)):
            lower_node, upper_node = fn.gaps[k]
            assert lower_node in fn.tied[lo] and upper_node in fn.tied[up]  # on the right vertebrae
            d = fn.points[upper_node] - fn.points[lower_node]  # the strut's push on the upper vertebra
            # from the SAP towards the IAP: along the SAP's outward side, and the IAP lies on that side
            assert d @ (pts[iap].mean(0) - pts[sap].mean(0)) > 0, fn.sections[k][1]
            assert fn.sections[k][0][2] == pytest.approx(fc.stiffness_n_per_mm / m)  # the joint's stiffness split


def test_real_ligament_bundles_have_their_fibres_and_the_primitives_keep_one_spring(real_template, template):
    t = real_template
    assert t.meta["ligament_fibres"] == {"ALL": 3, "PLL": 3, "LF": 3, "CL": 4}
    # 17 discs x 3 ALL / PLL fibres; 17 segments (L5-S1 on the sacrum's sites included) x 2 sides x 3 LF / 4 CL
    # fibres, one ISL and SSL each; ITL on the 16 segments T1-T2 .. L4-L5 (L5-S1's iliolumbar ligament is not
    # modelled)
    got = [len(t.elsets[f"LIG_{g}"]) for g in ("ALL", "PLL", "LF", "CL", "ISL", "SSL", "ITL")]
    assert got == [51, 51, 102, 136, 17, 17, 32]
    ends = t.ligaments[t.elsets["LIG_LF"]]
    assert len(np.unique(ends.reshape(-1, 3, 2)[:, :, 0], axis=0)) == 34  # 3 distinct upper ends per LF
    # the primitive test cohort has no sites: one spring per ligament, no surfaces, the configured angles
    assert template.ligament_fibres("CL") == 1 and not template.sites
    assert (
        len(template.elsets["LIG_CL"]) == 32
        and len(facet_nodes(template, template.nodes, facet_pairs(template), FacetContact()).gaps) == 64
    )


@needs_ccx
def test_a_real_unit_with_surface_facets_and_bundles_solves_in_ccx(real_template, tmp_path):
    # the T6-T7 unit of the reference with its facet struts and ligament bundles at 3 N.m axial rotation,
    # config/config.yaml's materials: the full load, 2.49 deg, the same with and without facets: the thoracic
    # superior facets face posteriorly and laterally, on an arc about the body, so axial rotation slides the
    # joint along its plane and never closes its 0.79 mm clearance (compression-only struts can only stiffen)
    from spinecohort.rom.run import Settings, run_case
    from spinecohort.rom.submodel import extract_rom_model

    rot = {}
    for name, facets in (("facets", FacetContact()), ("none", None)):
        m = extract_rom_model(real_template, real_template.nodes, "T6", "T7", facets=facets)
        assert m.ligament_groups["CL"] == 8 and m.ligament_groups["LF"] == 6 and m.ligament_groups["ALL"] == 3
        r = run_case(m, "axial_left", tmp_path / name, moment_nmm=3000.0, **Settings().deck_kw())
        assert r.load_fraction == 1.0
        rot[name] = r.curve[-1, 1]
    assert rot["facets"] == pytest.approx(2.492, abs=0.01)
    assert rot["facets"] == pytest.approx(rot["none"], rel=1e-3)


def test_real_landmarks_carry_the_sites_through_json_and_validation_names_a_bad_one():
    from spinecohort.anatomy.reference import load_reference
    from spinecohort.cohort.landmarks import Landmarks
    from spinecohort.cohort.real import first_use_reference

    ref = first_use_reference(load_reference())
    lm = ref.landmarks
    # 4 facet surfaces x 17 levels T1-L5 and S1's two superior ones; ligament sites on T1-L5 and S1's cranial
    # ones (its superior articular processes, laminae and median crest: the L5-S1 joint)
    assert len([k for k in lm.sites if k.startswith("facet_surface_")]) == 70
    assert lm.site("site_LF_inf_left", "T6") is not None and lm.site("site_LF_inf_left", "S1") is None
    assert lm.site("site_LF_sup_left", "S1") is not None and len(lm.site("anchor_sap_tip_R", "S1")) == 1
    back = Landmarks.from_dict(lm.to_dict())
    assert back.sites.keys() == lm.sites.keys()
    assert all(np.array_equal(back.sites[k], v) for k, v in lm.sites.items())
    back.validate(len(ref.vertices))
    bad = replace(back, sites={**back.sites, "site_CL_sup_left/T6": np.array([len(ref.vertices)])})
    with pytest.raises(ValueError, match=r"sites\[site_CL_sup_left/T6\]"):
        bad.validate(len(ref.vertices))
    # a cohort without sites serializes without the key (its JSON as before)
    assert "sites" not in replace(lm, sites={}).to_dict()


def test_the_lumbosacral_joint_hangs_on_the_s1_plate_in_the_deck_and_moves_with_the_potted_s1(real_template):
    from spinecohort.fe.connections import sacrum_nodes
    from spinecohort.fe.export import check_deck, fe_model
    from spinecohort.rom.submodel import extract_rom_model

    t = real_template
    n2 = len(t.grid.nodes)
    sacrum = sacrum_nodes(t)
    # L5-S1's joints: IAP tips on L5's arch, SAP tips on the sacrum's skin
    l5s1 = facet_pairs(t)[np.isin(facet_pairs(t)[:, 1], sacrum)]
    assert len(l5s1) == 2 and not np.isin(l5s1[:, 0], sacrum).any()
    # the exported deck is one body (the connectivity check from the fixed pelvis); the L5-S1 struts' sacral nodes
    # hang on the S1 plate (the column's bottom node layer) and so do the sacrum's ligament ends
    fe = fe_model(t)
    check_deck(fe, "real template")

    def plate_partners(elset):  # attached node -> how many S1 plate nodes its springs reach (a truss, 0..n2-1)
        pairs = fe.element_blocks["CONNECTORS"][1][_rows(fe, elset)]
        on_plate = pairs[pairs[:, 1] < n2]
        return dict(zip(*np.unique(on_plate[:, 0], return_counts=True)))

    facet_nodes_s1 = plate_partners("CONN_FACET_S1")
    # 2 joints x (4 struts + 1 stop), each strut's lower node tied to every plate node
    assert len(facet_nodes_s1) == 10 and set(facet_nodes_s1.values()) == {n2}
    lig_ends = np.intersect1d(t.ligaments, sacrum)
    assert len(lig_ends) == 2 * 3 + 2 * 4 + 2  # LF 3 and CL 4 fibres a side, ISL and SSL
    sacrum_tied = plate_partners("CONN_SACRUM")
    assert all(sacrum_tied.get(int(v)) == n2 for v in lig_ends)
    # the L5-S1 unit: its posterior ligaments and both joints (a strut each, 4 per joint, and a stop), every
    # sacral node in the fixed set with the S1 plate
    m = extract_rom_model(t, t.nodes, "L5", "S1", facets=FacetContact())
    g = m.ligament_groups
    assert (g["LF"], g["CL"], g["ISL"], g["SSL"], g["FACET"], g["FACET_TIP"]) == (6, 8, 1, 1, 2, 2)
    assert "ITL" not in g
    sacral_model_nodes = np.flatnonzero(np.isin(m.source_nodes, sacrum))
    assert len(sacral_model_nodes) == len(np.union1d(lig_ends, l5s1[:, 1]))
    assert np.isin(sacral_model_nodes, m.fixed_nodes).all()
    etype, struts = m.fe.element_blocks["FACETS"]
    lower = struts[:, 0]  # node 1 of every strut: its lower side; L5-S1's on S1, all of them fixed
    assert np.isin(lower, m.fixed_nodes).all() and not np.isin(struts[:, 1], m.fixed_nodes).any()


def _rows(fe, elset: str) -> np.ndarray:
    """Rows of the CONNECTORS block of an element set (its element indices are global, the block's first)."""
    first = sum(len(c) for name, (_, c) in fe.element_blocks.items() if name in _before(fe, "CONNECTORS"))
    return fe.element_sets[elset] - first


def _before(fe, block: str) -> list[str]:
    names = list(fe.element_blocks)
    return names[: names.index(block)]
