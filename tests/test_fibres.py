"""Tests of spinecohort.fe.fibres: the annulus fibres as tension-only springs embedded in the annulus hexes.

The physics checked: the embedded segment measures the hex's fibre stretch exactly under any homogeneous
deformation (trilinear interpolation reproduces affine maps); a spring stores the Holzapfel-Gasser-Ogden fibre
energy of its hex's volume (closed form); and in ccx one hex with spring fibres gives the same reaction as the
same hex with ccx's own ELASTIC_FIBER law under an isochoric stretch (where the law's isochoric I4 is the total
one), so the calibrated k1, k2 and angle keep their meaning."""

import shutil

import numpy as np
import pytest

from spinecohort.fe.abaqus import FEModel, NeoHooke, Orientation, Section, UserMaterial
from spinecohort.fe.fibres import (
    BIN_RATIO,
    HEX8_NATURAL,
    embedded_fibres,
    embedded_segments,
    fibre_directions,
    fibre_force_n,
    fibre_table,
    trilinear_weights,
)
from spinecohort.fe.writers import model_to_inp_text
from spinecohort.mesh.quality.verdict import hex_volumes

needs_ccx = pytest.mark.skipif(shutil.which("ccx") is None, reason="CalculiX 'ccx' not installed")


def _distorted_hex(seed=0):
    rng = np.random.default_rng(seed)
    return (HEX8_NATURAL * [3.0, 2.0, 1.5] + rng.normal(0, 0.25, (8, 3))) @ np.array(
        [[0.9, 0.1, 0.0], [-0.1, 0.9, 0.2], [0.0, -0.2, 1.0]]
    )


def test_trilinear_weights_are_a_partition_of_unity_and_interpolate_the_corners():
    w = trilinear_weights(HEX8_NATURAL)
    assert np.allclose(w, np.eye(8))
    xi = np.random.default_rng(1).uniform(-1, 1, (50, 3))
    assert np.allclose(trilinear_weights(xi).sum(axis=1), 1.0)


def test_the_segment_measures_the_fibre_stretch_of_any_homogeneous_deformation():
    # trilinear interpolation reproduces affine maps exactly, so under x -> F x + c the segment between the tied
    # ends stretches by |F f| for its reference direction f, whatever the hex's distortion (to round-off)
    corners = _distorted_hex()
    hexes = np.arange(8)[None]
    dirs = fibre_directions(corners.mean(0)[None], np.array([[0.0, -50.0, -5.0]]), np.array([[0.0, -50.0, 5.0]]), 40.0)
    ends, weights, halvings, in_layer = embedded_segments(corners, hexes, dirs, 1.0)
    assert not in_layer.any()  # the disc-axis directions fit: none replaced
    assert np.allclose(np.einsum("efsk,kj->efsj", weights, corners), ends, atol=1e-12)
    seg = ends[0, :, 1] - ends[0, :, 0]
    length = np.linalg.norm(seg, axis=1)
    # first order: the segments have the nominal length (halved for a small hex) and the fibre direction
    assert np.allclose(length, 1.0 / 2.0 ** halvings[0], rtol=1e-3)
    assert np.allclose(seg / length[:, None], dirs[0], atol=1e-3)
    F = np.array([[1.08, 0.03, -0.02], [0.01, 0.95, 0.04], [-0.03, 0.02, 1.02]])
    moved = corners @ F.T + [1.0, -2.0, 0.5]
    seg_moved = np.einsum("fsk,kj->fsj", weights[0], moved)
    stretch = np.linalg.norm(seg_moved[:, 1] - seg_moved[:, 0], axis=1) / length
    assert np.allclose(stretch, np.linalg.norm(seg @ F.T, axis=1) / length, atol=1e-12)


def test_a_fibre_stays_in_the_lamella_of_a_sheared_thin_outer_ring():
    # The outer annulus ring of a disc whose two endplates differ in extent: 0.4 mm thick radially (the 6 % shell
    # ring), 9 mm circumferential, 1 mm high, its top face 2.3 mm further in than its bottom (the T12-L1 ring of the
    # real-anatomy mean, hexes 3188-3191).  Along the disc-axis family (46 deg) half a 1 mm segment climbs
    # sin(46) 0.5 = 0.36 mm, i.e. 0.83 mm radially at constant height: 4.1 in the ring's natural coordinate, too
    # far even at 1/8 mm.  In the ring's lamella (constant radial natural coordinate) the segment fits.
    bottom = np.array([[0.0, 0.0, 0.0], [9.0, 0.0, 0.0], [9.0, 0.4, 0.0], [0.0, 0.4, 0.0]])
    corners = np.concatenate([bottom, bottom + [0.0, -2.3, 1.0]])  # VTK / C3D8 order
    hexes = np.arange(8)[None]
    axis_a, axis_b = np.array([[4.5, 30.0, -5.0]]), np.array([[4.5, 30.0, 5.0]])  # radial -y, circumferential x
    dirs = fibre_directions(corners.mean(0)[None], axis_a, axis_b, 46.0)
    assert np.allclose(np.abs(dirs[0] @ [0.0, 1.0, 0.0]), 0.0)  # the disc-axis family has no radial component
    ends, weights, halvings, in_layer = embedded_segments(corners, hexes, dirs, 1.0)
    assert in_layer.all()
    seg = ends[0, :, 1] - ends[0, :, 0]
    # in the lamella: the ring's radial natural coordinate (xi_2, edge 1 -> 2) is the same at both ends, so the
    # segment is parallel to the sheared wall, whose in-plane directions are x and (0, -2.3, 1)
    wall_normal = np.cross([1.0, 0.0, 0.0], [0.0, -2.3, 1.0])
    assert np.allclose(seg @ wall_normal, 0.0, atol=1e-12)
    assert np.allclose(np.linalg.norm(seg, axis=1), 1.0 / 2.0 ** halvings[0], rtol=1e-12)  # affine hex: exact
    xi = (
        2.0
        * np.linalg.solve(
            np.stack([corners[1] - corners[0], corners[3] - corners[0], corners[4] - corners[0]], 1),
            (ends[0] - corners[0]).reshape(-1, 3).T,
        ).T
        - 1.0
    )
    assert np.abs(xi).max() <= 0.5 + 1e-12  # inside the inner half of the hex
    # the closest in-layer direction: the disc-axis direction minus its component along the wall's normal
    n = wall_normal / np.linalg.norm(wall_normal)
    expected = dirs[0] - np.outer(dirs[0] @ n, n)
    expected /= np.linalg.norm(expected, axis=1, keepdims=True)
    assert np.allclose(seg / np.linalg.norm(seg, axis=1, keepdims=True), expected, atol=1e-12)
    # a hex too thin even in its lamella (0.01 mm high and 0.01 mm long circumferentially) is refused, naming the
    # model's hex id
    needle = bottom * [0.01 / 9.0, 1.0, 1.0]
    flat = np.concatenate([needle, needle + [0.0, 0.0, 0.01]])
    with pytest.raises(ValueError, match="annulus hex 3189 "):
        embedded_segments(flat, hexes, dirs, 1.0, hex_ids=np.array([3189]))


def test_fibre_directions_lie_at_the_angle_in_the_circumferential_axial_plane():
    # disc axis along z through the origin; a hex centred at (10, 0, 0): radial x, circumferential y
    d = fibre_directions(np.array([[10.0, 0.0, 2.0]]), np.zeros((1, 3)), np.array([[0.0, 0.0, 8.0]]), 30.0)[0]
    assert np.allclose(np.abs(d[:, 0]), 0.0)  # no radial component
    assert np.allclose(np.degrees(np.arcsin(d[:, 2])), [30.0, -30.0])  # +-30 deg to the transverse plane
    assert np.allclose(np.linalg.norm(d, axis=1), 1.0)


def test_hex_volume_is_the_exact_volume_of_the_trilinear_hex():
    corners = _distorted_hex(3)
    import pyvista as pv

    grid = pv.UnstructuredGrid(np.r_[8, np.arange(8)], [pv.CellType.HEXAHEDRON], corners)
    assert hex_volumes(corners, np.arange(8)[None])[0] == pytest.approx(
        grid.compute_cell_sizes()["Volume"][0], rel=1e-10
    )


def test_a_fibre_spring_stores_the_fibre_energy_of_its_hex():
    # F = (V/L) dPsi/dlambda, so the work of the spring from L to lambda L is V Psi(lambda), with
    # Psi = k1 / (2 k2) (exp(k2 (lambda^2 - 1)^2) - 1) (HGO); zero force in compression
    k1, k2, volume, length = 1.51, 11.0, 30.0, 0.5
    lam = np.linspace(1.0, 1.12, 2001)
    force = fibre_force_n(lam, k1, k2, volume / length)
    work = np.trapezoid(force, lam * length)
    assert work == pytest.approx(volume * k1 / (2 * k2) * (np.exp(k2 * (1.12**2 - 1) ** 2) - 1), rel=1e-6)
    assert fibre_force_n(np.array([0.9, 1.0]), k1, k2, 10.0).tolist() == [0.0, 0.0]
    table = np.array(fibre_table(k1, k2, volume / length, length))
    assert table[0].tolist() == [0.0, -length] and (np.diff(table[:, 1]) > 0).all()


def test_springs_share_a_table_within_one_bin_of_their_own_force_scale():
    corners = np.concatenate([_distorted_hex(s) + [10.0 * s, 0, 0] for s in range(4)])
    hexes = np.arange(32).reshape(4, 8)
    fib = embedded_fibres(
        corners, hexes, np.tile([0.0, -50, -5], (4, 1)), np.tile([0.0, -50, 5], (4, 1)), 1.51, 11.0, 40.0
    )
    assert len(fib.springs) == 8 and len(fib.points) == 16
    assert np.allclose(np.einsum("pk,pkj->pj", fib.weights, corners[fib.hosts]), fib.points)
    vol = hex_volumes(corners, hexes)
    for s, (a, b) in enumerate(fib.springs):
        table = np.array(fib.tables[fib.group[s]])
        rest = -table[0, 1]
        assert np.linalg.norm(fib.points[b] - fib.points[a]) == pytest.approx(rest, rel=2e-3)
        own = fibre_force_n(np.array([1.05]), 1.51, 11.0, vol[s // 2] / rest)[0]
        shared = np.interp(0.05 * rest, table[:, 1], table[:, 0])  # the bin holds k1 V / L
        assert shared == pytest.approx(own, rel=np.sqrt(BIN_RATIO) - 1 + 1e-3)


@needs_ccx
def test_one_hex_with_spring_fibres_stretches_as_with_ccx_fibre_law(tmp_path):
    # uniaxial tension across the fibres' bisector (x, circumferential): 6 N on the +x face, the -x face held in x;
    # nearly incompressible ground substance (D1 0.005: J - 1 < 0.3 %), where the law's isochoric I4 is the total
    # one and its deviatoric projection is taken up by the pressure, so both models must stretch alike
    from spinecohort.fe.calculix import run_ccx
    from spinecohort.fe.export import add_fibres
    from spinecohort.fe.materials import FEMaterials

    side, d1 = 4.0, 0.005
    corners = HEX8_NATURAL * side / 2
    axis_a, axis_b = np.array([0.0, -500.0, -10.0]), np.array([0.0, -500.0, 10.0])  # circumferential = -x here
    mats = FEMaterials(annulus_d1_per_mpa=d1, fibre_angle_deg=40.0)
    minus, plus = np.flatnonzero(corners[:, 0] < 0) + 1, np.flatnonzero(corners[:, 0] > 0) + 1
    step = "*STEP, NLGEOM, INC=100\n*STATIC\n0.1, 1.0, 0.0001, 0.2\n*BOUNDARY\n" + "".join(
        f"{n}, 1, 1\n" for n in minus
    )
    step += f"{minus[0]}, 2, 3\n{minus[1]}, 3, 3\n{minus[3]}, 2, 2\n*CLOAD\n" + "".join(f"{n}, 1, 1.5\n" for n in plus)
    step += "*NODE PRINT, NSET=PX\nU\n*END STEP\n"
    stretch = {}
    for kind in ("springs", "law"):
        blocks = {"HEX": ("C3D8R", np.arange(8)[None])}
        elsets, sections, ties, orient = {}, [Section("HEX", "AF")], None, []
        pts = corners
        if kind == "springs":
            mat = NeoHooke("AF", mats.annulus_c10_mpa, d1)
            fib = embedded_fibres(
                corners, np.arange(8)[None], axis_a[None], axis_b[None], mats.fibre_k1_mpa, mats.fibre_k2, 40.0
            )
            pts, ties = add_fibres(corners, blocks, elsets, sections, fib)
        else:
            mat = UserMaterial("ELASTIC_FIBER_AF", mats.annulus_constants())
            sections = [Section("HEX", "ELASTIC_FIBER_AF", orientation="OR")]
            orient = [Orientation("OR", tuple(axis_a), tuple(axis_b))]
        fe = FEModel(pts, blocks, {"PX": plus - 1}, elsets, [mat], sections, orientations=orient, embedded_ties=ties)
        deck = tmp_path / f"{kind}.inp"
        deck.write_text(model_to_inp_text(fe) + step)
        res = run_ccx(deck, tmp_path / kind)
        u = [p for p in res.node_prints if p.quantity.startswith("displacements")][-1].values
        stretch[kind] = 1.0 + u[:, 0].mean() / side
    # ground substance alone (Neo-Hooke, mu 0.45 MPa, sigma 6 N / 16 mm^2 = 0.375 MPa): lambda ~ 1.3; the fibres
    # hold it to a few per cent.  Same stretch within 0.3 % of the length (the bins <= 1 % of the fibre force)
    assert 0.01 < stretch["law"] - 1.0 < 0.15  # stretched, far less than the ground substance alone (~0.3)
    assert stretch["springs"] == pytest.approx(stretch["law"], abs=0.003)


def _confined_stress_mpa(c10: float, d1: float, stretch: float, volumetric: str) -> float:
    """Closed form: axial Cauchy stress (MPa) of a Neo-Hooke solid under confined compression F = diag(1, 1, s)
    (J = s): isochoric 2 C10 / J * dev(B_bar)_33 = 2 C10 J^(-5/3) (2/3)(s^2 - 1), plus the pressure dU/dJ,
    2 (J - 1) / D1 (quadratic) or (J - 1/J) / D1 (logarithmic)."""
    j = stretch
    iso = 2.0 * c10 * j ** (-5.0 / 3.0) * (2.0 / 3.0) * (stretch**2 - 1.0)
    vol = 2.0 * (j - 1.0) / d1 if volumetric == "quadratic" else (j - 1.0 / j) / d1
    return iso + vol


@needs_ccx
@pytest.mark.parametrize("volumetric", ["quadratic", "logarithmic"])
def test_the_ground_substance_volume_terms_match_their_closed_forms_in_ccx(tmp_path, volumetric):
    # one unit hex, sides held, top pushed down to 40 % of its height (J = 0.4: the anterior rim hexes of a disc
    # under a flexed vertebra reach ~0.44, docs/explanation/fe-model.md): the axial reaction per unit area is the
    # closed-form stress.  At J = 0.4 the logarithmic term resists 1.45x as much as the quadratic one (4.21 vs
    # 2.90 MPa with the config's C10 0.225, D1 0.688); at small strain the two are the same law
    from spinecohort.fe.calculix import run_ccx

    c10, d1, s = 0.225, 0.688, 0.4
    corners = (HEX8_NATURAL + 1.0) / 2  # unit cube [0, 1]^3
    top = np.flatnonzero(corners[:, 2] > 0.5) + 1
    fe = FEModel(
        corners,
        {"HEX": ("C3D8", np.arange(8)[None])},
        {"TOP": top - 1},
        {},
        [NeoHooke("AF", c10, d1, volumetric)],
        [Section("HEX", "AF")],
    )
    step = "*BOUNDARY\nNALL, 1, 2\n" + "".join(f"{n}, 3, 3\n" for n in np.flatnonzero(corners[:, 2] < 0.5) + 1)
    step += "*STEP, NLGEOM, INC=200\n*STATIC\n0.05, 1.0, 1e-5, 0.05\n*BOUNDARY\n"
    step += f"TOP, 3, 3, {s - 1.0}\n*NODE PRINT, NSET=TOP, TOTALS=ONLY\nRF\n*END STEP\n"
    deck = tmp_path / "cube.inp"
    deck.write_text(model_to_inp_text(fe) + step)
    # every degree of freedom is prescribed (a strain-driven check), which ccx notes as a warning
    res = run_ccx(deck, tmp_path / "out", allowed_warnings=("no degrees of freedom",))
    rf = [p for p in res.node_prints if p.quantity.startswith("total force")][-1].values
    expected = _confined_stress_mpa(c10, d1, s, volumetric)  # current area 1 mm^2 (sides held)
    assert float(np.ravel(rf)[2]) == pytest.approx(expected, rel=2e-3)
    assert _confined_stress_mpa(c10, d1, s, "logarithmic") / _confined_stress_mpa(c10, d1, s, "quadratic") > 1.4
    # near J = 1 the two are the same law (initial bulk modulus 2 / D1 either way)
    assert _confined_stress_mpa(c10, d1, 0.99, "logarithmic") == pytest.approx(
        _confined_stress_mpa(c10, d1, 0.99, "quadratic"), rel=0.02
    )


@pytest.mark.parametrize("per_hex", [1, 4])
def test_springs_share_their_hex_volume_and_sit_in_its_quarters(per_hex):
    corners = _distorted_hex(2)
    fib = embedded_fibres(
        corners, np.arange(8)[None], np.array([[0.0, -50, -5]]), np.array([[0.0, -50, 5]]), 1.51, 11.0, 40.0,
        per_hex=per_hex,
    )  # fmt: skip
    assert len(fib.springs) == 2 * per_hex
    assert np.allclose(np.einsum("pk,pkj->pj", fib.weights, corners[fib.hosts]), fib.points)
    # each table holds k1 V_q / L: the springs of one family share the hex's volume (to the 2 % bins)
    shares = []
    for s in range(0, len(fib.springs), 2):  # family 0 of each point (springs: point by point, two families)
        table = np.array(fib.tables[fib.group[s]])
        rest = -table[0, 1]
        shares.append(
            np.interp(0.05 * rest, table[:, 1], table[:, 0])
            / fibre_force_n(np.array([1.05]), 1.51, 11.0, 1.0)[0]
            * rest
        )
    assert sum(shares) == pytest.approx(hex_volumes(corners, np.arange(8)[None])[0], rel=0.02)
    with pytest.raises(ValueError, match="springs per hex"):
        embedded_fibres(corners, np.arange(8)[None], np.zeros((1, 3)), np.ones((1, 3)), 1.0, 1.0, 40.0, per_hex=2)


def test_four_springs_per_hex_store_the_energy_of_a_bent_hex_that_one_spring_misses():
    """A 4 mm cube whose fibres (angle 0: both families circumferential, along x) stretch linearly across it,
    lambda(y) = 1 + eps y / 2 for y in [-2, 2] mm (the disc's bending: tension on one side of the neutral axis).
    The spring through the centre sits on the neutral axis and stores nothing; the exact tension energy, with
    k2 -> 0 so Psi = k1 (lambda^2 - 1)^2 / 2, is 2 families x 16 mm^2 x int_0^2 Psi dy; the quarter springs at
    y = +-1 store 2 x (V / 4) x 2 x Psi(1 + eps / 2), 0.73 of it at eps = 0.1 (a midpoint rule on a quadratic)."""
    k1, k2, eps = 2.0, 1e-9, 0.1
    corners = HEX8_NATURAL * 2.0
    a, b = np.array([[0.0, -500.0, -10.0]]), np.array([[0.0, -500.0, 10.0]])

    def psi(lam):
        return k1 / (2 * k2) * (np.exp(k2 * (lam**2 - 1) ** 2) - 1)

    y = np.linspace(0, 2, 20001)
    exact = 2 * 16.0 * np.trapezoid(psi(1 + eps * y / 2), y)
    moved = corners + np.c_[eps * corners[:, 1] * corners[:, 0] / 2, np.zeros((8, 2))]  # u_x = eps x y / 2
    stored = {}
    for per_hex in (1, 4):
        fib = embedded_fibres(corners, np.arange(8)[None], a, b, k1, k2, 0.0, per_hex=per_hex)
        ends = np.einsum("pk,pkj->pj", fib.weights, moved[fib.hosts])
        rest = np.linalg.norm(np.diff(fib.points[fib.springs], axis=1)[:, 0], axis=1)
        lam = np.linalg.norm(np.diff(ends[fib.springs], axis=1)[:, 0], axis=1) / rest
        stored[per_hex] = float(np.sum(64.0 / per_hex * np.where(lam > 1, psi(lam), 0.0)))
    assert stored[1] == pytest.approx(0.0, abs=1e-9 * exact)
    assert stored[4] / exact == pytest.approx(0.73, abs=0.02)
