"""Abaqus/CalculiX input decks (.inp) for the hexahedral spine models, and their .vtu twin.

The deck is flat (no *PART/*ASSEMBLY/*INSTANCE, which CalculiX ignores) and uses only keywords that both
Abaqus and CalculiX (ccx 2.20) accept: one *NODE block, *ELEMENT blocks of C3D8/C3D8I/C3D8R hexes, S3/S4
shells, SPRINGA ligaments and T3D2 trusses, *NSET/*ELSET, *MATERIAL (*ELASTIC, *HYPERELASTIC
MOONEY-RIVLIN, *USER MATERIAL placeholders) and one section per element set.  Units: mm, N, MPa.

Conventions of `FEModel`: connectivity, node sets and element sets hold 0-based row indices (into
`nodes`, resp. into the concatenation of the element blocks in insertion order); the deck numbers nodes
and elements 1..N compactly, because ccx allocates memory by the largest node id, not the node count.
All nodes go into one *NODE block because meshio's reader keeps only the last one.

The *NODE / *ELEMENT text is formatted with a single `%` over a flattened array (measured 0.8 s for 500k
nodes; `np.savetxt` 2.0 s, pandas `to_csv` 2.4 s), so writing a model stays a small fraction of a
shard.  `substitute_coordinates` is written here rather than borrowed: it is the seed's "replace the point
coordinates in Mean_Model (Template).inp" step, and everything but the *NODE data lines must stay
byte-identical, which no mesh library guarantees.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from spinecohort.atomic import write_text_atomic

#: nodes per element of each supported Abaqus/CalculiX element type.
NODES_PER_ELEMENT = {
    "C3D8": 8,
    "C3D8I": 8,
    "C3D8R": 8,
    "C3D20R": 20,
    "S3": 3,
    "S4": 4,
    "S4R": 4,
    "SPRINGA": 2,
    "T3D2": 2,
    "GAPUNI": 2,
}
#: meshio cell type of each element type (hex node order is the same in VTK and Abaqus).
MESHIO_CELL_TYPE = {
    "C3D8": "hexahedron",
    "C3D8I": "hexahedron",
    "C3D8R": "hexahedron",
    "C3D20R": "hexahedron20",  # same node order in VTK and Abaqus
    "S3": "triangle",
    "S4": "quad",
    "S4R": "quad",
    "SPRINGA": "line",
    "T3D2": "line",
    "GAPUNI": "line",
}
SOLID_TYPES = {"C3D8", "C3D8I", "C3D8R", "C3D20R"}
SHELL_TYPES = {"S3", "S4", "S4R"}
# ccx 2.20 rejects or mis-handles these (see reference/calculix.md): refuse them instead of writing a
# deck that fails or silently shifts results.
UNSUPPORTED_TYPES = {
    "M3D3": "accepted by ccx but shifts results 1-2 %; use S3",
    "SFM3D3": "unknown to ccx; use S3",
    "SFM3D4": "unknown to ccx; use S4",
    "R3D3": "unknown to ccx",
    "R3D4": "unknown to ccx",
    "CONN3D2": "unknown to ccx; use SPRINGA",
}
IDS_PER_LINE = 16
_NAME = re.compile(r"^[A-Za-z][A-Za-z0-9_\-.]{0,79}$")


@dataclass(frozen=True)
class LinearElastic:
    """Isotropic linear elastic material: Young's modulus in MPa, Poisson ratio."""

    name: str
    youngs_modulus_mpa: float
    poisson_ratio: float


@dataclass(frozen=True)
class MooneyRivlin:
    """Mooney-Rivlin hyperelastic material: C10, C01 in MPa, D1 in 1/MPa (must be > 0: with D1 = 0,
    which Abaqus reads as incompressible, ccx 2.20 silently substitutes a default D1, e.g. 0.125)."""

    name: str
    c10_mpa: float
    c01_mpa: float
    d1_per_mpa: float


#: the volumetric terms a NeoHooke material can carry (see NeoHooke)
VOLUMETRIC_TERMS = ("quadratic", "logarithmic")
#: Arruda-Boyce locking stretch that makes its shear response the Neo-Hooke one: the first correction to
#: mu (I1 - 3) / 2 is mu (I1^2 - 9) / (20 lm^2), < 1e-4 of it for the stretches of a disc (I1 < 5)
NEO_HOOKE_LOCKING_STRETCH = 100.0


@dataclass(frozen=True)
class NeoHooke:
    """Neo-Hooke hyperelastic material: C10 in MPa, D1 in 1/MPa (> 0, see MooneyRivlin).

    volumetric: "quadratic" (*HYPERELASTIC, NEO HOOKE): U_vol = (J - 1)^2 / D1, whose pressure stays finite
    (2 / D1) as J -> 0, so a hex squeezed to half its volume has lost most of its bulk resistance;
    "logarithmic": U_vol = ((J^2 - 1)/2 - ln J) / D1, the same initial bulk modulus 2 / D1 and shear modulus
    2 C10, with a barrier (p -> -inf as J -> 0).  Abaqus and ccx 2.20 carry that term only in their
    Arruda-Boyce law, so it is written as *HYPERELASTIC, ARRUDA-BOYCE with mu = 2 C10 and a locking stretch
    (NEO_HOOKE_LOCKING_STRETCH) at which its shear response is the Neo-Hooke one."""

    name: str
    c10_mpa: float
    d1_per_mpa: float
    volumetric: str = "quadratic"

    def __post_init__(self):
        if self.volumetric not in VOLUMETRIC_TERMS:
            raise ValueError(f"material {self.name}: volumetric term {self.volumetric!r}, one of {VOLUMETRIC_TERMS}")


@dataclass(frozen=True)
class UserMaterial:
    """*USER MATERIAL placeholder: ccx's built-in laws are selected by name (e.g. `ELASTIC_FIBER...`,
    constants C10, D1, then ax, ay, k1, k2 per fibre family); Abaqus needs a matching UMAT."""

    name: str
    constants: tuple[float, ...]


@dataclass(frozen=True)
class Orientation:
    """A cylindrical local system (*ORIENTATION, SYSTEM=CYLINDRICAL): the axis runs from point a to point b
    (mm).  Local directions: 1 radial, 2 circumferential, 3 axial (a -> b).  Used for the annulus fibres
    of each disc, whose two families lie in the circumferential-axial plane."""

    name: str
    axis_a_mm: tuple[float, float, float]
    axis_b_mm: tuple[float, float, float]


@dataclass(frozen=True)
class Section:
    """Assigns element set `elset` a material (solids, shells, trusses) or a spring law (SPRINGA).

    thickness_mm: shell thickness (S3/S4).  area_mm2: truss cross-section (T3D2).
    spring_force_elongation: (K, 2) table of (force N, elongation mm), elongation ascending; used in
    an NLGEOM step it is tension-only if force is 0 for elongation <= 0 (ccx linearises it otherwise).
    orientation: name of an `Orientation` (solid sections only), e.g. the annulus' fibre system.
    gap: (clearance mm, unit direction (3,), stiffness N/mm) of GAPUNI elements (ccx *GAP): the gap stays
    open while clearance + direction . (u2 - u1) > 0 (node 1 -> node 2; checked on ccx 2.20).
    """

    elset: str
    material: str | None = None
    thickness_mm: float | None = None
    area_mm2: float | None = None
    spring_force_elongation: tuple[tuple[float, float], ...] | None = None
    orientation: str | None = None
    gap: tuple[float, tuple[float, float, float], float] | None = None


@dataclass
class FEModel:
    """A finite-element model in memory (mm).

    nodes: (N, 3) coordinates in mm.  element_blocks: {name: (type, (E, k) 0-based node indices)};
    each block is written as one *ELEMENT with ELSET=name.  node_sets: {name: 0-based node indices}.
    element_sets: {name: 0-based indices into the concatenated blocks}.  materials: list of
    LinearElastic / MooneyRivlin / UserMaterial.  sections: list of Section.  orientations: list of
    Orientation referred to by solid sections.
    """

    nodes: np.ndarray
    element_blocks: dict[str, tuple[str, np.ndarray]]
    node_sets: dict[str, np.ndarray] = field(default_factory=dict)
    element_sets: dict[str, np.ndarray] = field(default_factory=dict)
    materials: list = field(default_factory=list)
    sections: list[Section] = field(default_factory=list)
    heading: str = "spinecohort model"
    orientations: list[Orientation] = field(default_factory=list)
    #: (K, 3) 0-based [m, a, b]: node m moves as the mean of nodes a and b (*EQUATION per direction); the
    #: midside nodes of quadratic hexes on an edge of a linear neighbour (`spinecohort.fe.quadratic`)
    midside_ties: np.ndarray | None = None
    #: ((K, 1 + m) 0-based [d, i_1 .. i_m], (K, m) weights w): node d moves as sum_j w_j u_(i_j) (*EQUATION per
    #: direction); the annulus fibre springs' end nodes inside their hexes (`spinecohort.fe.fibres`)
    embedded_ties: tuple[np.ndarray, np.ndarray] | None = None

    def ties(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """Every *EQUATION tie as ((K, 1 + m) [dependent, independents], (K, m) weights): midside, then embedded."""
        out = []
        if self.midside_ties is not None and len(self.midside_ties):
            mid = np.asarray(self.midside_ties, dtype=np.int64)
            out.append((mid, np.full((len(mid), 2), 0.5)))
        if self.embedded_ties is not None and len(self.embedded_ties[0]):
            out.append((np.asarray(self.embedded_ties[0], dtype=np.int64), np.asarray(self.embedded_ties[1], float)))
        return out

    def embedded_hosts(self) -> np.ndarray:
        """0-based nodes that the embedded ties interpolate from (the fibre springs' host hex corners).

        Keep them out of a *RIGID BODY and out of a fixed set: ccx 2.20 accepts a linear *EQUATION on rigid-body
        nodes but does not follow the rigid body's rotation in it, so the tied fibre ends drift as the body turns
        (a partial-CEP T10-S1 model: the disc under the loaded T10 closed 0.34 mm against 0.13 mm in T10-T12 at the
        same flexion, and the model stalled at 69 %); on fixed nodes the tie's share of the force leaves ccx's
        reaction output (58 N of a functional unit's axial reaction missing) and stalled a lumbar model (test-config
        L5-S1 flexion at 26.5 %).  docs/rom.md "Session 16"."""
        if self.embedded_ties is None or not len(self.embedded_ties[0]):
            return np.zeros(0, np.int64)
        return np.unique(np.asarray(self.embedded_ties[0], dtype=np.int64)[:, 1:])

    @property
    def n_elements(self) -> int:
        return sum(len(conn) for _, conn in self.element_blocks.values())

    def block_offsets(self) -> dict[str, int]:
        """0-based index of each block's first element in the concatenated element numbering."""
        offsets, start = {}, 0
        for name, (_, conn) in self.element_blocks.items():
            offsets[name] = start
            start += len(conn)
        return offsets


def _check_name(kind: str, name: str) -> None:
    if not isinstance(name, str) or not _NAME.match(name):
        raise ValueError(
            f"{kind} name {name!r} is not a valid Abaqus name (a letter, then up to 79 of "
            f"letters, digits, '_', '-', '.'; no spaces or commas)"
        )


def _check_indices(kind: str, name: str, idx: np.ndarray, n: int) -> np.ndarray:
    idx = np.asarray(idx)
    if idx.ndim != 1 or (idx.size and not np.issubdtype(idx.dtype, np.integer)):
        raise ValueError(f"{kind} {name!r} must be a 1-D integer index array, got shape {idx.shape} dtype {idx.dtype}")
    if idx.size == 0:
        raise ValueError(f"{kind} {name!r} is empty (Abaqus rejects empty sets)")
    if idx.min() < 0 or idx.max() >= n:
        raise ValueError(f"{kind} {name!r} has indices outside 0..{n - 1}")
    return idx.astype(np.int64)


def validate_model(model: FEModel) -> None:
    """Raise ValueError naming the first problem that would make the deck invalid or ambiguous."""
    nodes = np.asarray(model.nodes)
    if nodes.ndim != 2 or nodes.shape[1] != 3 or len(nodes) == 0:
        raise ValueError(f"nodes must be a non-empty (N, 3) array in mm, got shape {nodes.shape}")
    if not np.isfinite(nodes).all():
        raise ValueError(f"nodes contain {int((~np.isfinite(nodes)).any(axis=1).sum())} non-finite rows")
    if not model.element_blocks:
        raise ValueError("the model has no element blocks")
    n_nodes = len(nodes)
    for name, (etype, conn) in model.element_blocks.items():
        _check_name("element block", name)
        if etype in UNSUPPORTED_TYPES:
            raise ValueError(f"element block {name!r}: type {etype} is not supported ({UNSUPPORTED_TYPES[etype]})")
        if etype not in NODES_PER_ELEMENT:
            raise ValueError(
                f"element block {name!r}: unknown element type {etype!r}; supported: {sorted(NODES_PER_ELEMENT)}"
            )
        conn = np.asarray(conn)
        k = NODES_PER_ELEMENT[etype]
        if conn.ndim != 2 or conn.shape[1] != k or len(conn) == 0:
            raise ValueError(
                f"element block {name!r}: {etype} needs a non-empty (E, {k}) connectivity, got shape {conn.shape}"
            )
        if not np.issubdtype(conn.dtype, np.integer):
            raise ValueError(f"element block {name!r}: connectivity must be integer, got {conn.dtype}")
        if conn.min() < 0 or conn.max() >= n_nodes:
            raise ValueError(f"element block {name!r}: node indices outside 0..{n_nodes - 1}")
    if model.midside_ties is not None and len(model.midside_ties):
        mid = np.asarray(model.midside_ties)
        if mid.ndim != 2 or mid.shape[1] != 3 or not np.issubdtype(mid.dtype, np.integer):
            raise ValueError(f"midside_ties must be a (K, 3) integer array [m, a, b], got shape {mid.shape}")
    if model.embedded_ties is not None:
        ids, w = (np.asarray(a) for a in model.embedded_ties)
        if ids.ndim != 2 or w.shape != (len(ids), ids.shape[1] - 1) or not np.issubdtype(ids.dtype, np.integer):
            raise ValueError(
                f"embedded_ties must be (K, 1 + m) integer ids and (K, m) weights, got {ids.shape}, {w.shape}"
            )
    ties = model.ties()
    if ties:
        ids = [t[0] for t in ties]
        if min(t.min() for t in ids) < 0 or max(t.max() for t in ids) >= n_nodes:
            raise ValueError(f"ties have node indices outside 0..{n_nodes - 1}")
        dependent = np.concatenate([t[:, 0] for t in ids])
        independent = np.concatenate([t[:, 1:].ravel() for t in ids])
        if len(np.unique(dependent)) != len(dependent) or np.isin(dependent, independent).any():
            # ccx removes a dependent DOF from the system: it may appear once, and never as an independent term
            raise ValueError("ties: a dependent node appears twice or also as an independent node")
    n_el = model.n_elements
    for name, idx in model.node_sets.items():
        _check_name("node set", name)
        _check_indices("node set", name, idx, n_nodes)
    block_names = {b.upper() for b in model.element_blocks}
    for name, idx in model.element_sets.items():
        _check_name("element set", name)
        if name.upper() in block_names:
            # meshio would merge the *ELEMENT ELSET and the *ELSET of the same name unpredictably
            raise ValueError(f"element set {name!r} has the name of an element block")
        _check_indices("element set", name, idx, n_el)
    mat_names = set()
    for mat in model.materials:
        _check_name("material", mat.name)
        if mat.name.upper() in mat_names:
            raise ValueError(f"material {mat.name!r} is defined twice")
        mat_names.add(mat.name.upper())
        if isinstance(mat, MooneyRivlin) and not mat.d1_per_mpa > 0:
            raise ValueError(
                f"material {mat.name!r}: Mooney-Rivlin D1 must be > 0 (ccx replaces D1 = 0 by a "
                f"default compressibility, so the two solvers would disagree)"
            )
        if isinstance(mat, LinearElastic) and not (mat.youngs_modulus_mpa > 0 and -1 < mat.poisson_ratio < 0.5):
            raise ValueError(f"material {mat.name!r}: needs E > 0 MPa and -1 < Poisson ratio < 0.5")
    orientation_names = set()
    for o in model.orientations:
        _check_name("orientation", o.name)
        a, b = np.asarray(o.axis_a_mm, float), np.asarray(o.axis_b_mm, float)
        if a.shape != (3,) or b.shape != (3,) or not np.isfinite([a, b]).all() or np.linalg.norm(b - a) <= 0:
            raise ValueError(f"orientation {o.name!r} needs two distinct finite axis points (mm)")
        orientation_names.add(o.name.upper())
    elsets = {
        **{b.upper(): model.element_blocks[b][0] for b in model.element_blocks},
        **{s.upper(): None for s in model.element_sets},
    }
    for sec in model.sections:
        if sec.elset.upper() not in elsets:
            raise ValueError(f"section refers to unknown element set {sec.elset!r}")
        types = _types_of_elset(model, sec.elset)
        if len(types) != 1:
            raise ValueError(f"section on {sec.elset!r} spans element types {sorted(types)}; one type per section")
        etype = types.pop()
        if etype == "SPRINGA":
            table = np.asarray(sec.spring_force_elongation if sec.spring_force_elongation is not None else [])
            if table.ndim != 2 or table.shape[1] != 2 or len(table) < 2:
                raise ValueError(f"spring section on {sec.elset!r} needs a (K>=2, 2) force-elongation table")
            if np.any(np.diff(table[:, 1]) <= 0):
                raise ValueError(f"spring section on {sec.elset!r}: elongations must be strictly ascending")
            continue
        if etype == "GAPUNI":
            if sec.gap is None:
                raise ValueError(f"gap section on {sec.elset!r} needs gap=(clearance, direction, stiffness)")
            clearance, direction, stiffness = sec.gap
            if not (np.isfinite(clearance) and stiffness > 0 and abs(np.linalg.norm(direction) - 1) < 1e-6):
                raise ValueError(
                    f"gap section on {sec.elset!r}: needs a finite clearance (mm), a unit direction "
                    f"and a stiffness > 0 N/mm, got {sec.gap}"
                )
            continue
        if sec.material is None or sec.material.upper() not in mat_names:
            raise ValueError(f"section on {sec.elset!r} refers to unknown material {sec.material!r}")
        if sec.orientation is not None and (
            etype not in SOLID_TYPES or sec.orientation.upper() not in orientation_names
        ):
            raise ValueError(
                f"section on {sec.elset!r}: orientation {sec.orientation!r} is unknown or the elements are not solids"
            )
        if etype in SHELL_TYPES and not (sec.thickness_mm and sec.thickness_mm > 0):
            raise ValueError(f"shell section on {sec.elset!r} needs thickness_mm > 0")
        if etype == "T3D2" and not (sec.area_mm2 and sec.area_mm2 > 0):
            raise ValueError(f"truss section on {sec.elset!r} needs area_mm2 > 0")


def _types_of_elset(model: FEModel, elset: str) -> set[str]:
    for b, (etype, _) in model.element_blocks.items():
        if b.upper() == elset.upper():
            return {etype}
    idx = next(v for k, v in model.element_sets.items() if k.upper() == elset.upper())
    offsets = model.block_offsets()
    starts = np.array(list(offsets.values()))
    block_of = np.searchsorted(starts, np.asarray(idx), side="right") - 1
    types = [t for t, _ in model.element_blocks.values()]
    return {types[i] for i in np.unique(block_of)}


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
    etype = _types_of_elset(model, sec.elset).pop()
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
    """The model's deck as text (see module docstring for the dialect)."""
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


# --- template decks ----------------------------------------------------------------------------------

_NODE_KEYWORD = re.compile(r"^\*NODE\s*(,[^\n]*)?$", re.IGNORECASE | re.MULTILINE)
_NEXT_KEYWORD = re.compile(r"^\*(?!\*)", re.MULTILINE)


@dataclass(frozen=True)
class InpTemplate:
    """A deck split around its *NODE data lines: head (up to and including the *NODE keyword line),
    node ids in file order, tail (from the next keyword on)."""

    head: str
    node_ids: np.ndarray
    tail: str
    decimals: int


def _node_block_span(text: str) -> tuple[int, int]:
    """Character span of the data lines of the deck's only *NODE block."""
    heads = list(_NODE_KEYWORD.finditer(text))
    if not heads:
        raise ValueError("deck has no *NODE block")
    if len(heads) > 1:
        raise ValueError(f"deck has {len(heads)} *NODE blocks; exactly one is supported")
    data_start = heads[0].end() + 1
    nxt = _NEXT_KEYWORD.search(text, data_start)
    return data_start, (nxt.start() if nxt else len(text))


def _parse_node_block(block: str) -> np.ndarray:
    # comment lines inside the block would be lost by a substitution; refuse rather than drop them
    if "**" in block:
        raise ValueError("*NODE block contains comment lines; remove them first")
    values = np.array(block.replace(",", " ").split(), dtype=np.float64)
    if values.size == 0 or values.size % 4:
        raise ValueError("*NODE block must hold lines 'id, x, y, z' (3-D nodes)")
    return values.reshape(-1, 4)


def parse_template(template: str | Path, decimals: int | None = None) -> InpTemplate:
    """Split a deck (text, or path to a file) around its single *NODE block.

    decimals: precision for substituted coordinates; default = that of the template's first node line.
    """
    text = _read_text(template)
    data_start, data_end = _node_block_span(text)
    block = text[data_start:data_end]
    table = _parse_node_block(block)
    if decimals is None:
        first = block.lstrip("\n").split("\n", 1)[0].split(",")[1].strip()
        decimals = len(first.partition(".")[2]) if ("." in first and "e" not in first.lower()) else 6
    return InpTemplate(text[:data_start], table[:, 0].astype(np.int64), text[data_end:], int(decimals))


def _read_text(template: str | Path) -> str:
    if isinstance(template, Path) or ("\n" not in template and len(template) < 4096):
        path = Path(template)
        if not path.is_file():
            raise ValueError(f"template deck {path} does not exist")
        return path.read_text()
    return template


def substitute_coordinates(
    template: str | Path | InpTemplate, points_mm: np.ndarray, out_path: str | Path | None = None
) -> str:
    """A model's deck = the template deck with only its *NODE data lines replaced by `points_mm`.

    points_mm: (N, 3) coordinates in mm, in the template's node order.  Node ids, elements, sets,
    materials and every other byte of the template stay identical.  Returns the text; writes it to
    `out_path` when given.  Pass a parsed `InpTemplate` when substituting many models.
    """
    tpl = template if isinstance(template, InpTemplate) else parse_template(template)
    points_mm = np.asarray(points_mm, dtype=np.float64)
    if points_mm.shape != (len(tpl.node_ids), 3):
        raise ValueError(
            f"points must have shape ({len(tpl.node_ids)}, 3) to match the template's nodes, got {points_mm.shape}"
        )
    if not np.isfinite(points_mm).all():
        raise ValueError("points contain non-finite coordinates")
    text = tpl.head + format_node_lines(tpl.node_ids, points_mm, tpl.decimals) + tpl.tail
    if out_path is not None:
        write_text_atomic(out_path, text)
    return text


def read_inp_nodes(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Node ids (N,) int64 and coordinates (N, 3) mm of a deck's single *NODE block."""
    text = Path(path).read_text()
    data_start, data_end = _node_block_span(text)
    table = _parse_node_block(text[data_start:data_end])
    return table[:, 0].astype(np.int64), table[:, 1:]


def read_inp(path: str | Path):
    """meshio.Mesh of a deck, with SPRINGA and GAPUNI elements read as 'line' cells.

    meshio 5.3.5's Abaqus reader knows neither and raises on them; they are registered in meshio's type
    table (additive, idempotent entries) so ligaments, connectors and facet gaps read back as 2-node lines.
    """
    import meshio
    from meshio.abaqus import _abaqus

    for etype in ("SPRINGA", "GAPUNI"):
        _abaqus.abaqus_to_meshio_type.setdefault(etype, "line")
    return meshio.read(path, file_format="abaqus")


def write_vtu(model: FEModel, path: str | Path) -> Path:
    """Write the model as .vtu via meshio: one cell block per element block (hexes stay VTK_HEXAHEDRON,
    same node order), cell data `element_id` (the deck's 1-based id) and `block` (block number)."""
    import meshio

    validate_model(model)
    cells, element_id, block = [], [], []
    first = 1
    for i, (_name, (etype, conn)) in enumerate(model.element_blocks.items()):
        conn = np.asarray(conn, dtype=np.int64)
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
