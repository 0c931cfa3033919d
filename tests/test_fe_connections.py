"""Tests of spinecohort.fe.connections and spinecohort.fe.connectivity: every deck the project exports is one
mechanical body (each posterior arch on its vertebral body, the sacrum on the S1 plate, the pelvis on the
sacrum, the femoral heads on the pelvis, the annulus C3D8R with its fibre springs tied inside it, the nucleus C3D20R tied to
its neighbours), checked by graph reachability from the fixed
pelvis; a part held only by tension-only springs is reported by name."""

import shutil
from dataclasses import replace

import numpy as np
import pytest

from spinecohort.fe.connections import CONNECTOR_TABLE, posterior_wall, skin_pieces, spread_nodes, truss_pairs
from spinecohort.fe.connectivity import ConnectivityError, check_connected, unreachable_report
from spinecohort.fe.export import check_deck, fe_model, write_deck
from spinecohort.fe.materials import DEFAULT_MATERIALS
from spinecohort.fe.quadratic import HEX20_EDGES, quadratic_hexes


def test_truss_pairs_join_every_attachment_node_to_every_target_and_to_each_other():
    pairs = truss_pairs(np.array([1, 2, 3]), np.array([10, 11]))
    # 3 x 2 attachment-target springs, then the 3 choose 2 = 3 springs between the attachment nodes
    assert pairs.tolist() == [[1, 10], [1, 11], [2, 10], [2, 11], [3, 10], [3, 11], [1, 2], [1, 3], [2, 3]]


def test_spread_nodes_are_three_non_collinear_nodes_of_the_piece(template):
    for piece in skin_pieces(template, "POST_L3"):
        ids = spread_nodes(template.nodes, piece, template.nodes[posterior_wall(template, "L3")].mean(0))
        assert len(ids) == 3 and np.isin(ids, piece).all()
        a, b, c = template.nodes[ids]
        # the triangle they span has a real area (mm^2): non-collinear, so the three fix the piece
        assert np.linalg.norm(np.cross(b - a, c - a)) / 2 > 1.0


def test_the_exported_deck_is_one_body_and_without_connectors_it_is_not(template):
    fe = fe_model(template)
    assert unreachable_report(fe, fe.node_sets["PELVIS"]) == {}
    # every bony skin is attached: 17 arches, sacrum, pelvis (its 12 pieces), two femoral heads; and the
    # facet-joint nodes of each of the 17 vertebrae (T1-T2 ... L4-L5 joints; none at L5-S1)
    conn = {k for k in fe.element_sets if k.startswith("CONN_")}
    levels = "T1 T2 T3 T4 T5 T6 T7 T8 T9 T10 T11 T12 L1 L2 L3 L4 L5".split()
    assert conn == {f"CONN_ARCH_{v}" for v in levels} | {f"CONN_FACET_{v}" for v in levels} | {
        "CONN_SACRUM",
        "CONN_PELVIS",
        "CONN_FH_L",
        "CONN_FH_R",
    }
    loose = unreachable_report(fe_model(template, connectors=False), fe.node_sets["PELVIS"])
    # the old deck: with the pelvis fixed, only tension-only ligaments hold anything else -- every arch, the
    # sacrum, the femoral heads and the whole hex column float
    assert {f"POST_{v}" for v in ("T1", "L5")} | {"SACRUM", "FH_L", "FH_R", "V_L3_CORE", "D_L4L5_AF"} <= set(loose)
    assert "PELVIS" not in loose and loose["POST_L3"] == len(template.elsets["POST_L3"])


def test_a_part_held_only_by_tension_only_springs_is_reported_by_name(template, tmp_path):
    fe = fe_model(template)
    slack = ((0.0, -10.0), (0.0, 0.0), (1000.0, 1.0))  # force 0 for any shortening: a ligament-like table
    fe.sections = [replace(s, spring_force_elongation=slack) if s.elset == "CONN_ARCH_L3" else s for s in fe.sections]
    report = unreachable_report(fe, fe.node_sets["PELVIS"])
    # L3's skin (every triangle) and the 16 ligaments with an end on L3's arch, named by their segment's set
    # (L2-L3 above, L3-L4 below): SSL, ISL 1 each, LF, CL, ITL 2 each (left and right)
    per_segment = {"SSL": 1, "ISL": 1, "LF": 2, "CL": 2, "ITL": 2}
    assert report == {
        "POST_L3": len(template.elsets["POST_L3"]),
        **{f"LIG_{g}_{seg}": n for g, n in per_segment.items() for seg in ("L2L3", "L3L4")},
        "CONN_ARCH_L3": len(fe.element_sets["CONN_ARCH_L3"]),
    }
    deck = tmp_path / "model_00013.inp"
    with pytest.raises(ConnectivityError, match=r"deck .*model_00013\.inp: .*POST_L3 \(\d+ elements\)"):
        write_deck(fe, deck)
    assert not deck.exists()  # nothing written
    # a coupling (e.g. a *RIGID BODY of the arch and the body's wall) joins it again
    arch = np.unique(template.tris[template.elsets["POST_L3"]])
    check_connected(fe, fe.node_sets["PELVIS"], "x", couplings=[np.concatenate([arch, posterior_wall(template, "L3")])])


def test_the_exported_deck_carries_the_facet_joints_the_rom_analysis_validates(template):
    from spinecohort.fe.facets import FacetContact, facet_nodes, facet_pairs
    from spinecohort.rom.submodel import extract_rom_model

    mats = replace(DEFAULT_MATERIALS, facets=replace(FacetContact(), tip_clearance_mm=1.0))
    fe = fe_model(template, materials=mats)
    n = template.n_nodes
    etype, gaps = fe.element_blocks["FACETS"]
    # 16 segments x 2 sides, a joint gap and an extension stop each, as 20 mm compression-only struts; the new
    # nodes come after the template's
    # (then the quadratic nucleus' midside nodes, one per distinct nucleus edge, then the fibre springs' ends)
    n_mid = len(quadratic_hexes(template.nodes, fe.element_blocks["HEXES_NP"][1][:, :8])[0])
    n_fib = 2 * len(fe.element_blocks["FIBRES"][1])
    assert etype == "SPRINGA" and len(gaps) == 64 and len(fe.nodes) == n + 128 + n_mid + n_fib and gaps.min() >= n
    assert gaps.max() < n + 128
    np.testing.assert_array_equal(fe.nodes[:n], template.nodes)
    # each strut runs from its lower node to its upper one along the contact direction, 20 mm long
    direction = np.array(
        [g[1] for g, _ in facet_nodes(template, template.nodes, facet_pairs(template), mats.facets).sections]
    )
    np.testing.assert_allclose(fe.nodes[gaps[:, 1]] - fe.nodes[gaps[:, 0]], 20.0 * direction, atol=1e-9)
    # the struts the exported deck and the ROM sub-model of L2-L4 define for the same joints are the same
    sec = {s.elset: s.spring_force_elongation for s in fe.sections if s.elset.startswith("FACET_")}
    rom = extract_rom_model(template, template.nodes, "L2", "L4", materials=mats, facets=mats.facets)
    rom_sec = {s.elset: s.spring_force_elongation for s in rom.fe.sections if s.elset.startswith("FACET_")}
    assert len(sec) == 64 and len(rom_sec) == 8 and all(sec[k] == v for k, v in rom_sec.items())
    # the GAPUNI variant: coincident node pairs with the same directions
    gap = fe_model(template, materials=replace(mats, facets=replace(mats.facets, strut_length_mm=None)))
    etype, pairs = gap.element_blocks["FACETS"]
    assert etype == "GAPUNI"
    np.testing.assert_allclose(gap.nodes[pairs[:, 0]], gap.nodes[pairs[:, 1]], atol=1e-12)
    assert [tuple(s.gap[1]) for s in gap.sections if s.gap is not None] == [tuple(d) for d in direction]
    # and the deck without facets has none
    bare = fe_model(template, materials=replace(DEFAULT_MATERIALS, facets=None))
    assert "FACETS" not in bare.element_blocks and len(bare.nodes) == n + n_mid + n_fib


def test_exported_disc_is_c3d8r_annulus_and_c3d20r_nucleus_tied_to_its_neighbours(template):
    fe = fe_model(template)
    (t_hex, hexes), (t_af, af), (t_np, nuc) = (fe.element_blocks[b] for b in ("HEXES", "HEXES_DISC", "HEXES_NP"))
    n_af = sum(len(v) for k, v in template.elsets.items() if k.endswith("_AF"))
    n_np = sum(len(v) for k, v in template.elsets.items() if k.endswith("_NP"))
    assert (t_hex, t_af, t_np) == ("C3D8", "C3D8R", "C3D20R") and (len(af), len(nuc)) == (n_af, n_np)
    assert len(hexes) + n_af + n_np == len(template.hexes)
    # every midside node sits at its edge's midpoint; the ones on an edge of a linear neighbour (cartilage
    # endplate, annulus) are tied to it
    corners = fe.nodes[nuc[:, :8]][:, HEX20_EDGES].mean(axis=2)
    np.testing.assert_allclose(fe.nodes[nuc[:, 8:]], corners, atol=1e-12)
    ties = fe.midside_ties
    assert (
        len(ties) and np.isin(ties[:, 1:], np.concatenate([hexes, af])).all() and np.isin(ties[:, 0], nuc[:, 8:]).all()
    )
    np.testing.assert_allclose(fe.nodes[ties[:, 0]], fe.nodes[ties[:, 1:]].mean(axis=1), atol=1e-12)
    both = np.concatenate([hexes, af, nuc[:, :8]])
    for name, kind in template.elset_kind.items():
        if kind == "hex":  # the same elements under the same set name, in the new numbering
            np.testing.assert_array_equal(
                np.sort(both[fe.element_sets[name]], axis=0), np.sort(template.hexes[template.elsets[name]], axis=0)
            )
    # connectors are linear (stiff in compression too); ligaments one table per group and segment: tension-only
    # where slack in the neutral posture (the thoracic PLL's bilinear law, the lumbar PLL's slack curve), the
    # lumbar ALL taut (Remus et al. 2021: it gives back its neutral tension when it shortens)
    sec = {s.elset: s for s in fe.sections}
    assert sec["CONN_SACRUM"].spring_force_elongation == CONNECTOR_TABLE
    assert "LIG_PLL" in fe.element_sets and "LIG_PLL" not in sec  # the union, without a section of its own
    assert sec["LIG_PLL_T6T7"].spring_force_elongation[0][0] == 0.0
    assert sec["LIG_PLL_L3L4"].spring_force_elongation[0][0] == 0.0
    assert sec["LIG_ALL_L3L4"].spring_force_elongation[0][0] < 0.0


HAS_CCX = shutil.which("ccx") is not None
needs_ccx = pytest.mark.skipif(not HAS_CCX, reason="CalculiX 'ccx' not installed (Debian package calculix-ccx)")


@needs_ccx
def test_the_exported_deck_solves_under_a_pure_moment(template, tmp_path):
    # The deck as `export` writes it (the test config's coarse model: 23,028 nodes, 64,598 elements; ccx
    # expands the S3 skins to 108,447 equations), plus a load step written here: pelvis fixed, T1's body rigid,
    # 6.25 N.mm flexion in one NLGEOM increment with the ROM's convergence controls (the full 7.5 N.m is far too
    # long for CI).  With the facet contacts a 25 N.mm first increment diverges after 21 iterations; 6.25 N.mm
    # converges in 4-6 (one increment: ~1 min).  Without the connectors this deck diverges (displacement
    # increments ~1e15 mm).
    from spinecohort.fe.calculix import run_ccx
    from spinecohort.fe.facets import vertebra_frame
    from spinecohort.fe.writers import format_id_list

    fe = fe_model(template)
    deck = write_deck(fe, tmp_path / "model.inp")
    n, n2 = len(fe.nodes), len(template.grid.nodes)
    t1 = np.concatenate([fe.node_sets["EP_INF_T1"], fe.node_sets["EP_SUP_T1"]])
    body = np.arange(t1.min(), t1.max() + 1)  # T1's node layers, inferior to superior endplate
    assert len(body) % n2 == 0
    c = fe.nodes[body].mean(0)
    frame, _ = vertebra_frame(template, fe.nodes, "T1")
    m = -6.25 * frame[:, 0]  # flexion: a negative moment about the lateral (right) axis, N.mm
    step = (
        f"*NODE, NSET=RBN\n{n + 1}, {c[0]}, {c[1]}, {c[2]}\n{n + 2}, {c[0]}, {c[1]}, {c[2]}\n"
        f"*NSET, NSET=TOP\n{format_id_list(body + 1)}*RIGID BODY, NSET=TOP, REF NODE={n + 1}, ROT NODE={n + 2}\n"
        "*BOUNDARY\nPELVIS, 1, 3\n*STEP, NLGEOM, INC=20\n*STATIC\n1.0, 1.0, 0.01, 1.0\n"
        "*CONTROLS, PARAMETERS=TIME INCREMENTATION\n20, 30, 9, 200, 10, 4, , 20\n"
        "*CONTROLS, PARAMETERS=FIELD\n0.005, 0.01, 0.01, 500.0, 0.02, 1e-5, 1e-3, 1e-8\n"
        f"*CLOAD\n{n + 2}, 1, {m[0]}\n{n + 2}, 2, {m[1]}\n{n + 2}, 3, {m[2]}\n"
        f"*NODE PRINT, NSET=RBN\nU\n*NODE PRINT, NSET=NALL\nU\n*END STEP\n"
    )
    deck.write_text(deck.read_text() + step)
    res = run_ccx(deck, tmp_path, threads=2, timeout_s=600)
    last = {b.node_set.upper(): b for b in res.node_prints if b.time == 1.0}
    u = last["NALL"].values
    assert u.shape == (n, 3) and np.isfinite(u).all()
    assert np.abs(u).max() < 15.0  # mm: T1 turns about a centre ~400 mm above the pelvis by < 2 deg
    rot = last["RBN"].values[1]  # the ROT NODE: rotation vector (rad)
    flex = -np.degrees(rot @ frame[:, 0])
    # at 6.25 N.mm (1/1200 of the in-vitro load) the 17 discs in series give some tenths of a degree (measured
    # 0.21 deg; 0.64 at 25 N.mm, 2.03 at 0.1 N.m: the ligaments' toe makes the first newton-millimetres the
    # softest); 0.6 deg would mean several hundred degrees T1-S1 at 7.5 N.m: a loose part or a mechanism
    assert 0.006 < flex < 0.6, flex
    # the test mean is nearly left-right symmetric: little coupled lateral bending or axial rotation
    assert np.degrees(np.abs(rot @ frame[:, 1:])).max() < 0.25 * flex


def test_the_export_load_deck_takes_a_25_nmm_flexion_increment_in_one(template, tmp_path):
    # The load deck exactly as `export --load` writes it (arches without their S3 skins, `arch_skin_free`), its
    # first increment (25 N.mm) as the whole step: ccx must converge without a cutback (INC=1).  With the arch
    # skins this increment diverged after 21 iterations and ccx cut it to 6.25 N.mm; without them it converges
    # in ~7 (docs/explanation/fe-model.md "Loading the whole model"; ~1 min).
    from spinecohort.fe.calculix import run_ccx
    from spinecohort.fe.facets import vertebra_frame
    from spinecohort.fe.pure_moment import model_load_text

    fe = fe_model(template)
    one = dict(initial_increment=1.0, max_increment=1.0, max_increments=1)
    deck = tmp_path / "flex.inp"
    deck.write_text(model_load_text(fe, template, "flexion", "T1", 25.0, node_file=False, **one))
    res = run_ccx(deck, tmp_path, threads=2, timeout_s=900)
    rot = [b for b in res.node_prints if b.node_set.upper() == "ROTTOP"]
    assert [b.time for b in rot] == [1.0]
    r = rot[0].values[0]  # the ROT NODE's rotation vector (rad)
    frame, _ = vertebra_frame(template, fe.nodes, "T1")
    flex = -np.degrees(r @ frame[:, 0])
    # 25 N.mm = 1/300 of the in-vitro load: the 17 discs in series, softest at the start, give under a degree
    # (0.85 deg on the test config's pipeline mean); 2.4 deg would mean several hundred
    # degrees T1-S1 at 7.5 N.m: a loose part or a mechanism
    assert 0.025 < flex < 2.4, flex
    assert np.degrees(np.abs(r @ frame[:, 1:])).max() < 0.25 * flex  # nearly symmetric: little coupling
    # T1 is a rigid body in equilibrium: the forces its nodes pass to the spine add up to the load, 25 N.mm about
    # the deck's load axis and nothing across it or as a net force (to ccx's residual, < 0.5 % of 500 N)
    from spinecohort.fe.pure_moment import load_axis
    from spinecohort.rom.reaction import moment_on_top

    text = deck.read_text()
    # the model deck's nucleus is C3D20R; the load deck's fully integrated (`fully_integrated_nucleus`)
    assert "*ELEMENT, TYPE=C3D20, ELSET=HEXES_NP\n" in text and "TYPE=C3D20R" not in text
    axis = load_axis(text)
    np.testing.assert_allclose(axis, -frame[:, 0], atol=1e-8)  # flexion: about T1's -x
    top = moment_on_top(text, res.node_prints)[-1]
    assert top.time == 1.0 and top.moment_nmm @ axis == pytest.approx(25.0, rel=1e-3)
    assert np.linalg.norm(top.moment_nmm - (top.moment_nmm @ axis) * axis) < 0.25  # 1 % of the load
    assert np.linalg.norm(top.force_n) < 0.01


def test_a_guided_export_load_deck_turns_its_top_about_the_load_axis_only(template, tmp_path):
    # `export --load extension --guided`: two *EQUATIONs keep T1's rotation vector on the moment's axis (the
    # validation's lumbar model is loaded so); its first 25 N.mm increment converges as the whole step
    from spinecohort.fe.calculix import run_ccx
    from spinecohort.fe.facets import vertebra_frame
    from spinecohort.fe.pure_moment import load_axis, model_load_text
    from spinecohort.rom.reaction import moment_on_top

    fe = fe_model(template)
    one = dict(initial_increment=1.0, max_increment=1.0, max_increments=1)
    text = model_load_text(fe, template, "extension", "T1", 25.0, node_file=False, guided=True, **one)
    # one generalised moment on the loaded rotation, where the free deck puts all three components
    assert len(text.split("*CLOAD\n")[1].split("*")[0].splitlines()) == 1
    assert "turning about the load's axis only" in text
    deck = tmp_path / "ext.inp"
    deck.write_text(text)
    res = run_ccx(deck, tmp_path, threads=2, timeout_s=900)
    rot = [b for b in res.node_prints if b.node_set.upper() == "ROTTOP"]
    assert [b.time for b in rot] == [1.0]
    r = rot[0].values[0]
    axis = vertebra_frame(template, fe.nodes, "T1")[0][:, 0]  # extension: +x of T1's frame
    np.testing.assert_allclose(load_axis(text), axis, atol=1e-8)
    ext = np.degrees(r @ axis)
    assert 0.025 < ext < 2.4, ext  # as the free flexion increment above, by the same argument
    # off the axis: what the deck prints (6 significant digits) leaves of the constraint
    assert np.linalg.norm(np.cross(r, axis)) < 1e-5 * np.linalg.norm(r)
    # the generalised moment on one rotation component does the work of 25 N.mm about the axis: T1 passes the
    # load to the spine, plus what the guide holds across the axis (the nearly symmetric mean couples little)
    top = moment_on_top(text, res.node_prints)[-1]
    assert top.moment_nmm @ axis == pytest.approx(25.0, rel=1e-3)
    assert np.linalg.norm(top.moment_nmm - (top.moment_nmm @ axis) * axis) < 0.25 * 25.0


def test_the_export_load_deck_puts_the_moment_on_the_top_and_fixes_the_pelvis(template):
    import re

    from spinecohort.fe.facets import vertebra_frame
    from spinecohort.fe.pure_moment import load_axis, model_load_text

    fe = fe_model(template)
    n = len(fe.nodes)
    text = model_load_text(fe, template, "lateral_right", "L1", 7500.0)
    # REF and ROT NODE right after the mesh (ccx allocates memory by the largest node id)
    assert f"*RIGID BODY, NSET=RB_L1, REF NODE={n + 1}, ROT NODE={n + 2}\n" in text
    assert "*NSET, NSET=FIXED\n" in text and "*BOUNDARY\nFIXED, 1, 3\n" in text
    # a first increment of 25 N.mm = 1/300 of the load, at most 5 % (the whole spine turns far more than one unit)
    assert (
        "*STEP, NLGEOM, INC=1000\n" in text
        and "\n0.0033333333333333335, 1.0, 1e-05, 0.05\n" in text
        and "*CONTROLS, PARAMETERS=TIME INCREMENTATION\n" in text
    )
    # the top's rotation, its rigid nodes' positions and forces (their moment is the one on the spine: the pelvis's
    # shell nodes print zero reactions) and the displacement field for a viewer
    prints = "*NODE PRINT, NSET=RB_L1\nU\n*NODE PRINT, NSET=RB_L1\nRF\n"
    assert f"*NODE PRINT, NSET=ROTTOP\nU\n{prints}*NODE FILE\nU\n*END STEP\n" in text
    # the fixed set is the pelvis; the moment is 7.5 N.m about L1's anterior axis (right lateral bending)
    fixed = text.split("*NSET, NSET=FIXED\n")[1].split("*")[0]
    assert sorted(int(i) for i in re.split(r"[,\s]+", fixed.strip())) == (fe.node_sets["PELVIS"] + 1).tolist()
    cload = text.split("*CLOAD\n")[1].split("*")[0].splitlines()
    m = np.array([float(line.split(",")[2]) for line in cload])
    assert all(line.startswith(f"{n + 2}, ") for line in cload)
    np.testing.assert_allclose(m, 7500.0 * vertebra_frame(template, fe.nodes, "L1")[0][:, 1], atol=1e-5)
    np.testing.assert_allclose(7500.0 * load_axis(text), m, atol=1e-5)  # the axis a reader of the deck finds
    # the arches act through their connector trusses, as in the ROM sub-models: their S3 skins are left out (they
    # made ccx's Newton iterations cycle), the pelvis, sacrum and femoral heads keep theirs, and it is one body
    from spinecohort.fe.pure_moment import arch_skin_free

    loaded = arch_skin_free(fe)
    arch = np.concatenate([idx for name, idx in fe.element_sets.items() if name.startswith("POST_")])
    kept = len(fe.element_blocks["SURFACES"][1]) - len(np.unique(arch))
    assert len(loaded.element_blocks["SURFACES"][1]) == kept > 0
    assert not any(name.startswith("POST_") for name in loaded.element_sets)
    assert "*ELEMENT, TYPE=S3, ELSET=SURFACES\n" in text and text.count("*SHELL SECTION") == len(
        [s for s in loaded.sections if s.thickness_mm]
    )
    check_deck(loaded, "load deck")  # raises ConnectivityError if a part hung only on the skins
    with pytest.raises(ValueError, match="unknown load case"):
        model_load_text(fe, template, "twist", "T1")
    with pytest.raises(ValueError, match="top vertebra 'S1'"):
        model_load_text(fe, template, "flexion", "S1")
