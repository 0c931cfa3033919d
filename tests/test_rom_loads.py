"""Nucleus pressure and facet-strut forces read from a ccx run (`spinecohort.rom.loads`), against closed forms and
ccx's own reactions on tiny decks (each solves in well under a second)."""

import shutil

import numpy as np
import pandas as pd
import pytest

from spinecohort.fe.abaqus import FEModel, LinearElastic, Section
from spinecohort.fe.calculix import NodePrint, run_ccx
from spinecohort.fe.facets import strut_table
from spinecohort.fe.quadratic import quadratic_hexes
from spinecohort.fe.writers import model_to_inp_text
from spinecohort.rom.loads import (
    element_pressure,
    facet_forces,
    facet_struts,
    nucleus_pressure,
    nucleus_sets,
    with_load_prints,
)
from spinecohort.testing import hex_grid

needs_ccx = pytest.mark.skipif(shutil.which("ccx") is None, reason="CalculiX 'ccx' not installed")


def _step(body: str) -> str:
    return f"*STEP\n*STATIC\n{body}*END STEP\n"


@needs_ccx
@pytest.mark.parametrize("etype", ["C3D20R", "C3D20"])
def test_nucleus_pressure_of_a_confined_two_layer_block_is_the_volume_weighted_closed_form(tmp_path, etype):
    # A 10 x 10 mm column of two 20-node layers (the model's C3D20R; C3D20, the load deck's), 4 mm (nu 0.49,
    # nucleus-like) under 6 mm (nu 0.3), rollers on every side and the bottom, 0.5 MPa on top (linear, confined
    # compression): in each layer sigma_zz = -q and sigma_xx = sigma_yy = -q nu / (1 - nu), so p = q (1 + nu) / (3
    # (1 - nu)): 0.48693 and 0.30952 MPa. Volume-weighted over the set: (4 * 0.48693 + 6 * 0.30952) / 10 = 0.38048
    # MPa (a plain mean of the two elements would give 0.39822).
    q = 0.5
    nodes, hexes = hex_grid([0.0, 10.0], [0.0, 10.0], [0.0, 4.0, 10.0])
    mid, hex20, _ = quadratic_hexes(nodes, hexes)
    pts = np.concatenate([nodes, mid])
    fe = FEModel(
        pts,
        {"NP": (etype, hex20)},
        element_sets={"LOWER": np.array([0]), "UPPER": np.array([1]), "D_L4L5_NP": np.array([0, 1])},
        materials=[LinearElastic("SOFT", 1.0, 0.49), LinearElastic("FIRM", 1.0, 0.3)],
        sections=[Section("LOWER", material="SOFT"), Section("UPPER", material="FIRM")],
    )
    bc = "".join(
        f"*NSET, NSET=B{d}{e}\n" + ", ".join(str(i + 1) for i in np.flatnonzero(np.isclose(pts[:, d], v))) + "\n"
        for d, vals in enumerate(([0.0, 10.0], [0.0, 10.0], [0.0]))
        for e, v in enumerate(vals)
    )
    bc += "*BOUNDARY\nB00, 1, 1\nB01, 1, 1\nB10, 2, 2\nB11, 2, 2\nB20, 3, 3\n"
    deck = tmp_path / "np.inp"
    deck.write_text(with_load_prints(model_to_inp_text(fe) + bc + _step(f"*DLOAD\n2, P2, {q}\n"), fe))
    prints = run_ccx(deck, tmp_path).node_prints
    p = [q * (1 + nu) / (3 * (1 - nu)) for nu in (0.49, 0.3)]
    got = nucleus_pressure(fe, prints, 1.0)
    assert nucleus_sets(fe.element_sets) == {"D_L4L5_NP": "L4-L5"}
    assert got["disc"].tolist() == ["L4-L5"] and got["n_elements"].tolist() == [2]
    assert got["volume_mm3"].iloc[0] == pytest.approx(1000.0, rel=1e-6)
    assert got["pressure_mpa"].iloc[0] == pytest.approx((4 * p[0] + 6 * p[1]) / 10, rel=1e-4)
    # at a time with no print the pressure is unknown, not zero
    assert np.isnan(nucleus_pressure(fe, prints, 0.5)["pressure_mpa"].iloc[0])


def _one_element_stresses(element: int, pressure_mpa: np.ndarray) -> NodePrint:
    """An *EL PRINT S block of one element: hydrostatic stress -p at its integration points 1..len(p)."""
    n = len(pressure_mpa)
    values = np.column_stack([np.arange(1, n + 1), -np.repeat(pressure_mpa[:, None], 3, 1), np.zeros((n, 3))])
    return NodePrint(
        "stresses (elem, integ.pnt.,sxx,syy,szz,sxy,sxz,syz)", "D_L4L5_NP", 1.0, np.full(n, element), values
    )


def test_element_pressure_weights_a_fully_integrated_hex_by_its_gauss_rule():
    # C3D20's 27 points are the 3-point Gauss-Legendre rule in each direction (xi = -sqrt(0.6), 0, +sqrt(0.6), the
    # first fastest).  A pressure p = xi^2 over the parent cube has the mean 1/3 (closed form), which the rule
    # integrates exactly; the plain mean of the 27 point values is 0.4.  The 8 points of C3D20R weigh alike.
    xi = np.array([-np.sqrt(0.6), 0.0, np.sqrt(0.6)])
    elems, p = element_pressure(_one_element_stresses(7, np.tile(xi**2, 9)))
    assert elems.tolist() == [7] and p[0] == pytest.approx(1.0 / 3.0, rel=1e-12)
    p8 = np.array([0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8])
    assert element_pressure(_one_element_stresses(3, p8))[1][0] == pytest.approx(0.45, rel=1e-12)


@needs_ccx
def test_strut_force_from_its_nodes_equals_the_reaction_ccx_puts_on_its_fixed_end(tmp_path):
    # The facet strut of `strut_table` (0.5 mm clearance, 1000 N/mm, 20 mm, corner 0.05 mm) 30 deg off the x axis
    # in series with a 10 N/mm spring, 100 N on their shared node 2 along the strut (tests/test_rom.py's strut
    # deck): node 2 moves u = 625 / 1010 = 0.61881 mm, the strut carries 1000 (u - 0.525) = 93.81 N and the spring
    # 6.19 N.  The force read from the printed displacements through the table equals ccx's reaction at the
    # strut's fixed node 1.
    d = np.array([np.cos(np.radians(30.0)), np.sin(np.radians(30.0)), 0.0])
    fe = FEModel(
        np.array([[0.0, 0, 0], 20.0 * d, 30.0 * d]),
        {"FACETS": ("SPRINGA", np.array([[0, 1]])), "S": ("SPRINGA", np.array([[1, 2]]))},
        element_sets={"FACET_L4L5_R": np.array([0])},
        sections=[
            Section("FACET_L4L5_R", spring_force_elongation=strut_table(0.5, 1000.0, 20.0)),
            Section("S", spring_force_elongation=((-100.0, -10.0), (100.0, 10.0))),
        ],
    )
    deck = tmp_path / "strut.inp"
    deck.write_text(
        with_load_prints(
            model_to_inp_text(fe)
            + f"*NSET, NSET=N1\n1\n*NSET, NSET=N2\n2\n*TRANSFORM, NSET=N2, TYPE=R\n{d[0]}, {d[1]}, 0., {-d[1]}, {d[0]}, 0.\n"
            "*BOUNDARY\n1, 1, 3\n3, 1, 3\n2, 2, 3\n*STEP, NLGEOM\n*STATIC\n0.1, 1.0, 1e-5, 0.1\n*CLOAD\n2, 1, -100.\n"
            "*NODE PRINT, NSET=N1\nRF\n*END STEP\n",
            fe,
        )
    )
    prints = run_ccx(deck, tmp_path).node_prints
    got = facet_forces(fe, prints, 1.0)
    assert got[["joint", "side", "kind", "n_struts"]].values.tolist() == [["L4-L5", "R", "joint", 1]]
    rf = [b for b in prints if b.node_set == "N1" and b.time == 1.0][-1].values[0]
    assert got["force_n"].iloc[0] == pytest.approx(np.linalg.norm(rf), rel=1e-4)
    assert got["force_n"].iloc[0] == pytest.approx(1000.0 * (625.0 / 1010.0 - 0.525), rel=1e-3)


def test_struts_are_summed_by_joint_from_their_set_names_one_or_several_a_joint():
    # one strut on the left, two on the right (FACET_<up><lo>_<side><k>, as spinecohort.fe.facets names a joint's
    # struts), an extension stop: the right joint's
    # force is the sum of its two struts'; each strut is 10 mm long with 1 N/mm past no clearance
    table = ((-10.0, -10.0), (0.0, 0.0), (0.0, 10.0))
    nodes = np.array([[0.0, 0, 0], [0, 0, 10], [5, 0, 0], [5, 0, 10], [9, 0, 0], [9, 0, 10], [0, 5, 0], [0, 5, 10]])
    names = ["FACET_L4L5_L", "FACET_L4L5_R1", "FACET_L4L5_R2", "FACET_TIP_L4L5_L"]
    fe = FEModel(
        nodes,
        {"FACETS": ("SPRINGA", np.array([[0, 1], [2, 3], [4, 5], [6, 7]]))},
        element_sets={n: np.array([i]) for i, n in enumerate(names)} | {"LIG_CL_1": np.array([0])},
        sections=[Section(n, spring_force_elongation=table) for n in names],
    )
    assert facet_struts(fe)["kind"].tolist() == ["joint", "joint", "joint", "tip"]
    # the upper nodes come down 1, 2, 3 and 0.5 mm: compression 1, 2 + 3, 0.5 N
    u = np.zeros((8, 3))
    u[[1, 3, 5, 7], 2] = [-1.0, -2.0, -3.0, -0.5]
    block = NodePrint("displacements (vx,vy,vz)", "FACETNODES", 1.0, np.arange(1, 9), u)
    got = facet_forces(fe, [block], 1.0).set_index(["side", "kind"])
    assert got.loc[("L", "joint"), "force_n"] == pytest.approx(1.0)
    assert got.loc[("R", "joint"), "force_n"] == pytest.approx(5.0) and got.loc[("R", "joint"), "n_struts"] == 2
    assert got.loc[("L", "tip"), "force_n"] == pytest.approx(0.5)
    # no print at the time asked: unknown, not zero
    assert facet_forces(fe, [block], 0.5)["force_n"].isna().all()
    assert isinstance(facet_forces(FEModel(nodes, {}), [block], 1.0), pd.DataFrame)


@needs_ccx
def test_a_unit_presses_its_nucleus_in_flexion_and_its_contralateral_facet_in_axial_rotation(template, tmp_path):
    # Physics of the test-config mean's L3-L4 unit under 7.5 N.m (two nonlinear cases, ~10 s each): flexion
    # squeezes the disc's front and opens the facet joints behind it (no contact force, nucleus pressure up);
    # left axial rotation swings the posterior arch to the right, pressing the right (contralateral) inferior
    # articular process onto the superior one below, the left joint carrying nothing (Jaumard et al. 2011,
    # T12-L2: contralateral 70 N > ipsilateral 31 N)
    from spinecohort.fe.facets import FacetContact
    from spinecohort.rom.run import Settings, run_case
    from spinecohort.rom.submodel import extract_rom_model

    m = extract_rom_model(template, template.nodes, "L3", "L4", facets=FacetContact())
    flex = run_case(m, "flexion", tmp_path, **Settings().deck_kw())
    turn = run_case(m, "axial_left", tmp_path, **Settings().deck_kw())
    assert flex.load_fraction == 1.0 and turn.load_fraction == 1.0
    assert flex.idp["disc"].tolist() == ["L3-L4"] and flex.idp["pressure_mpa"].iloc[0] > 0.05
    assert (flex.facets["force_n"] == 0.0).all()
    f = turn.facets.set_index(["side", "kind"])["force_n"]
    assert f["R", "joint"] > 50.0 and f["L", "joint"] == 0.0
