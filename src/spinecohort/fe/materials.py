"""The materials of the FE models (units MPa, mm, N), from the config's ``fe:`` block (`materials_from_config`);
the defaults below equal config/config.yaml, each with its literature source:

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
  material ``ELASTIC_FIBER_AF_R<k>`` per ring), which aborts ccx 2.20 at random fibre states
  (docs/explanation/fe-model.md);
* ligaments tension-only bilinear springs (SPRINGA, *SPRING NONLINEAR): Young's moduli below/above a
  transition strain and cross-section areas of Goel et al. 1995 (as tabulated in Kim et al. 2013, BMC
  Musculoskelet Disord 14:220, Table 1); the anterior longitudinal ligament (ALL) is a seventh group,
  switchable.  Where the template builds ALL, PLL, LF and CL as fibre bundles, each fibre has the group's area
  divided by its fibre count (`fibre_law`).  At L1-L2 ... L5-S1 the segment's own force-elongation curves replace
  the group laws (`segment_ligaments`, config ``fe.lumbar_ligaments``: `spinecohort.fe.ligament_curves`; the table
  of a spring: `spring_table`).  A spring's table is force vs elongation, so it depends on the ligament's rest length: the
  export deck uses one table per group and segment at that segment's mean rest length in the model; the ROM decks
  (`spinecohort.rom.submodel`) use one table per ligament element.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from spinecohort.fe.abaqus import LinearElastic, MooneyRivlin, NeoHooke, UserMaterial
from spinecohort.fe.facets import FacetContact
from spinecohort.fe.ligament_curves import curve_table, load_segment_ligaments
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
    annulus_c10_mpa: float = 0.18
    annulus_d1_per_mpa: float = 0.3  # calibrated (config/config.yaml)
    # the ground substance's volumetric term (abaqus.NeoHooke): "quadratic" (J-1)^2/D1 or "logarithmic" (a barrier)
    annulus_volumetric: str = "quadratic"
    fibre_k1_mpa: float = 2.5
    # radial k1 gradient (`annulus_ring_k1`): k1 of the innermost / outermost annulus ring (MPa), linear in
    # between; None (both): the uniform fibre_k1_mpa
    fibre_k1_inner_mpa: float | None = None
    fibre_k1_outer_mpa: float | None = None
    fibre_k2: float = 89.6
    fibre_angle_deg: float = 49.0  # to the transverse plane, +- (two families); calibrated (config/config.yaml)
    # "springs": tension-only springs embedded in the annulus hexes (`spinecohort.fe.fibres`), Neo-Hooke ground
    # substance; "elastic_fiber": ccx's built-in ELASTIC_FIBER law (aborts at random fibre states, docs/explanation/fe-model.md)
    fibre_model: str = "springs"
    # springs per hex and family (`spinecohort.fe.fibres.QUADRATURE`): 1 at the hex's centre, 4 at its in-layer quarters
    fibre_springs_per_hex: int = 4
    ligaments: dict[str, LigamentLaw] = field(default_factory=lambda: dict(DEFAULT_LIGAMENTS))
    include_all: bool = True  # the anterior longitudinal ligament (not among the seed's six groups)
    #: (segment, group) -> the force-elongation curve that replaces the group's law there
    #: (`spinecohort.fe.ligament_curves`; config ``fe.lumbar_ligaments``, default Remus et al. 2021's L1-S1)
    segment_ligaments: dict = field(default_factory=lambda: load_segment_ligaments("remus2021"))
    facets: FacetContact | None = FacetContact()  # facet-joint gaps (None: none), `spinecohort.fe.facets`
    #: hexes along each pedicle (`spinecohort.fe.pedicles`); None: no pedicles, the arches hang on the posterior wall
    pedicle_layers: int | None = 3
    posterior_bone: tuple[float, float] = (3500.0, 0.25)  # E MPa, nu of the pedicles (posterior bony elements)

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
#: the pedicles' material (posterior bony elements, `spinecohort.fe.pedicles`)
POSTERIOR_BONE = "POSTERIOR"

#: bilinear ligaments (E1, E2 MPa, transition strain, area mm^2): moduli of Goel et al. 1995 via Kim et al. 2013;
#: areas calibrated inside the published range (config/config.yaml, docs/explanation/fe-model.md): ALL and CL Goel's, the others
#: the low end (doi:10.1155/2020/8858686 Table 2)
DEFAULT_LIGAMENTS = {
    "ALL": LigamentLaw(7.8, 20.0, 0.12, 63.7),
    "PLL": LigamentLaw(10.0, 20.0, 0.11, 7.0),
    "LF": LigamentLaw(15.0, 19.5, 0.062, 14.1),
    "CL": LigamentLaw(3.0, 32.9, 0.25, 30.0),
    "ITL": LigamentLaw(10.0, 58.7, 0.18, 40.5),
    "ISL": LigamentLaw(10.0, 11.6, 0.14, 14.1),
    "SSL": LigamentLaw(8.0, 15.0, 0.20, 10.5),
}
DEFAULT_MATERIALS = FEMaterials()
ANNULUS_MATERIAL = "ELASTIC_FIBER_AF"  # ccx selects its built-in law by this name prefix


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
        fibre_springs_per_hex=int(fib.get("springs_per_hex", 4)),
        ligaments=ligs,
        include_all=bool(fe["include_all"]),
        # absent (a release made before the per-segment curves) or null: the groups' laws at every segment
        segment_ligaments=load_segment_ligaments(fe["lumbar_ligaments"]) if fe.get("lumbar_ligaments") else {},
        facets=FacetContact.from_config(fe.get("facets")),  # None: a release made before facets were exported
        # absent: a release made before the pedicles were hexes (its arches hang on the posterior wall)
        pedicle_layers=int(fe["pedicles"]["layers"]) if fe.get("pedicles", {}).get("enabled") else None,
        posterior_bone=(
            (float(fe["pedicles"]["E_mpa"]), float(fe["pedicles"]["nu"])) if fe.get("pedicles") else (3500.0, 0.25)
        ),
    )


def fibre_law(law: LigamentLaw, fibres: int) -> LigamentLaw:
    """The law of one fibre of a ligament made of `fibres` equal fibres (`spinecohort.mesh.ligament_sites`): the
    ligament's area split equally, so the fibres under one uniform strain carry the single spring's force."""
    if fibres < 1:
        raise ValueError(f"a ligament needs at least one fibre, got {fibres}")
    return dataclasses.replace(law, area_mm2=law.area_mm2 / fibres)


def spring_table(
    mats: FEMaterials, group: str, segment: str, fibres: int, rest_length_mm: float
) -> tuple[tuple[float, float], ...]:
    """The force table of one fibre (of ``fibres``) of a ligament of ``group`` in ``segment`` (``"L5-S1"``): the
    segment's own curve where ``mats.segment_ligaments`` has one (`spinecohort.fe.ligament_curves`), else the
    group's bilinear law with the area split across the fibres (`fibre_law`, `ligament_table`)."""
    curve = mats.segment_ligaments.get((segment, group))
    if curve is not None:
        return curve_table(curve, fibres, rest_length_mm)
    return ligament_table(fibre_law(mats.ligaments[group], fibres), rest_length_mm)


def ligament_force_n(law: LigamentLaw, strain: np.ndarray, toe_strain: float = 0.01, blend: float = 0.2) -> np.ndarray:
    """Tension-only ligament force (N) at the given engineering strains: the bilinear law (E1 A up to the
    transition strain, E2 A beyond) with its two corners rounded so that the slope is continuous (C1):
    a quadratic toe from 0 to `toe_strain` (slope 0 -> E1 A; the linear part shifts by E1 A toe / 2, a
    physiological toe region) and a quadratic blend over +-`blend` x the transition strain.  ccx's Newton
    iterations cycled between the two slopes of a sharp corner (docs/explanation/fe-model.md)."""
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
    """The named materials every deck carries: CORTICAL, CANCELLOUS, CEP, POSTERIOR (the pedicles), NP, ELASTIC_FIBER_AF (with a k1
    gradient instead one ELASTIC_FIBER_AF_R<k> per annulus ring of `template`, `annulus_ring_k1`)."""
    cards = [
        LinearElastic("CORTICAL", *mats.cortical),
        LinearElastic("CANCELLOUS", *mats.cancellous),
        LinearElastic("CEP", *mats.cep),
        LinearElastic(POSTERIOR_BONE, *mats.posterior_bone),
        MooneyRivlin("NP", *mats.nucleus),
    ]
    ground = NeoHooke(ANNULUS_GROUND, mats.annulus_c10_mpa, mats.annulus_d1_per_mpa, mats.annulus_volumetric)
    if mats.fibre_springs:
        return cards + [ground]
    if template is not None and any(name.endswith("_" + RIM_TISSUE) for name in template.elsets):
        raise ValueError(
            "a partial cartilage endplate (template.cep_diameter_fraction < 1) needs fe.annulus.fibres.model: springs: "
            "its rim insertion D_<disc>_RIM sits in the bone's C3D8 block, where ccx's fibre law aborts, and without "
            "fibres it is a soft shear layer between the annulus and the bone (docs/explanation/fe-model.md)"
        )
    if not mats.k1_graded:
        return cards + [UserMaterial(ANNULUS_MATERIAL, mats.annulus_constants())]
    if template is None:
        raise ValueError("a k1 gradient's materials need the template (its annulus rings)")
    rings = annulus_ring_k1(template, mats)
    return cards + [UserMaterial(annulus_material(r), mats.annulus_constants(k)) for r, k in rings.items()]
