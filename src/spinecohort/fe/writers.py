"""The text of an `FEModel`'s Abaqus/CalculiX deck (.inp), and its .vtu twin.

The deck is flat (no *PART/*ASSEMBLY/*INSTANCE, which CalculiX ignores): one *NODE block (meshio's reader keeps
only the last one), *ELEMENT blocks, *NSET/*ELSET, *EQUATION ties, *ORIENTATION, *MATERIAL and the sections.
The *NODE / *ELEMENT text is formatted with a single `%` over a flattened array (measured 0.8 s for 500k
nodes; `np.savetxt` 2.0 s, pandas `to_csv` 2.4 s), so writing a model stays a small fraction of a shard
(benchmarks/bench_abaqus.py times the writer against meshio's).  Units: mm, N, MPa.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from spinecohort.atomic import write_text_atomic
from spinecohort.fe.abaqus import (
    IDS_PER_LINE,
    MESHIO_CELL_TYPE,
    NEO_HOOKE_LOCKING_STRETCH,
    SHELL_TYPES,
    FEModel,
    LinearElastic,
    MooneyRivlin,
    NeoHooke,
    Orientation,
    Section,
    UserMaterial,
    elset_types,
    validate_model,
)


def format_node_lines(ids: np.ndarray, points_mm: np.ndarray, decimals: int = 6) -> str:
    """*NODE data lines `id, x, y, z` (one % over the flattened table: no per-node Python formatting)."""
    points_mm = np.asarray(points_mm, dtype=np.float64)
    row = f"%d, %.{decimals}f, %.{decimals}f, %.{decimals}f\n"
    # ids ride along as float64 (exact below 2**53; "%d" prints them as integers): one homogeneous
    # tolist() is 1.5x faster than an object table of int ids and float coordinates
    table = np.column_stack([np.asarray(ids, dtype=np.float64), points_mm])
    return (row * len(points_mm)) % tuple(table.ravel().tolist())


def _format_int_rows(rows: np.ndarray) -> str:
    """Rows of integers, IDS_PER_LINE a line: a longer row (a C3D20R element: id + 20 nodes) ends its first
    line with a comma and continues on the next (the Abaqus rule ccx 2.20 reads)."""
    rows = np.asarray(rows, dtype=np.int64)
    k = rows.shape[1]
    cuts = range(IDS_PER_LINE, k, IDS_PER_LINE)
    line = ",\n".join(", ".join(["%d"] * len(c)) for c in np.split(np.arange(k), list(cuts))) + "\n"
    return (line * len(rows)) % tuple(rows.ravel().tolist())


def equation_text(nodes: np.ndarray, weights: np.ndarray) -> str:
    """*EQUATION cards u_d - sum_j w_j u_(i_j) = 0 in directions 1-3 for rows [d, i_1 .. i_m] (0-based) with
    weights (K, m); at most 4 terms a line (the Abaqus rule, which ccx follows)."""
    nodes = np.asarray(nodes, dtype=np.int64) + 1
    k, m = nodes.shape[0], nodes.shape[1] - 1
    coef = np.column_stack([np.ones(k), -np.asarray(weights, dtype=np.float64)])

    def one(dof: int) -> str:
        terms = [f"%d, {dof}, %.12g"] * (m + 1)
        return f"{m + 1}\n" + "\n".join(", ".join(terms[i : i + 4]) for i in range(0, m + 1, 4)) + "\n"

    values = np.stack([nodes.astype(np.float64), coef], axis=-1)  # (K, 1 + m, 2): node, coefficient per term
    values = np.broadcast_to(values[:, None], (k, 3, m + 1, 2))  # the same terms in each direction
    return "*EQUATION\n" + ("".join(one(d) for d in (1, 2, 3)) * k) % tuple(values.ravel().tolist())


def format_id_list(ids_1based: np.ndarray) -> str:
    """Set data lines, IDS_PER_LINE ids a line, the last line shorter."""
    ids = np.asarray(ids_1based, dtype=np.int64)
    n_full = len(ids) // IDS_PER_LINE * IDS_PER_LINE
    text = _format_int_rows(ids[:n_full].reshape(-1, IDS_PER_LINE)) if n_full else ""
    if n_full < len(ids):
        text += ", ".join(map(str, ids[n_full:].tolist())) + "\n"
    return text


#: ccx 2.20 reads the first 20 characters of a data field (e.g. '2.4178372958533995E-05' gave
#: "*ERROR reading *GAP"); Abaqus reads 20 too in fixed-length fields
MAX_FIELD_CHARS = 20


def _fmt_float(x: float) -> str:
    """Shortest round-tripping repr, or 14 significant digits when that would exceed MAX_FIELD_CHARS."""
    s = repr(float(x))
    return s if len(s) <= MAX_FIELD_CHARS else f"{float(x):.14g}"


def _material_text(mat) -> str:
    out = f"*MATERIAL, NAME={mat.name}\n"
    if isinstance(mat, LinearElastic):
        out += f"*ELASTIC\n{_fmt_float(mat.youngs_modulus_mpa)}, {_fmt_float(mat.poisson_ratio)}\n"
    elif isinstance(mat, MooneyRivlin):
        out += (
            f"*HYPERELASTIC, MOONEY-RIVLIN\n{_fmt_float(mat.c10_mpa)}, {_fmt_float(mat.c01_mpa)}, "
            f"{_fmt_float(mat.d1_per_mpa)}\n"
        )
    elif isinstance(mat, NeoHooke) and mat.volumetric == "logarithmic":
        out += (
            f"*HYPERELASTIC, ARRUDA-BOYCE\n{_fmt_float(2.0 * mat.c10_mpa)}, {_fmt_float(NEO_HOOKE_LOCKING_STRETCH)}, "
            f"{_fmt_float(mat.d1_per_mpa)}\n"
        )
    elif isinstance(mat, NeoHooke):
        out += f"*HYPERELASTIC, NEO HOOKE\n{_fmt_float(mat.c10_mpa)}, {_fmt_float(mat.d1_per_mpa)}\n"
    elif isinstance(mat, UserMaterial):
        c = [_fmt_float(x) for x in mat.constants]
        out += f"*USER MATERIAL, CONSTANTS={len(c)}\n"
        out += "".join(", ".join(c[i : i + 8]) + "\n" for i in range(0, len(c), 8))  # 8 per line (Abaqus rule)
    else:
        raise ValueError(f"unknown material kind {type(mat).__name__}")
    return out


def _section_text(model: FEModel, sec: Section) -> str:
    etype = elset_types(model, sec.elset).pop()
    if etype == "SPRINGA":
        table = np.asarray(sec.spring_force_elongation, dtype=np.float64)
        # first data line of a SPRINGA *SPRING is empty (no DOFs for axial springs)
        return f"*SPRING, ELSET={sec.elset}, NONLINEAR\n\n" + "".join(
            f"{_fmt_float(f)}, {_fmt_float(d)}\n" for f, d in table
        )
    if etype == "GAPUNI":
        clearance, (nx, ny, nz), stiffness = sec.gap
        vals = ", ".join(_fmt_float(v) for v in (clearance, nx, ny, nz))
        return f"*GAP, ELSET={sec.elset}\n{vals}, , {_fmt_float(stiffness)}\n"
    if etype in SHELL_TYPES:
        return f"*SHELL SECTION, ELSET={sec.elset}, MATERIAL={sec.material}\n{_fmt_float(sec.thickness_mm)}\n"
    if etype == "T3D2":
        return f"*SOLID SECTION, ELSET={sec.elset}, MATERIAL={sec.material}\n{_fmt_float(sec.area_mm2)}\n"
    orient = f", ORIENTATION={sec.orientation}" if sec.orientation else ""
    return f"*SOLID SECTION, ELSET={sec.elset}, MATERIAL={sec.material}{orient}\n"


def _orientation_text(o: Orientation) -> str:
    pts = ", ".join(_fmt_float(x) for x in (*o.axis_a_mm, *o.axis_b_mm))
    return f"*ORIENTATION, NAME={o.name}, SYSTEM=CYLINDRICAL\n{pts}\n"


def model_to_inp_text(model: FEModel, decimals: int = 6, provenance: str = "") -> str:
    """The model's deck as text (the dialect: `spinecohort.fe.abaqus`, this module's docstring)."""
    validate_model(model)
    from spinecohort import __version__

    nodes = np.asarray(model.nodes, dtype=np.float64)
    parts = [
        "** spinecohort Abaqus/CalculiX input deck\n",
        "** units: length mm, force N, stress MPa (moments N.mm)\n",
        f"** written by spinecohort {__version__}" + (f"; {provenance}" if provenance else "") + "\n",
        f"** {len(nodes)} nodes, {model.n_elements} elements; node and element ids 1-based, compact\n",
        "*HEADING\n",
        model.heading.replace("\n", " ") + "\n",
        "*NODE, NSET=NALL\n",
        format_node_lines(np.arange(1, len(nodes) + 1), nodes, decimals),
    ]
    first = 1
    for name, (etype, conn) in model.element_blocks.items():
        conn = np.asarray(conn, dtype=np.int64)
        ids = np.arange(first, first + len(conn))
        parts += [f"*ELEMENT, TYPE={etype}, ELSET={name}\n", _format_int_rows(np.column_stack([ids, conn + 1]))]
        first += len(conn)
    for name, idx in model.node_sets.items():
        parts += [f"*NSET, NSET={name}\n", format_id_list(np.asarray(idx) + 1)]
    for name, idx in model.element_sets.items():
        parts += [f"*ELSET, ELSET={name}\n", format_id_list(np.asarray(idx) + 1)]
    parts += [equation_text(ids, w) for ids, w in model.ties()]
    parts += [_orientation_text(o) for o in model.orientations]
    parts += [_material_text(m) for m in model.materials]
    parts += [_section_text(model, s) for s in model.sections]
    return "".join(parts)


def write_inp(model: FEModel, path: str | Path, decimals: int = 6, provenance: str = "") -> Path:
    """Write the model's .inp deck (mm, N, MPa); coordinates with `decimals` decimals (6 = 1 nm)."""
    path = Path(path)
    text = model_to_inp_text(model, decimals, provenance)
    return write_text_atomic(path, text)


def write_vtu(model: FEModel, path: str | Path, leave_out: tuple[str, ...] = ()) -> Path:
    """Write the model as .vtu via meshio: one cell block per element block (hexes stay VTK_HEXAHEDRON,
    same node order), cell data `element_id` (the deck's 1-based id) and `block` (block number); the blocks named
    in `leave_out` (e.g. connector lines, which are not anatomy) are not drawn, and every other element keeps its
    deck id."""
    import meshio

    validate_model(model)
    cells, element_id, block = [], [], []
    first = 1
    for i, (name, (etype, conn)) in enumerate(model.element_blocks.items()):
        conn = np.asarray(conn, dtype=np.int64)
        if name not in leave_out:
            cells.append((MESHIO_CELL_TYPE[etype], conn))
            element_id.append(np.arange(first, first + len(conn), dtype=np.int64))
            block.append(np.full(len(conn), i, dtype=np.int32))
        first += len(conn)
    mesh = meshio.Mesh(
        np.asarray(model.nodes, dtype=np.float64), cells, cell_data={"element_id": element_id, "block": block}
    )
    path = Path(path)
    meshio.write(path, mesh, file_format="vtu", binary=True)
    return path
