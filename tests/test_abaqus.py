"""Tests of spinecohort.fe.abaqus (deck writing, template substitution, meshio/pyvista read-back) and
spinecohort.fe.calculix (strict ccx wrapper), on a hand-built 10 x 10 x 60 mm hex column."""

import re
import shutil

import numpy as np
import pytest

from spinecohort.fe.abaqus import (
    FEModel,
    LinearElastic,
    MooneyRivlin,
    Section,
    UserMaterial,
    validate_model,
    without_elements,
)
from spinecohort.fe.calculix import CalculixError, check_input, find_ccx, parse_dat, run_ccx
from spinecohort.fe.inp_template import InpTemplate, parse_template, read_inp, read_inp_nodes, substitute_coordinates
from spinecohort.fe.writers import format_id_list, model_to_inp_text, write_inp, write_vtu
from spinecohort.testing import hex_grid

HAS_CCX = shutil.which("ccx") is not None
needs_ccx = pytest.mark.skipif(not HAS_CCX, reason="CalculiX 'ccx' not installed (Debian package calculix-ccx)")

SIDE_MM, LENGTH_MM = 10.0, 60.0


def hex_column(nx=3, ny=3, nz=6, side=SIDE_MM, length=LENGTH_MM):
    """Nodes (N, 3) mm and C3D8 connectivity (E, 8), 0-based, of a structured square column along z."""
    xs, ys, zs = np.linspace(0, side, nx + 1), np.linspace(0, side, ny + 1), np.linspace(0, length, nz + 1)
    nodes, hexes = hex_grid(xs, ys, zs, x_fastest=True)
    return nodes, hexes


def column_model(etype="C3D8I"):
    """54 hexes (LOWER/UPPER halves, 27 each), 18 S3 triangles on the top face, 2 SPRINGA ligaments."""
    nodes, hexes = hex_column()
    top = np.flatnonzero(nodes[:, 2] == LENGTH_MM)
    base = np.flatnonzero(nodes[:, 2] == 0.0)
    # top face as a 4 x 4 node grid -> 9 quads -> 18 triangles with outward (+z) normals
    g = top.reshape(4, 4)
    q = np.column_stack([g[:-1, :-1].ravel(), g[:-1, 1:].ravel(), g[1:, 1:].ravel(), g[1:, :-1].ravel()])
    tris = np.vstack([q[:, [0, 1, 2]], q[:, [0, 2, 3]]])
    ligaments = np.array([[base[0], top[0]], [base[15], top[15]]])
    centroid_z = nodes[hexes][:, :, 2].mean(axis=1)
    lower = np.flatnonzero(centroid_z < LENGTH_MM / 2)
    upper = np.flatnonzero(centroid_z > LENGTH_MM / 2)
    return FEModel(
        nodes=nodes,
        element_blocks={"COLUMN": (etype, hexes), "ENDPLATE": ("S3", tris), "LIG": ("SPRINGA", ligaments)},
        node_sets={"BASE": base, "TOP": top},
        element_sets={"LOWER": lower, "UPPER": upper},
        materials=[
            LinearElastic("BONE", 12000.0, 0.3),
            MooneyRivlin("DISC", 0.3, 0.1, 0.05),
            UserMaterial("ELASTIC_FIBER_AF", (0.35, 0.0, 1.0, 0.0, 0.5, 1.0, 1.0, 0.0, 0.5, 1.0)),
        ],
        sections=[
            Section("LOWER", "BONE"),
            Section("UPPER", "DISC"),
            Section("ENDPLATE", "BONE", thickness_mm=0.5),
            Section("LIG", spring_force_elongation=((0.0, -10.0), (0.0, 0.0), (100.0, 1.0), (1000.0, 10.0))),
        ],
        heading="test column",
    )


def elastic_column(nz=6):
    """The column all in BONE (E = 12 GPa, nu = 0.3), C3D8I hexes only, nz elements along its length."""
    nodes, hexes = hex_column(nz=nz)
    sets = {"BASE": np.flatnonzero(nodes[:, 2] == 0.0), "TOP": np.flatnonzero(nodes[:, 2] == LENGTH_MM)}
    return FEModel(
        nodes,
        {"COLUMN": ("C3D8I", hexes)},
        node_sets=sets,
        materials=[LinearElastic("BONE", 12000.0, 0.3)],
        sections=[Section("COLUMN", "BONE")],
    )


def test_without_elements_drops_a_block_renumbers_the_sets_after_it_and_their_sections():
    model = column_model()  # 54 hexes (0-53), 18 S3 (54-71), 2 springs (72-73)
    out = without_elements(model, np.arange(54, 72))  # the whole S3 block
    assert list(out.element_blocks) == ["COLUMN", "LIG"] and out.n_elements == 56
    np.testing.assert_array_equal(out.element_sets["LOWER"], model.element_sets["LOWER"])  # before the drop
    assert [s.elset for s in out.sections] == ["LOWER", "UPPER", "LIG"]  # ENDPLATE's section went with it
    validate_model(out)
    part = without_elements(model, np.array([0, 54]))  # one hex and one triangle: sets shift by what went before
    assert part.n_elements == 72 and len(part.element_blocks["ENDPLATE"][1]) == 17
    lower = model.element_sets["LOWER"]
    np.testing.assert_array_equal(part.element_sets["LOWER"], lower[lower != 0] - 1)
    assert without_elements(model, np.zeros(0, np.int64)) is model
    with pytest.raises(ValueError, match="outside"):
        without_elements(model, np.array([74]))


# --- writing and reading back -----------------------------------------------------------------------


def test_meshio_round_trip_counts_sets_and_coordinates(tmp_path):
    model = column_model()
    path = write_inp(model, tmp_path / "column.inp")
    mesh = read_inp(path)
    # 4 x 4 x 7 = 112 nodes; 3 x 3 x 6 = 54 hexes; 9 top quads x 2 = 18 triangles; 2 ligaments
    assert mesh.points.shape == (112, 3)
    np.testing.assert_allclose(mesh.points, model.nodes, atol=5e-7)  # 6 decimals written
    assert [(c.type, len(c.data)) for c in mesh.cells] == [("hexahedron", 54), ("triangle", 18), ("line", 2)]
    np.testing.assert_array_equal(mesh.cells[0].data, model.element_blocks["COLUMN"][1])
    np.testing.assert_array_equal(mesh.cells[2].data, model.element_blocks["LIG"][1])
    assert set(mesh.point_sets) == {"BASE", "TOP"}
    np.testing.assert_array_equal(mesh.point_sets["TOP"], model.node_sets["TOP"])
    np.testing.assert_array_equal(mesh.point_sets["BASE"], model.node_sets["BASE"])
    for name in ("LOWER", "UPPER"):
        per_block = mesh.cell_sets[name]
        np.testing.assert_array_equal(per_block[0], model.element_sets[name])  # all in the hex block
        assert [len(b) for b in per_block[1:]] == [0, 0]
    assert [len(b) for b in mesh.cell_sets["ENDPLATE"]] == [0, 18, 0]


def test_deck_layout_one_node_block_ids_compact_sixteen_per_line():
    text = model_to_inp_text(column_model(), provenance="unit test")
    assert len(re.findall(r"^\*NODE\b(?! PRINT)", text, re.MULTILINE)) == 1
    assert "** units: length mm, force N, stress MPa" in text and "unit test" in text
    # element ids run 1..74 over the three blocks in order (54 + 18 + 2)
    assert "\n1, 1, 2, 6, 5, 17, 18, 22, 21\n" in text  # first hex, 1-based nodes
    assert "*ELEMENT, TYPE=S3, ELSET=ENDPLATE\n55, " in text
    assert "*ELEMENT, TYPE=SPRINGA, ELSET=LIG\n73, 1, 97\n74, 16, 112\n*NSET" in text
    assert format_id_list(np.arange(1, 36)).splitlines() == [
        ", ".join(map(str, range(1, 17))),
        ", ".join(map(str, range(17, 33))),
        "33, 34, 35",
    ]
    # SPRINGA: empty first data line, then the (force, elongation) table
    assert "*SPRING, ELSET=LIG, NONLINEAR\n\n0.0, -10.0\n0.0, 0.0\n100.0, 1.0\n1000.0, 10.0\n" in text
    # 10 user constants -> 8 + 2 per line
    assert "*USER MATERIAL, CONSTANTS=10\n0.35, 0.0, 1.0, 0.0, 0.5, 1.0, 1.0, 0.0\n0.5, 1.0\n" in text


def test_read_inp_nodes_returns_ids_and_coordinates(tmp_path):
    model = column_model()
    ids, pts = read_inp_nodes(write_inp(model, tmp_path / "c.inp"))
    np.testing.assert_array_equal(ids, np.arange(1, 113))
    np.testing.assert_allclose(pts, model.nodes, atol=5e-7)


def test_write_vtu_hex_volume_and_pyvista_read(tmp_path):
    import pyvista as pv

    path = write_vtu(elastic_column(), tmp_path / "c.vtu")
    grid = pv.read(path)
    assert grid.n_points == 112 and grid.n_cells == 54
    # VTK hex order = Abaqus order, so every cell has positive volume summing to 10 x 10 x 60 mm^3
    vol = grid.compute_cell_sizes(length=False, area=False, volume=True)["Volume"]
    assert np.all(vol > 0)
    assert vol.sum() == pytest.approx(6000.0, rel=1e-9)
    np.testing.assert_array_equal(grid.cell_data["element_id"], np.arange(1, 55))


@pytest.mark.parametrize(
    "mutate, message",
    [
        (lambda m: m.element_blocks.update(SKIN=("M3D3", m.element_blocks["ENDPLATE"][1])), "M3D3"),
        (lambda m: m.element_blocks.update(SKIN=("SFM3D3", m.element_blocks["ENDPLATE"][1])), "SFM3D3"),
        (lambda m: m.node_sets.update(BAD=np.array([0, 112])), "outside 0..111"),
        (lambda m: m.node_sets.update({"has space": np.array([0])}), "not a valid Abaqus name"),
        (lambda m: m.sections.append(Section("COLUMN", "STEEL")), "unknown material 'STEEL'"),
        (lambda m: m.element_sets.update(COLUMN=np.array([0])), "name of an element block"),
        (lambda m: m.sections.__setitem__(2, Section("ENDPLATE", "BONE")), "thickness_mm"),
        # ccx silently replaces D1 = 0 by a default (0.125 /MPa seen in ccx 2.20): refuse it
        (lambda m: m.materials.__setitem__(1, MooneyRivlin("DISC", 0.3, 0.1, 0.0)), "D1 must be > 0"),
    ],
)
def test_invalid_models_raise_value_error(mutate, message):
    model = column_model()
    mutate(model)
    with pytest.raises(ValueError, match=re.escape(message)):
        validate_model(model)


# --- template substitution --------------------------------------------------------------------------


def test_substitute_changes_only_node_lines(tmp_path):
    model = column_model()
    template = write_inp(model, tmp_path / "Mean_Model (Template).inp")
    rng = np.random.default_rng(3)
    moved = model.nodes * 1.1 + rng.normal(0, 2.0, model.nodes.shape)
    out = substitute_coordinates(template, moved, tmp_path / "model_00001.inp")
    old, new = template.read_text().splitlines(), (tmp_path / "model_00001.inp").read_text().splitlines()
    assert len(old) == len(new)
    first_node = old.index("*NODE, NSET=NALL") + 1
    changed = [i for i, (a, b) in enumerate(zip(old, new)) if a != b]
    assert changed and min(changed) >= first_node and max(changed) < first_node + 112
    # node ids are kept, coordinates reproduced to the written precision (6 decimals: <= 5e-7 mm)
    assert [ln.split(",")[0] for ln in new[first_node : first_node + 112]] == [str(i) for i in range(1, 113)]
    ids, pts = read_inp_nodes(tmp_path / "model_00001.inp")
    np.testing.assert_allclose(pts, moved, atol=5e-7)
    assert out == (tmp_path / "model_00001.inp").read_text()


def test_substitute_original_coordinates_is_byte_identical_and_accepts_text_and_parsed(tmp_path):
    model = column_model()
    text = model_to_inp_text(model)
    tpl = parse_template(text)
    assert isinstance(tpl, InpTemplate) and tpl.decimals == 6 and len(tpl.node_ids) == 112
    assert substitute_coordinates(text, model.nodes) == text
    assert substitute_coordinates(tpl, model.nodes) == text
    with pytest.raises(ValueError, match=r"shape \(112, 3\)"):
        substitute_coordinates(tpl, model.nodes[:-1])
    with pytest.raises(ValueError, match="2 \\*NODE blocks"):
        parse_template(text + "*NODE\n999, 0., 0., 0.\n")


# --- CalculiX ---------------------------------------------------------------------------------------


def test_parse_dat_reads_node_print_blocks():
    dat = (
        "\n displacements (vx,vy,vz) for set TOP and time  0.1000000E+01\n\n"
        "       193  7.183913E-01 -1.299122E-04  8.887360E-02\n"
        "       194  7.179766E-01  8.293880E-06  2.940252E-02\n\n"
        " forces (fx,fy,fz) for set BASE and time  0.5000000E+00\n\n"
        "         1 -1.0E+01  0.0E+00  2.5E+00\n"
    )
    blocks = parse_dat(dat)
    assert [(b.quantity, b.node_set, b.time) for b in blocks] == [
        ("displacements (vx,vy,vz)", "TOP", 1.0),
        ("forces (fx,fy,fz)", "BASE", 0.5),
    ]
    np.testing.assert_array_equal(blocks[0].node_ids, [193, 194])
    assert blocks[0].values[1, 2] == 2.940252e-02 and blocks[1].values.tolist() == [[-10.0, 0.0, 2.5]]


def test_find_ccx_names_the_debian_package(monkeypatch):
    monkeypatch.setenv("CCX", "/nonexistent/ccx")
    with pytest.raises(FileNotFoundError, match="calculix-ccx"):
        find_ccx()


@needs_ccx
def test_ccx_data_check_accepts_the_full_deck(tmp_path):
    path = write_inp(column_model(), tmp_path / "Mean_Model (Template).inp")
    result = check_input(path, tmp_path / "run")
    assert "No analysis was selected" in result.log


@needs_ccx
def test_ccx_data_check_catches_an_inverted_hex(tmp_path):
    model = elastic_column()
    hexes = model.element_blocks["COLUMN"][1].copy()
    hexes[0] = hexes[0][[4, 5, 6, 7, 0, 1, 2, 3]]  # top and bottom faces swapped: negative Jacobian
    model.element_blocks["COLUMN"] = ("C3D8I", hexes)
    with pytest.raises(CalculixError, match="nonpositive jacobian"):
        check_input(write_inp(model, tmp_path / "inv.inp"), tmp_path / "run")


LOAD_STEP = """*BOUNDARY
BASE, 1, 3
*STEP
*STATIC
*CLOAD
TOP, 1, {per_node}
*NODE PRINT, NSET=TOP
U
*END STEP
"""


@needs_ccx
def test_ccx_cantilever_tip_deflection_matches_timoshenko_beam(tmp_path):
    # 100 N transverse end load on a 10 x 10 x 60 mm clamped column (3 x 3 x 12 C3D8I), E 12 GPa, nu 0.3:
    # bending F L^3 / (3 E I) = 0.7200 mm, shear F L / (k G A) with k = 5/6 adds 0.0156 mm -> 0.7356 mm.
    e, nu, f, L, a = 12000.0, 0.3, 100.0, LENGTH_MM, SIDE_MM
    expected = f * L**3 / (3 * e * a**4 / 12) + f * L / (5 / 6 * e / (2 * (1 + nu)) * a * a)
    path = tmp_path / "cantilever.inp"
    path.write_text(model_to_inp_text(elastic_column(nz=12)) + LOAD_STEP.format(per_node=f / 16))
    result = run_ccx(path, tmp_path / "run")
    (block,) = result.node_prints
    assert block.node_set == "TOP" and len(block.node_ids) == 16
    tip = block.values[:, 0].mean()
    # C3D8I with a fully clamped base (Poisson contraction restrained) is slightly stiff: ccx 2.20 gives
    # 0.7179 mm (-2.4 %); 3 x 3 x 6 elements would give 0.7039 mm (-4.3 %)
    assert tip == pytest.approx(expected, rel=0.03)
    assert expected == pytest.approx(0.7356, abs=1e-4)
    # the data check keeps the model data (incl. *BOUNDARY) and replaces the step by *NO ANALYSIS
    assert check_input(path, tmp_path / "check").node_prints == []


@needs_ccx
def test_run_ccx_raises_on_unknown_keyword_that_ccx_only_warns_about(tmp_path):
    path = tmp_path / "unknown.inp"
    path.write_text(model_to_inp_text(elastic_column()) + "*NOT A KEYWORD, X=1\n" + LOAD_STEP.format(per_node=1.0))
    with pytest.raises(CalculixError, match=r"exit code 0.*\n.*WARNING"):
        run_ccx(path, tmp_path / "run")
    # the same deck passes when the caller allows that warning explicitly
    result = run_ccx(path, tmp_path / "run2", allowed_warnings=(r"card image",))
    assert result.returncode == 0


def test_orientation_is_written_and_checked():
    from spinecohort.fe.abaqus import Orientation

    model = column_model()
    model.orientations.append(Orientation("OR_AF", (5.0, 5.0, 0.0), (5.0, 5.0, 60.0)))
    model.sections[1] = Section("UPPER", "ELASTIC_FIBER_AF", orientation="OR_AF")
    text = model_to_inp_text(model)
    assert "*ORIENTATION, NAME=OR_AF, SYSTEM=CYLINDRICAL\n5.0, 5.0, 0.0, 5.0, 5.0, 60.0\n" in text
    assert "*SOLID SECTION, ELSET=UPPER, MATERIAL=ELASTIC_FIBER_AF, ORIENTATION=OR_AF\n" in text
    model.sections[1] = Section("UPPER", "ELASTIC_FIBER_AF", orientation="OR_NONE")
    with pytest.raises(ValueError, match="orientation 'OR_NONE' is unknown"):
        validate_model(model)


def test_data_check_replaces_the_fibre_law_by_its_ground_substance():
    # ccx 2.20 segfaults on *NO ANALYSIS with an ELASTIC_FIBER element: the check uses Neo-Hooke C10, D1
    # (D1 = 0 -> 1 / (20 C10), what the fibre law itself substitutes: 1 / (20 * 0.35) = 0.142857...)
    from spinecohort.fe.calculix import fibre_ground_substance

    text = model_to_inp_text(column_model())
    out = fibre_ground_substance(text)
    assert "*USER MATERIAL" not in out
    assert "*MATERIAL, NAME=ELASTIC_FIBER_AF\n*HYPERELASTIC, NEO HOOKE\n0.35, 0.14285714285714285\n" in out
    assert out.replace(out[out.index("*MATERIAL, NAME=ELASTIC_FIBER_AF") :], "") == text.replace(
        text[text.index("*MATERIAL, NAME=ELASTIC_FIBER_AF") :], ""
    )


def test_every_float_field_fits_ccx_20_characters():
    # ccx 2.20 reads 20 characters of a field: repr(2.4178372958533995e-05) has 22 and ccx stopped with
    # "*ERROR reading *GAP"; the writer falls back to 14 significant digits (relative error <= 5e-15)
    from spinecohort.fe.writers import MAX_FIELD_CHARS, _fmt_float

    rng = np.random.default_rng(0)
    xs = np.concatenate([[2.4178372958533995e-05, -1.0 / 3.0, 1e-300, -123.45678901234567], rng.normal(size=1000)])
    xs = np.concatenate([xs, xs * 1e-7, xs * 1e5])
    out = [_fmt_float(x) for x in xs]
    assert max(len(s) for s in out) <= MAX_FIELD_CHARS
    np.testing.assert_allclose([float(s) for s in out], xs, rtol=5e-14)
    assert _fmt_float(0.5) == "0.5" and _fmt_float(1670.0) == "1670.0"  # short values are unchanged
