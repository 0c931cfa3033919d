"""The Abaqus/CalculiX vocabulary of the hexahedral spine models in memory: element types, materials,
sections, orientations, the `FEModel` that holds them, and its validation.

Decks use only what both Abaqus and CalculiX (ccx 2.20) accept: C3D8/C3D8I/C3D8R/C3D20/C3D20R hexes, S3/S4 shells,
SPRINGA springs, T3D2 trusses and GAPUNI gaps; *MATERIAL (*ELASTIC, *HYPERELASTIC MOONEY-RIVLIN / NEO HOOKE /
ARRUDA-BOYCE, *USER MATERIAL) and one section per element set.  Units: mm, N, MPa.

Conventions of `FEModel`: connectivity, node sets and element sets hold 0-based row indices (into
`nodes`, resp. into the concatenation of the element blocks in insertion order); the deck numbers nodes
and elements 1..N compactly, because ccx allocates memory by the largest node id, not the node count.
The deck text: `spinecohort.fe.writers`; template decks and reading: `spinecohort.fe.inp_template`.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field

import numpy as np

#: nodes per element of each supported Abaqus/CalculiX element type.
NODES_PER_ELEMENT = {
    "C3D8": 8,
    "C3D8I": 8,
    "C3D8R": 8,
    "C3D20": 20,
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
    "C3D20": "hexahedron20",  # same node order in VTK and Abaqus
    "C3D20R": "hexahedron20",
    "S3": "triangle",
    "S4": "quad",
    "S4R": "quad",
    "SPRINGA": "line",
    "T3D2": "line",
    "GAPUNI": "line",
}
SOLID_TYPES = {"C3D8", "C3D8I", "C3D8R", "C3D20", "C3D20R"}
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
        L5-S1 flexion at 26.5 %); docs/explanation/fe-model.md."""
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
        types = elset_types(model, sec.elset)
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


def elset_types(model: FEModel, elset: str) -> set[str]:
    for b, (etype, _) in model.element_blocks.items():
        if b.upper() == elset.upper():
            return {etype}
    idx = next(v for k, v in model.element_sets.items() if k.upper() == elset.upper())
    offsets = model.block_offsets()
    starts = np.array(list(offsets.values()))
    block_of = np.searchsorted(starts, np.asarray(idx), side="right") - 1
    types = [t for t, _ in model.element_blocks.values()]
    return {types[i] for i in np.unique(block_of)}


def without_elements(model: FEModel, drop: np.ndarray) -> FEModel:
    """`model` without the elements of the 0-based index array `drop` (into the concatenated blocks): each block
    keeps its other elements in order, every element set is renumbered, and a set (and its section) left with no
    element is removed.  Nodes stay as they are (a node of no element carries nothing in a ccx solve)."""
    import dataclasses

    n_el = model.n_elements
    if not len(drop):
        return model
    keep = np.ones(n_el, bool)
    keep[_check_indices("element", "drop", np.asarray(drop, dtype=np.int64), n_el)] = False
    new_id = np.cumsum(keep) - 1
    offsets = model.block_offsets()
    blocks = {}
    for name, (etype, conn) in model.element_blocks.items():
        kept = conn[keep[offsets[name] : offsets[name] + len(conn)]]
        if len(kept):
            blocks[name] = (etype, kept)
    sets = {}
    for name, idx in model.element_sets.items():
        idx = np.asarray(idx, dtype=np.int64)
        idx = new_id[idx[keep[idx]]]
        if len(idx):
            sets[name] = idx
    live = {name.upper() for name in (*sets, *blocks)}
    sections = [s for s in model.sections if s.elset.upper() in live]
    return dataclasses.replace(model, element_blocks=blocks, element_sets=sets, sections=sections)
