"""From the hex template (+ any model's node coordinates) to an Abaqus/CalculiX deck, STL and VTU.

Materials (units MPa, mm, N) come from the config's ``fe:`` block (`materials_from_config`); the defaults
below equal config/config.yaml, each with its literature source:

* vertebral bodies linear elastic, cortical shell and cancellous core as separate sets (Goel et al. 1995,
  Shirazi-Adl et al. 1986: 12000 / 100 MPa); posterior-element shells cortical, 1 mm;
* cartilage endplates linear elastic (Lu et al. 1996: 24 MPa, 0.4);
* nucleus Mooney-Rivlin, nearly incompressible (Schmidt et al. 2007, Clin Biomech 22:377: C10 0.12,
  C01 0.03 MPa); D1 > 0 because ccx replaces D1 = 0 by its own default;
* annulus: Neo-Hooke ground substance (*HYPERELASTIC, NEO HOOKE, material ``AF``) with two collagen fibre
  families at +-angle to the transverse plane in the circumferential-axial plane of each disc's cylindrical
  system, as tension-only springs embedded in the annulus hexes (`spinecohort.fe.fibres`, the default): per hex
  and family one SPRINGA spring (block ``FIBRES``, element sets ``FIB_<k>`` per force table) whose end nodes are
  tied inside the hex by *EQUATION, with the Holzapfel-Gasser-Ogden fibre force of the hex's volume (k1, k2).
  Optionally a radial gradient of k1 (fibre content grows inner -> outer, Schmidt et al. 2006), linear over the
  template's annulus rings (`annulus_ring_k1`).  ``fibre_model="elastic_fiber"`` instead writes CalculiX's
  built-in ``ELASTIC_FIBER`` user material (constants C10, D1, then ax, ay, k1, k2 per family, in a cylindrical
  *ORIENTATION per disc: 1 radial, 2 circumferential, 3 axial; with a gradient one set ``D_<disc>_AF_R<k>`` and
  material ``ELASTIC_FIBER_AF_R<k>`` per ring), which aborts ccx 2.20 at random fibre states (docs/rom.md);
* ligaments tension-only bilinear springs (SPRINGA, *SPRING NONLINEAR): Young's moduli below/above a
  transition strain and cross-section areas of Goel et al. 1995 (as tabulated in Kim et al. 2013, BMC
  Musculoskelet Disord 14:220, Table 1); the anterior longitudinal ligament (ALL) is a seventh group,
  switchable.  A spring's table is force vs elongation, so it depends on the ligament's rest length: the
  export deck uses one table per group at the group's mean rest length in the model; the ROM decks
  (`spinecohort.rom.submodel`) use one table per ligament element.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from spinecohort.fe.abaqus import FEModel, LinearElastic, MooneyRivlin, NeoHooke, Orientation, Section, UserMaterial
from spinecohort.fe.facets import FacetContact
from spinecohort.fe.fibres import EmbeddedFibres, embedded_fibres
from spinecohort.fe.writers import write_inp, write_vtu
from spinecohort.mesh.template import LIGAMENT_GROUPS, RIM_TISSUE, HexTemplate


@dataclass(frozen=True)
class LigamentLaw:
    """Bilinear tension-only ligament: E below / above the transition strain (MPa), area (mm^2)."""

    e1_mpa: float
    e2_mpa: float
    transition_strain: float
    area_mm2: float


@dataclass(frozen=True)
class FEMaterials:
    """Every material constant of the FE models (MPa, 1/MPa, mm^2, deg)."""

    cortical: tuple[float, float] = (12000.0, 0.3)  # E MPa, nu
    cancellous: tuple[float, float] = (100.0, 0.2)
    cep: tuple[float, float] = (24.0, 0.4)
    shell_thickness_mm: float = 1.0  # posterior elements, sacrum, pelvis (S3, cortical material)
    nucleus: tuple[float, float, float] = (0.12, 0.03, 0.0111)  # C10, C01 MPa, D1 1/MPa (K 180 MPa)
    annulus_c10_mpa: float = 0.225
    annulus_d1_per_mpa: float = 0.688  # calibrated (config/config.yaml)
    # the ground substance's volumetric term (abaqus.NeoHooke): "quadratic" (J-1)^2/D1 or "logarithmic" (a barrier)
    annulus_volumetric: str = "quadratic"
    fibre_k1_mpa: float = 1.51
    # radial k1 gradient (`annulus_ring_k1`): k1 of the innermost / outermost annulus ring (MPa), linear in
    # between; None (both): the uniform fibre_k1_mpa
    fibre_k1_inner_mpa: float | None = None
    fibre_k1_outer_mpa: float | None = None
    fibre_k2: float = 11.0
    fibre_angle_deg: float = 46.0  # to the transverse plane, +- (two families); calibrated (config/config.yaml)
    # "springs": tension-only springs embedded in the annulus hexes (`spinecohort.fe.fibres`), Neo-Hooke ground
    # substance; "elastic_fiber": ccx's built-in ELASTIC_FIBER law (aborts at random fibre states, docs/rom.md)
    fibre_model: str = "springs"
    ligaments: dict[str, LigamentLaw] = field(default_factory=lambda: dict(DEFAULT_LIGAMENTS))
    include_all: bool = True  # the anterior longitudinal ligament (not among the seed's six groups)
    facets: FacetContact | None = FacetContact()  # facet-joint gaps (None: none), `spinecohort.fe.facets`

    def __post_init__(self):
        if (self.fibre_k1_inner_mpa is None) != (self.fibre_k1_outer_mpa is None):
            raise ValueError("the fibre k1 gradient needs both its inner and its outer k1 (or neither)")
        if self.fibre_model not in FIBRE_MODELS:
            raise ValueError(f"fibre model {self.fibre_model!r}: one of {FIBRE_MODELS}")

    @property
    def fibre_springs(self) -> bool:
        """Whether the annulus fibres are embedded springs (else ccx's ELASTIC_FIBER law)."""
        return self.fibre_model == "springs"

    @property
    def k1_graded(self) -> bool:
        """Whether the annulus has a radial k1 gradient (per-ring sets and materials)."""
        return self.fibre_k1_inner_mpa is not None

    def annulus_constants(self, k1_mpa: float | None = None) -> tuple[float, ...]:
        """ELASTIC_FIBER constants: C10, D1, then (ax, ay, k1, k2) per family in the cylindrical system
        (a = fibre direction; ccx sets az = +sqrt(1 - ax^2 - ay^2), the axial component).  k1_mpa: a ring's
        k1 (default the uniform fibre_k1_mpa)."""
        c = float(np.cos(np.radians(self.fibre_angle_deg)))  # circumferential component; az = sin
        k1 = self.fibre_k1_mpa if k1_mpa is None else float(k1_mpa)
        return (
            self.annulus_c10_mpa,
            self.annulus_d1_per_mpa,
            0.0,
            float(c),
            k1,
            self.fibre_k2,
            0.0,
            float(-c),
            k1,
            self.fibre_k2,
        )


FIBRE_MODELS = ("springs", "elastic_fiber")
#: the annulus ground substance's material with spring fibres (Neo-Hooke)
ANNULUS_GROUND = "AF"

#: bilinear ligaments (E1, E2 MPa, transition strain, area mm^2): moduli of Goel et al. 1995 via Kim et al. 2013;
#: areas calibrated inside the published range (config/config.yaml, docs/rom.md): ALL and CL Goel's, the others
#: the low end (doi:10.1155/2020/8858686 Table 2)
DEFAULT_LIGAMENTS = {
    "ALL": LigamentLaw(7.8, 20.0, 0.12, 63.7),
    "PLL": LigamentLaw(10.0, 20.0, 0.11, 7.0),
    "LF": LigamentLaw(15.0, 19.5, 0.062, 14.1),
    "CL": LigamentLaw(7.5, 32.9, 0.25, 30.0),
    "ITL": LigamentLaw(10.0, 58.7, 0.18, 0.6),
    "ISL": LigamentLaw(10.0, 11.6, 0.14, 14.1),
    "SSL": LigamentLaw(8.0, 15.0, 0.20, 10.5),
}
DEFAULT_MATERIALS = FEMaterials()
ANNULUS_MATERIAL = "ELASTIC_FIBER_AF"  # ccx selects its built-in law by this name prefix
#: the annulus' element of every deck: ccx 2.20's ELASTIC_FIBER law aborts with C3D8/C3D8I, and now and then with
#: C3D20R (docs/rom.md "Element choice")
DISC_HEX_TYPE = "C3D8R"
#: the nucleus' element: quadratic, tied to the annulus and endplates by midside *EQUATIONs (`spinecohort.fe.quadratic`).
#: A C3D8R nucleus leaked moment (the T10-S1 base carried 87 % of 7.5 N.m), C3D8 locks it (docs/moment_check.md)
NUCLEUS_HEX_TYPE = "C3D20R"
#: hex sets (by name suffix) of the disc soft tissue, the elements after the bone's: the annulus (``disc_hex_type``)
#: and the nucleus (``nucleus_hex_type``, its own block when it differs; see `hex_blocks`)
DISC_TYPE_TISSUES: tuple[str, ...] = ("_AF", "_NP")


def disc_hexes(template: HexTemplate, tissues: tuple[str, ...] = DISC_TYPE_TISSUES) -> np.ndarray:
    """(E,) bool: the template's hexes of the disc soft tissue (`DISC_TYPE_TISSUES`; ``("_NP",)``: the nucleus)."""
    disc = np.zeros(len(template.hexes), bool)
    for name, idx in template.elsets.items():
        if template.elset_kind[name] == "hex" and name.endswith(tissues):
            disc[idx] = True
    return disc


def hex_blocks(
    template: HexTemplate,
    hex_ids: np.ndarray,
    hex_type: str,
    disc_hex_type: str | None,
    nucleus_hex_type: str | None = None,
) -> tuple[np.ndarray, dict[str, tuple[str, np.ndarray]]]:
    """Order the template hexes `hex_ids` into element blocks by element type: ``HEXES`` (bone, cartilage
    endplates: `hex_type`), ``HEXES_DISC`` (annulus, and the nucleus unless it differs: `disc_hex_type`,
    None = `hex_type`), ``HEXES_NP`` (the nucleus when `nucleus_hex_type` differs from the annulus'), each in
    template order.  Returns the reordered ids and {block: (type, (E, 8) template node indices)} in that order."""
    disc_hex_type = disc_hex_type or hex_type
    nucleus_hex_type = nucleus_hex_type or disc_hex_type
    hex_ids = np.asarray(hex_ids, dtype=np.int64)
    disc, nucleus = disc_hexes(template)[hex_ids], disc_hexes(template, ("_NP",))[hex_ids]
    kind = np.where(disc & (nucleus_hex_type != disc_hex_type) & nucleus, 2, np.where(disc, 1, 0))
    if disc_hex_type == hex_type:
        kind[kind == 1] = 0
    order = hex_ids[np.argsort(kind, kind="stable")]
    names = {0: ("HEXES", hex_type), 1: ("HEXES_DISC", disc_hex_type), 2: ("HEXES_NP", nucleus_hex_type)}
    bounds = np.concatenate([[0], np.cumsum(np.bincount(kind, minlength=3))])
    blocks = {
        names[k][0]: (names[k][1], template.hexes[order[bounds[k] : bounds[k + 1]]])
        for k in range(3)
        if bounds[k + 1] > bounds[k]
    }
    return order, blocks


#: node sets by which an exported deck is fixed, in order of preference
FIXED_SETS = ("PELVIS", "EP_SUP_S1")


def _optional_float(value) -> float | None:
    return None if value is None else float(value)


def annulus_rings(template: HexTemplate) -> np.ndarray:
    """The O-grid rings of the annulus, inner -> outer (coarse template: 2, 3; ring 3 the thin outer lamella)."""
    return np.arange(template.grid.np_ring + 1, template.grid.shell_ring + 1)


def annulus_ring_k1(template: HexTemplate, mats: FEMaterials) -> dict[int, float]:
    """{ring: k1 MPa} of the radial fibre-stiffness gradient: fibre_k1_inner_mpa on the innermost annulus ring,
    fibre_k1_outer_mpa on the outermost, linear in the ring index in between; {} when k1 is uniform."""
    if not mats.k1_graded:
        return {}
    rings = annulus_rings(template)
    t = (rings - rings[0]) / max(len(rings) - 1, 1)
    k1 = mats.fibre_k1_inner_mpa + t * (mats.fibre_k1_outer_mpa - mats.fibre_k1_inner_mpa)
    return {int(r): float(k) for r, k in zip(rings, k1)}


def annulus_material(ring: int | None = None) -> str:
    """Material name of the annulus (ring None) or of one annulus ring of a k1 gradient."""
    return ANNULUS_MATERIAL if ring is None else f"{ANNULUS_MATERIAL}_R{ring}"


def annulus_ring_sets(template: HexTemplate, mats: FEMaterials) -> dict[str, dict[str, np.ndarray]]:
    """With a k1 gradient: each disc's annulus set -> its per-ring sets, ``D_<disc>_AF`` -> {``D_<disc>_AF_R<k>``:
    template hex ids}, rings inner -> outer; {} when k1 is uniform (the decks keep ``D_<disc>_AF``)."""
    rings = annulus_ring_k1(template, mats)
    if not rings or mats.fibre_springs:  # spring fibres carry their ring's k1 themselves
        return {}
    ring_of_hex = template.grid.quad_ring[np.arange(len(template.hexes)) % len(template.grid.quads)]
    out = {}
    for name, idx in template.elsets.items():
        if template.elset_kind[name] == "hex" and name.endswith("_AF"):
            out[name] = {f"{name}_R{r}": idx[ring_of_hex[idx] == r] for r in rings}
    return out


def materials_from_config(fe: dict | None) -> FEMaterials:
    """FEMaterials from the config's ``fe:`` block (None -> the defaults, equal to config/config.yaml)."""
    if fe is None:
        return DEFAULT_MATERIALS
    ligs = {
        g: LigamentLaw(float(v["E1_mpa"]), float(v["E2_mpa"]), float(v["transition_strain"]), float(v["area_mm2"]))
        for g, v in fe["ligaments"].items()
    }
    missing = set(LIGAMENT_GROUPS) - set(ligs)
    if missing:
        raise ValueError(f"fe.ligaments lacks the groups {sorted(missing)}")
    af, fib, np_ = fe["annulus"], fe["annulus"]["fibres"], fe["nucleus"]
    return FEMaterials(
        cortical=(float(fe["cortical"]["E_mpa"]), float(fe["cortical"]["nu"])),
        cancellous=(float(fe["cancellous"]["E_mpa"]), float(fe["cancellous"]["nu"])),
        cep=(float(fe["cep"]["E_mpa"]), float(fe["cep"]["nu"])),
        shell_thickness_mm=float(fe["shell_thickness_mm"]),
        nucleus=(float(np_["c10_mpa"]), float(np_["c01_mpa"]), float(np_["d1_per_mpa"])),
        annulus_c10_mpa=float(af["c10_mpa"]),
        annulus_d1_per_mpa=float(af["d1_per_mpa"]),
        annulus_volumetric=str(af.get("volumetric", "quadratic")),
        fibre_k1_mpa=float(fib["k1_mpa"]),
        fibre_k1_inner_mpa=_optional_float(fib.get("k1_inner_mpa")),
        fibre_k1_outer_mpa=_optional_float(fib.get("k1_outer_mpa")),
        fibre_k2=float(fib["k2"]),
        fibre_angle_deg=float(fib["angle_deg"]),
        fibre_model=str(fib.get("model", "springs")),
        ligaments=ligs,
        include_all=bool(fe["include_all"]),
        facets=FacetContact.from_config(fe.get("facets")),  # None: a release made before facets were exported
    )


def ligament_force_n(law: LigamentLaw, strain: np.ndarray, toe_strain: float = 0.01, blend: float = 0.2) -> np.ndarray:
    """Tension-only ligament force (N) at the given engineering strains: the bilinear law (E1 A up to the
    transition strain, E2 A beyond) with its two corners rounded so that the slope is continuous (C1):
    a quadratic toe from 0 to `toe_strain` (slope 0 -> E1 A; the linear part shifts by E1 A toe / 2, a
    physiological toe region) and a quadratic blend over +-`blend` x the transition strain.  ccx's Newton
    iterations cycled between the two slopes of a sharp corner (docs/rom.md)."""
    e = np.asarray(strain, dtype=np.float64)
    a1, a2 = law.e1_mpa * law.area_mm2, law.e2_mpa * law.area_mm2
    et, w = law.transition_strain, blend * law.transition_strain

    def slope(x):  # piecewise-linear slope, integrated exactly below
        s = np.where(x < toe_strain, a1 * x / toe_strain, a1)
        ramp = np.clip((x - (et - w)) / (2 * w), 0.0, 1.0)
        return np.where(x <= 0, 0.0, s + (a2 - a1) * ramp)

    # the slope is linear between its breakpoints, so the trapezoid rule on a grid holding the breakpoints
    # and the query strains integrates it exactly
    grid = np.unique(np.concatenate([[0.0, toe_strain, et - w, et + w], np.clip(e.ravel(), 0.0, None)]))
    f = np.concatenate([[0.0], np.cumsum(0.5 * (slope(grid[1:]) + slope(grid[:-1])) * np.diff(grid))])
    return np.where(e <= 0, 0.0, np.interp(e, grid, f))


def ligament_table(
    law: LigamentLaw, rest_length_mm: float, max_strain: float = 2.0, toe_strain: float = 0.01, blend: float = 0.2
) -> tuple[tuple[float, float], ...]:
    """(force N, elongation mm) pairs, ascending, of `ligament_force_n` for a spring of the given rest
    length: zero force in compression (tension only in an NLGEOM step), 6 points across the toe and the
    transition each, extended to `max_strain` (ccx holds the force constant past the table's end)."""
    if not rest_length_mm > 0:
        raise ValueError(f"ligament rest length must be > 0 mm, got {rest_length_mm}")
    et, w = law.transition_strain, blend * law.transition_strain
    strains = np.unique(np.concatenate([np.linspace(0.0, toe_strain, 7), np.linspace(et - w, et + w, 7), [max_strain]]))
    strains = strains[(strains >= 0) & (strains <= max_strain)]
    force = ligament_force_n(law, strains, toe_strain, blend)
    rows = [(0.0, -float(rest_length_mm))] + [(float(f), float(e * rest_length_mm)) for f, e in zip(force, strains)]
    return tuple(rows)


def material_cards(mats: FEMaterials, template: HexTemplate | None = None) -> list:
    """The named materials every deck carries: CORTICAL, CANCELLOUS, CEP, NP, ELASTIC_FIBER_AF (with a k1
    gradient instead one ELASTIC_FIBER_AF_R<k> per annulus ring of `template`, `annulus_ring_k1`)."""
    cards = [
        LinearElastic("CORTICAL", *mats.cortical),
        LinearElastic("CANCELLOUS", *mats.cancellous),
        LinearElastic("CEP", *mats.cep),
        MooneyRivlin("NP", *mats.nucleus),
    ]
    ground = NeoHooke(ANNULUS_GROUND, mats.annulus_c10_mpa, mats.annulus_d1_per_mpa, mats.annulus_volumetric)
    if mats.fibre_springs:
        return cards + [ground]
    if template is not None and any(name.endswith("_" + RIM_TISSUE) for name in template.elsets):
        raise ValueError(
            "a partial cartilage endplate (template.cep_diameter_fraction < 1) needs fe.annulus.fibres.model: springs: "
            "its rim insertion D_<disc>_RIM sits in the bone's C3D8 block, where ccx's fibre law aborts, and without "
            "fibres it is a soft shear layer between the annulus and the bone (docs/rom.md, Session 15)"
        )
    if not mats.k1_graded:
        return cards + [UserMaterial(ANNULUS_MATERIAL, mats.annulus_constants())]
    if template is None:
        raise ValueError("a k1 gradient's materials need the template (its annulus rings)")
    rings = annulus_ring_k1(template, mats)
    return cards + [UserMaterial(annulus_material(r), mats.annulus_constants(k)) for r, k in rings.items()]


def disc_orientations(template: HexTemplate, points: np.ndarray) -> dict[str, Orientation]:
    """Cylindrical fibre system per disc ('D_L4L5' -> OR_D_L4L5): axis from the centre of the disc's lower
    bounding node layer to the centre of its upper one (mm)."""
    from spinecohort.mesh.template import disc_runs

    n2 = len(template.grid.nodes)
    out = {}
    for first, end in disc_runs(template.layers):
        name = "D_" + template.layers[first]["disc"].replace("-", "")
        lo = points[(first - 1) * n2 : first * n2].mean(0)
        hi = points[end * n2 : (end + 1) * n2].mean(0)
        out[name] = Orientation(f"OR_{name}", tuple(map(float, lo)), tuple(map(float, hi)))
    return out


def hex_section(name: str, orientations: dict[str, Orientation] | None) -> Section:
    """Section of a template hex set (V_<lvl>_CORE/SHELL, D_<disc>_NP/AF/CEP/RIM) or of an annulus ring's set
    (D_<disc>_AF_R<k>, `annulus_ring_sets`: material ELASTIC_FIBER_AF_R<k>, the disc's orientation).
    orientations None: spring fibres, the annulus is its isotropic ground substance (material AF)."""
    parts = name.split("_")
    tissue = parts[-1]
    if orientations is not None:  # ccx's fibre law: the annulus material carries the fibres in the disc's system
        if parts[0] == "D" and len(parts) == 4 and parts[2] == "AF" and parts[3].startswith("R"):
            ring = int(parts[3][1:])
            orient = orientations["_".join(parts[:2])].name
            return Section(elset=name, material=annulus_material(ring), orientation=orient)
        if tissue == "AF":
            return Section(elset=name, material=ANNULUS_MATERIAL, orientation=orientations[name[:-3]].name)
    # AF with spring fibres: its ground substance, material ANNULUS_GROUND ("AF")
    material = {"CORE": "CANCELLOUS", "SHELL": "CORTICAL", RIM_TISSUE: ANNULUS_GROUND}.get(tissue, tissue)
    return Section(elset=name, material=material)


def annulus_fibres(
    template: HexTemplate, points: np.ndarray, mats: FEMaterials, hex_ids: np.ndarray | None = None
) -> EmbeddedFibres:
    """The fibre springs (`spinecohort.fe.fibres`) of the template's annulus hexes (only those in `hex_ids`, if
    given) at `points` (template node order, mm): each disc's cylindrical axis sets the directions, k1 per ring
    (`annulus_ring_k1`) or uniform.  Hosts are template node ids."""
    orient = disc_orientations(template, points)
    ring_k1 = annulus_ring_k1(template, mats)
    ring_of_hex = template.grid.quad_ring[np.arange(len(template.hexes)) % len(template.grid.quads)]
    ids, axis_a, axis_b = [], [], []
    for name, idx in template.elsets.items():
        # the annulus and its insertion into the bony rim (a partial CEP's D_<disc>_RIM): the fibres reach the bone
        if template.elset_kind[name] != "hex" or not name.endswith(("_AF", "_" + RIM_TISSUE)):
            continue
        if hex_ids is not None:
            idx = idx[np.isin(idx, hex_ids)]
        o = orient[name.rsplit("_", 1)[0]]
        ids.append(idx)
        axis_a.append(np.broadcast_to(o.axis_a_mm, (len(idx), 3)))
        axis_b.append(np.broadcast_to(o.axis_b_mm, (len(idx), 3)))
    ids = np.concatenate(ids)
    k1_of_ring = np.full(template.grid.shell_ring + 1, mats.fibre_k1_mpa)
    k1_of_ring[list(ring_k1)] = list(ring_k1.values())  # {} (uniform k1): unchanged
    k1 = k1_of_ring[ring_of_hex[ids]]
    return embedded_fibres(
        points,
        template.hexes[ids],
        np.concatenate(axis_a),
        np.concatenate(axis_b),
        k1,
        mats.fibre_k2,
        mats.fibre_angle_deg,
    )


def add_fibres(
    pts: np.ndarray,
    blocks: dict,
    elsets: dict,
    sections: list,
    fibres: EmbeddedFibres,
    node_of: np.ndarray | None = None,
) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray]]:
    """Append the fibre springs to a model being built: their end nodes after `pts`, a last SPRINGA block
    ``FIBRES`` with one element set and table per force bin (``FIB_<k>``).  node_of: template node id -> model
    node index (a submodel's renumbering; None: the same).  Returns the points and the ends' embedded ties."""
    n = len(pts)
    hosts = fibres.hosts if node_of is None else node_of[fibres.hosts]
    if (hosts < 0).any():
        raise ValueError("an annulus fibre's host hex has a node outside the model")
    first = sum(len(c) for _, c in blocks.values())
    blocks["FIBRES"] = ("SPRINGA", n + fibres.springs)
    for g, table in enumerate(fibres.tables):
        elsets[f"FIB_{g + 1}"] = first + np.flatnonzero(fibres.group == g)
        sections.append(Section(elset=f"FIB_{g + 1}", spring_force_elongation=table))
    ties = (np.column_stack([n + np.arange(len(fibres.points)), hosts]), fibres.weights)
    return np.concatenate([pts, fibres.points]), ties


def fe_model(
    template: HexTemplate,
    points: np.ndarray | None = None,
    hex_type: str = "C3D8",
    include_all: bool | None = None,
    heading: str = "spinecohort model",
    materials: FEMaterials | None = None,
    disc_hex_type: str | None = DISC_HEX_TYPE,
    connectors: bool = True,
    nucleus_hex_type: str | None = NUCLEUS_HEX_TYPE,
) -> FEModel:
    """The template as an FEModel with the given node coordinates (default: the template's own): one
    connected mechanical body (`spinecohort.fe.connections`).

    Element blocks, in this order: ``HEXES`` (bone, cartilage endplates: `hex_type`), ``HEXES_DISC`` (annulus:
    `disc_hex_type`, C3D8R; ccx 2.20's fibre law aborts with C3D8/C3D8I), ``HEXES_NP`` (nucleus: `nucleus_hex_type`,
    C3D20R with its midside nodes tied to its neighbours, `FEModel.midside_ties`; C3D8R leaks moment, C3D8
    locks), ``SURFACES`` (S3 skins), ``LIGAMENTS``
    (tension-only SPRINGA), ``CONNECTORS`` (linear SPRINGA, element sets ``CONN_*``; ``CONN_FACET_<lvl>`` hang the
    facet nodes on their vertebra), ``FACETS`` (facet-joint contact struts, SPRINGA, `spinecohort.fe.facets`; element sets
    ``FACET_*``), ``FIBRES`` (the annulus fibre springs, `spinecohort.fe.fibres`; element sets ``FIB_*``; none with
    ``fibre_model="elastic_fiber"``).  Nodes: the template's (ids 1..N, template order), then the facet nodes
    (materials.facets None: none), then the quadratic hexes' midside nodes, then the fibre springs' end nodes.  Hex elements are therefore numbered bone and endplates first,
    then annulus, then nucleus, each in template order.  Node sets: the template's plus ``PELVIS`` (where a user fixes the model). disc_hex_type None: the disc
    in ``HEXES`` (template order); connectors False: no ``CONNECTORS``
    (a deck of loose parts, for pictures only).
    materials: default `DEFAULT_MATERIALS` (= config/config.yaml); include_all overrides its switch.
    """
    from spinecohort.fe.connections import CONNECTOR_TABLE, model_connectors, posterior_wall, truss_pairs
    from spinecohort.fe.facets import facet_nodes, facet_pairs
    from spinecohort.fe.quadratic import quadratic_blocks

    mats = DEFAULT_MATERIALS if materials is None else materials
    include_all = mats.include_all if include_all is None else include_all
    pts = template.nodes if points is None else np.asarray(points, dtype=np.float64)
    if pts.shape != template.nodes.shape:
        raise ValueError(f"points have shape {pts.shape}, the template has {template.nodes.shape}")
    template_points = pts
    lig_keep = np.ones(len(template.ligaments), bool)
    if not include_all:
        lig_keep[template.elsets["LIG_ALL"]] = False
    hex_order, blocks = hex_blocks(template, np.arange(len(template.hexes)), hex_type, disc_hex_type, nucleus_hex_type)
    pos_of_hex = np.empty(len(template.hexes), dtype=np.int64)
    pos_of_hex[hex_order] = np.arange(len(hex_order))
    blocks["SURFACES"] = ("S3", template.tris)
    blocks["LIGAMENTS"] = ("SPRINGA", template.ligaments[lig_keep])
    offset = {"hex": 0, "tri": len(template.hexes), "lig": len(template.hexes) + len(template.tris)}
    lig_new = np.cumsum(lig_keep) - 1
    elsets = {}
    ring_sets = annulus_ring_sets(template, mats)  # {} unless k1 is graded
    for name, idx in template.elsets.items():
        kind = template.elset_kind[name]
        if kind == "lig":
            idx = lig_new[idx[lig_keep[idx]]]
            if len(idx) == 0:
                continue
        elif kind == "hex":
            if name in ring_sets:
                for ring_name, ring_idx in ring_sets[name].items():
                    elsets[ring_name] = offset["hex"] + np.sort(pos_of_hex[ring_idx])
                continue
            idx = np.sort(pos_of_hex[idx])
        elsets[name] = offset[kind] + np.asarray(idx)
    conn_sets = model_connectors(template, template.nodes) if connectors else {}
    fn = None
    if connectors and mats.facets is not None and "LIG_CL" in template.elsets:
        # facet joints: new nodes after the template's (ids N+1..), each hung on its vertebra's posterior wall
        # by the arch truss (coordinate-free: the same springs in every model of the cohort)
        fn = facet_nodes(template, pts, facet_pairs(template), mats.facets)
        n = len(pts)
        for v, ix in fn.tied.items():
            conn_sets[f"CONN_FACET_{v}"] = truss_pairs(n + ix, posterior_wall(template, v))
    if conn_sets:
        first = offset["lig"] + int(lig_keep.sum())
        blocks["CONNECTORS"] = ("SPRINGA", np.concatenate(list(conn_sets.values())))
        for name, pairs in conn_sets.items():
            elsets[name] = np.arange(first, first + len(pairs))
            first += len(pairs)
    if fn is not None:
        first = sum(len(c) for _, c in blocks.values())
        blocks["FACETS"] = (fn.element_type, len(pts) + fn.gaps)
        for i, (_, name) in enumerate(fn.sections):
            elsets[name] = np.array([first + i])
    orientations = disc_orientations(template, pts)
    hex_orient = None if mats.fibre_springs else orientations
    sections = []
    for name, kind in template.elset_kind.items():
        if name in ring_sets:
            sections += [hex_section(ring_name, orientations) for ring_name in ring_sets[name]]
            continue
        if name not in elsets:
            continue
        if kind == "hex":
            sections.append(hex_section(name, hex_orient))
        elif kind == "tri":
            sections.append(Section(elset=name, material="CORTICAL", thickness_mm=mats.shell_thickness_mm))
        else:
            group = name.split("_", 1)[1]
            ends = pts[template.ligaments[template.elsets[name]]]
            rest = float(np.linalg.norm(ends[:, 1] - ends[:, 0], axis=1).mean())
            sections.append(Section(elset=name, spring_force_elongation=ligament_table(mats.ligaments[group], rest)))
    sections += [Section(elset=name, spring_force_elongation=CONNECTOR_TABLE) for name in conn_sets]
    if fn is not None:
        sections += fn.section_list()
        pts = np.concatenate([pts, fn.points])
    # quadratic hexes' midside nodes after every other node, tied to their linear neighbours (`fe.quadratic`)
    pts, blocks, ties = quadratic_blocks(pts, blocks)
    embedded = None
    if mats.fibre_springs:  # the annulus fibres, last nodes and last elements (`spinecohort.fe.fibres`)
        pts, embedded = add_fibres(pts, blocks, elsets, sections, annulus_fibres(template, template_points, mats))
    node_sets = dict(template.nsets)
    if "PELVIS" in template.elsets and "PELVIS" not in node_sets:
        node_sets["PELVIS"] = np.unique(template.tris[template.elsets["PELVIS"]])
    return FEModel(
        nodes=pts,
        element_blocks=blocks,
        node_sets=node_sets,
        element_sets=elsets,
        materials=material_cards(mats, template),
        sections=sections,
        heading=heading,
        orientations=[] if mats.fibre_springs else list(orientations.values()),
        midside_ties=ties,
        embedded_ties=embedded,
    )


def fixed_set(model: FEModel) -> str:
    """The node set a user fixes the exported deck by: ``PELVIS`` (else the S1 plate ``EP_SUP_S1``)."""
    for name in FIXED_SETS:
        if name in model.node_sets:
            return name
    raise ValueError(f"the model has none of the node sets {FIXED_SETS} to fix it by")


def write_deck(model: FEModel, path: str | Path, provenance: str = "") -> Path:
    """Write an exported deck after checking that it is one body: every element reachable from the fixed
    set (`fixed_set`) through load-carrying elements (`spinecohort.fe.connectivity`); raises
    ConnectivityError naming the deck and its loose parts otherwise."""
    check_deck(model, str(path))
    return write_inp(model, path, provenance=provenance)


def check_deck(model: FEModel, deck: str) -> None:
    """The connectivity check of every exported deck (see `write_deck`); deck: its name for the message."""
    from spinecohort.fe.connectivity import check_connected

    check_connected(model, model.node_sets[fixed_set(model)], deck)


def read_deck_points(deck: str | Path, template: HexTemplate) -> np.ndarray:
    """The template-node coordinates (n_nodes, 3) mm of an exported deck: its first N nodes, ids 1..N (the
    facet-joint nodes after them derive from these); ValueError naming the deck if it is not an export."""
    from spinecohort.fe.inp_template import read_inp_nodes

    ids, points = read_inp_nodes(deck)
    n = template.n_nodes
    if len(points) < n or not np.array_equal(ids[:n], np.arange(1, n + 1)):
        raise ValueError(
            f"{deck}: {len(points)} nodes with ids {ids[:3]}..., but the template has {n} nodes numbered 1..N "
            f"first: not an exported spinecohort deck of this template"
        )
    return points[:n]


def write_model_files(
    template: HexTemplate,
    points: np.ndarray,
    out: str | Path,
    fmt: str,
    heading: str = "spinecohort model",
    materials: FEMaterials | None = None,
) -> Path:
    """Write one model as ``inp`` (Abaqus/CalculiX deck) or ``vtu``."""
    model = fe_model(template, points, heading=heading, materials=materials)
    if fmt == "inp":
        return write_deck(model, out, provenance=heading)
    if fmt == "vtu":
        return write_vtu(model, out)
    raise ValueError(f"unknown FE format '{fmt}' (inp | vtu)")


__all__ = [
    "fe_model",
    "write_deck",
    "write_model_files",
    "ligament_table",
    "materials_from_config",
    "annulus_ring_k1",
    "FEMaterials",
    "LigamentLaw",
    "DEFAULT_MATERIALS",
    "LIGAMENT_GROUPS",
]
