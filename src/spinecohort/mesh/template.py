"""The hexahedral FE template of the osteo-ligamentous thoracolumbar spine.

Structure (all node ids 0-based here; the Abaqus export makes them 1-based):

* One structured **O-grid** cross-section (a square core block plus rings out to a superellipse) is shared
  by every vertebral body and every disc, and the column T1 ... S1 is one extruded stack of it.  Vertebral
  bodies and discs therefore share their interface node layers: the mesh is conforming, with no tie
  constraints.  The outermost ring of a body is its cortical shell (own element set); inside it is the
  cancellous core.
* Each **disc** has a cartilage endplate (CEP) layer at the top and bottom (0.7 mm, the seed's value), and
  in between the nucleus pulposus (NP: the core and inner rings, ~40 % of the cross-section area) and the
  annulus fibrosus (AF: the outer rings, in radial layers).  ``cep_diameter_fraction`` < 1 makes the CEP cover
  the central endplate only and the outer rings of the CEP layers the annulus' insertion into the bony rim
  (``D_<disc>_RIM``, as in vivo): annulus with its fibre springs (the fibres insert into the bone), in the
  bone's element type, the disc's node layers evenly spaced outside the cartilage (docs/explanation/hex-mesh.md:
  without fibres the rim is a soft shear layer between the fibred annulus and the bone, and the thoracic
  units' axial rotation doubles; as a 0.7 mm layer its hexes invert next to the potted vertebra).
  Disc node layers are always placed by interpolation between the two adjacent endplates, so a disc fills
  exactly the space between them.
* **Surface elements** (S3) for the posterior elements of every vertebra, the sacrum, the pelvis and both
  femoral heads: the triangles of the mean triangulated shape, whose nodes are SSM vertices.
* **Ligaments** as 2-node elements between landmark nodes of adjacent levels: ISL, SSL, LF, CL, ITL, PLL
  (the seed's six groups) and ALL (anterior longitudinal ligament, a seventh group, switchable at export).

Element and node sets: ``V_<lvl>_CORE``, ``V_<lvl>_SHELL`` per vertebra, ``D_<up><lo>_NP/_AF/_CEP`` (and
``_RIM`` when the CEP covers the central endplate only) per disc (e.g. ``D_L4L5_NP``), ``POST_<lvl>``,
``SACRUM``, ``PELVIS``, ``FH_L``, ``FH_R``, ``LIG_<group>``; node sets ``EP_SUP_<lvl>``, ``EP_INF_<lvl>``,
``EP_SUP_S1``, ``FH_L``, ``FH_R``, ``SACRUM`` (boundary conditions).
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from spinecohort.cohort.landmarks import LEVELS, Landmarks
from spinecohort.mesh import ligament_sites as ls

LIGAMENT_GROUPS = ("ISL", "SSL", "LF", "CL", "ITL", "PLL", "ALL")


@dataclass(frozen=True)
class TemplateResolution:
    core_cells: int = 4  # cells per side of the core block (4 * core_cells cells around)
    rings: int = 3  # ring layers between the core and the outer surface (>= 3)
    body_layers: int = 4  # element layers through a vertebral body
    disc_layers: int = 3  # element layers of a disc between its two CEP layers
    np_area_fraction: float = 0.40  # nucleus share of the disc cross-section area (seed: 40 %)
    shell_fraction: float = 0.06  # radial share of the outermost ring (cortical shell / outer AF lamella)
    cep_thickness_mm: float = 0.7  # cartilage endplate thickness (seed: 0.7 mm)
    #: the CEP layers are CEP out to the ring boundary whose enclosed area is nearest this fraction squared, annulus
    #: beyond it.  1.0 (the validated decks): the whole layer.  In vivo the cartilage covers ~70 % of the endplate's
    #: diameter and the outer annulus inserts into the bony rim (Wang, Battie & Videman 2012 Eur Spine J 21:2316); the
    #: rim of the layers is then ``D_<disc>_RIM``.  At 0.70 (docs/explanation/hex-mesh.md) the units move as in vitro
    #: (11 of 13 in range at fibres 42 and 45 deg) but the T10-S1 model stops at 69 % of flexion and 87 % of extension
    #: (the 0.7 mm central CEP hexes under the potted T10 invert), so it is not the default
    cep_diameter_fraction: float = 1.0
    exponent: float = 2.6  # superellipse exponent of the cross-section


TEMPLATE_RESOLUTIONS = {
    #: below the default, for the mesh-convergence study only (docs/explanation/validation.md "Mesh convergence")
    "coarser": TemplateResolution(core_cells=3, rings=3, body_layers=3, disc_layers=2),
    "coarse": TemplateResolution(),
    "medium": TemplateResolution(core_cells=6, rings=5, body_layers=8, disc_layers=5),
    "fine": TemplateResolution(core_cells=12, rings=9, body_layers=14, disc_layers=8),
}


# ----------------------------------------------------------------------------------------------------------
# The 2-D O-grid


@dataclass
class OGrid:
    nodes: np.ndarray  # (n, 2) in the unit superellipse
    quads: np.ndarray  # (q, 4) counter-clockwise seen from +z
    quad_ring: np.ndarray  # (q,) 0 = core block, k = k-th ring from inside
    outer: np.ndarray  # (4 * core_cells,) node ids of the outer boundary, counter-clockwise
    np_ring: int  # quads with quad_ring <= np_ring are nucleus
    shell_ring: int  # the outermost ring index
    cep_ring: int  # in a disc's CEP layers, quads with quad_ring <= cep_ring are CEP, the others annulus

    def rim_nodes(self) -> np.ndarray:
        """(n,) bool: the nodes outside the cartilage endplate (on no CEP quad); none when the CEP is whole."""
        on_cep = np.zeros(len(self.nodes), bool)
        on_cep[self.quads[self.quad_ring <= self.cep_ring].ravel()] = True
        return ~on_cep


def _square_boundary(c: float, n: int) -> np.ndarray:
    """Counter-clockwise points on the square [-c, c]^2 boundary, n per side, starting at (c, -c)."""
    t = np.linspace(-c, c, n + 1)[:-1]
    right = np.stack([np.full(n, c), t], 1)
    top = np.stack([-t, np.full(n, c)], 1)
    left = np.stack([np.full(n, -c), -t], 1)
    bottom = np.stack([t, np.full(n, -c)], 1)
    return np.concatenate([right, top, left, bottom])


def _superellipse_on_rays(pts: np.ndarray, exponent: float) -> np.ndarray:
    th = np.arctan2(pts[:, 1], pts[:, 0])
    c, s = np.abs(np.cos(th)), np.abs(np.sin(th))
    r = (c**exponent + s**exponent) ** (-1.0 / exponent)
    return np.stack([r * np.cos(th), r * np.sin(th)], 1)


def _polygon_area(p: np.ndarray) -> float:
    x, y = p[:, 0], p[:, 1]
    return 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))


def core_boundary_ids(n: int) -> np.ndarray:
    """Node ids of the core block's boundary, counter-clockwise in the order of ``_square_boundary``: the
    j-th one starts ray j, whose ring nodes are ``n_core + k * 4n + j``."""

    def core_id(i, j):
        return j * (n + 1) + i

    return np.array(
        [core_id(n, j) for j in range(n)]
        + [core_id(n - i, n) for i in range(n)]
        + [core_id(0, n - j) for j in range(n)]
        + [core_id(i, 0) for i in range(n)]
    )


def ogrid(res: TemplateResolution) -> OGrid:
    """The shared cross-section: core block + rings; ring spacing puts the NP boundary at the requested
    area fraction and makes the outermost ring a thin shell."""
    n, rings = res.core_cells, res.rings
    if rings < 3 or n < 2:
        raise ValueError("the O-grid needs core_cells >= 2 and rings >= 3")
    c = 0.35
    g = np.linspace(-c, c, n + 1)
    core = np.stack(np.meshgrid(g, g, indexing="xy"), -1).reshape(-1, 2)  # id = j * (n + 1) + i
    inner = _square_boundary(c, n)  # 4n points
    outer = _superellipse_on_rays(inner, res.exponent)
    total = _polygon_area(outer)
    from scipy.optimize import brentq  # here: the shard jobs load a template and never build one (0.4 s import)

    f_np = brentq(lambda f: _polygon_area(inner + f * (outer - inner)) - res.np_area_fraction * total, 0.0, 1.0)
    k_np = max(1, (rings - 1) // 2)
    f = np.concatenate(
        [np.linspace(0, f_np, k_np + 1)[1:], np.linspace(f_np, 1.0 - res.shell_fraction, rings - k_np)[1:], [1.0]]
    )
    ring_nodes = inner[None] + f[:, None, None] * (outer - inner)[None]  # (rings, 4n, 2)
    enclosed = np.array([_polygon_area(r) for r in ring_nodes]) / total  # area inside ring k's outer boundary
    cep_ring = 1 + int(np.argmin(np.abs(enclosed - res.cep_diameter_fraction**2)))
    nodes = np.concatenate([core, ring_nodes.reshape(-1, 2)])

    def core_id(i, j):
        return j * (n + 1) + i

    quads = [
        [core_id(i, j), core_id(i + 1, j), core_id(i + 1, j + 1), core_id(i, j + 1)] for j in range(n) for i in range(n)
    ]
    ring_of = [0] * len(quads)
    prev = core_boundary_ids(n)
    m = 4 * n
    for k in range(rings):
        cur = len(core) + k * m + np.arange(m)
        for j in range(m):
            a, b = prev[j], prev[(j + 1) % m]
            quads.append([a, b, cur[(j + 1) % m], cur[j]])
            ring_of.append(k + 1)
        prev = cur
    quads = np.array(quads, dtype=np.int64)
    # orient every quad counter-clockwise
    p = nodes[quads]
    area = 0.5 * np.sum(p[:, :, 0] * np.roll(p[:, :, 1], -1, 1) - p[:, :, 1] * np.roll(p[:, :, 0], -1, 1), 1)
    quads[area < 0] = quads[area < 0][:, ::-1]
    return OGrid(nodes, quads, np.array(ring_of), prev, k_np, rings, cep_ring)


# ----------------------------------------------------------------------------------------------------------
# Endplate frames of a triangulated shape (for placing the template before morphing)


@dataclass
class Endplate:
    centre: np.ndarray  # (3,) mm
    frame: np.ndarray  # (3, 3) columns: lateral, anterior, cranial normal
    half_axes: np.ndarray  # (2,) mm: lateral, antero-posterior half extents


def fit_endplate(points: np.ndarray, lateral_hint=(1.0, 0.0, 0.0)) -> Endplate:
    """Plane fit (total least squares) of a planar endplate patch with its in-plane extents."""
    c = points.mean(0)
    _, _, vt = np.linalg.svd(points - c)
    n = vt[-1] if vt[-1][2] > 0 else -vt[-1]
    ex = np.asarray(lateral_hint, float) - np.dot(lateral_hint, n) * n
    ex /= np.linalg.norm(ex)
    ey = np.cross(n, ex)
    d = points - c
    half = np.array([np.ptp(d @ ex), np.ptp(d @ ey)]) / 2
    return Endplate(c, np.stack([ex, ey, n], 1), half)


# ----------------------------------------------------------------------------------------------------------
# The template


@dataclass
class HexTemplate:
    nodes: np.ndarray  # (N, 3) mm; hex nodes first, then surface nodes
    hexes: np.ndarray  # (E, 8) VTK / Abaqus C3D8 node order
    tris: np.ndarray  # (T, 3) surface triangles (S3)
    ligaments: np.ndarray  # (L, 2)
    elsets: dict[str, np.ndarray]  # set name -> indices into hexes / tris / ligaments (see elset_kind)
    elset_kind: dict[str, str]  # set name -> "hex" | "tri" | "lig"
    nsets: dict[str, np.ndarray]
    n_hex_nodes: int
    surface_vertex: np.ndarray  # (N - n_hex_nodes,) triangulated-mesh vertex of each surface node
    layer_of_node: np.ndarray  # (n_hex_nodes,) node layer (bottom = S1 plate = 0)
    layers: list[dict]  # per node layer: {"kind": "s1"|"body"|"disc", ...}
    grid: OGrid
    resolution: TemplateResolution
    meta: dict = field(default_factory=dict)
    #: facet articular surfaces (``"facet_surface_<sup|inf>_<side>/<level>"`` -> skin node ids) and the facet
    #: joints' anchor pairs (``"facet_joints"``: (J, 2) IAP tip, SAP tip) of a cohort with insertion sites
    #: (`spinecohort.mesh.ligament_sites`); empty for a cohort without
    sites: dict[str, np.ndarray] = field(default_factory=dict)

    def ligament_fibres(self, group: str) -> int:
        """Fibres per ligament of a group (1: one spring; `spinecohort.mesh.ligament_sites`)."""
        return int(self.meta.get("ligament_fibres", {}).get(group, 1))

    @property
    def n_nodes(self) -> int:
        return int(self.nodes.shape[0])

    def part_of_hex(self) -> np.ndarray:
        """(E,) tissue label per hex: 'vertebra' | 'AF' | 'NP' | 'CEP' (for the Table 3 summary; the annulus'
        rim insertion ``_RIM`` is annulus)."""
        out = np.empty(len(self.hexes), dtype=object)
        for name, idx in self.elsets.items():
            if self.elset_kind[name] != "hex":
                continue
            out[idx] = "vertebra" if name.startswith("V_") else set_tissue(name)
        return out.astype(str)

    def save(self, path: str | Path) -> None:
        meta = {
            "elset_kind": self.elset_kind,
            "layers": self.layers,
            "resolution": asdict(self.resolution),
            "np_ring": self.grid.np_ring,
            "shell_ring": self.grid.shell_ring,
            "cep_ring": self.grid.cep_ring,
            "meta": self.meta,
            "elsets": list(self.elsets),
            "nsets": list(self.nsets),
            "sites": list(self.sites),
        }
        arrays = {f"elset__{k}": v for k, v in self.elsets.items()}
        arrays.update({f"nset__{k}": v for k, v in self.nsets.items()})
        arrays.update({f"site__{i}": v for i, v in enumerate(self.sites.values())})  # names hold "/"
        np.savez(
            path,
            nodes=self.nodes,
            hexes=self.hexes,
            tris=self.tris,
            ligaments=self.ligaments,
            n_hex_nodes=self.n_hex_nodes,
            surface_vertex=self.surface_vertex,
            layer_of_node=self.layer_of_node,
            grid_nodes=self.grid.nodes,
            grid_quads=self.grid.quads,
            grid_quad_ring=self.grid.quad_ring,
            grid_outer=self.grid.outer,
            meta_json=np.array(json.dumps(meta)),
            **arrays,
        )

    @classmethod
    def load(cls, path: str | Path) -> HexTemplate:
        with np.load(path, allow_pickle=False) as z:
            meta = json.loads(str(z["meta_json"]))
            grid = OGrid(
                z["grid_nodes"],
                z["grid_quads"],
                z["grid_quad_ring"],
                z["grid_outer"],
                meta["np_ring"],
                meta["shell_ring"],
                meta.get("cep_ring", meta["shell_ring"]),  # a template without cep_ring: the whole layer is CEP
            )
            return cls(
                nodes=z["nodes"],
                hexes=z["hexes"],
                tris=z["tris"],
                ligaments=z["ligaments"],
                elsets={k: z[f"elset__{k}"] for k in meta["elsets"]},
                elset_kind=meta["elset_kind"],
                nsets={k: z[f"nset__{k}"] for k in meta["nsets"]},
                n_hex_nodes=int(z["n_hex_nodes"]),
                surface_vertex=z["surface_vertex"],
                layer_of_node=z["layer_of_node"],
                layers=meta["layers"],
                grid=grid,
                resolution=TemplateResolution(**meta["resolution"]),
                meta=meta["meta"],
                sites={k: z[f"site__{i}"] for i, k in enumerate(meta.get("sites", []))},
            )


#: tissue suffix of the annulus' insertion into the bony rim (``D_<disc>_RIM``, a partial CEP's outer rings)
RIM_TISSUE = "RIM"


def set_tissue(name: str) -> str:
    """Tissue of a hex set by its name's suffix (CORE, SHELL, NP, AF, CEP); the rim insertion counts as annulus."""
    tissue = name.rsplit("_", 1)[1]
    return "AF" if tissue == RIM_TISSUE else tissue


def _compact(name: str) -> str:
    return name.replace("-", "")


def layer_plan(res: TemplateResolution) -> list[dict]:
    """Node layers from the S1 plate (bottom) to the T1 superior endplate (top)."""
    layers: list[dict] = [{"kind": "s1"}]
    for vert in range(len(LEVELS) - 1, -1, -1):  # L5 ... T1
        lower = LEVELS[vert + 1] if vert + 1 < len(LEVELS) else "S1"
        disc = f"{LEVELS[vert]}-{lower}"
        nd = res.disc_layers + 2
        for k in range(1, nd):  # interior disc node layers; the top one is the vertebra's inferior endplate
            layers.append({"kind": "disc", "disc": disc, "k": k, "n": nd})
        for k in range(res.body_layers + 1):
            layers.append({"kind": "body", "level": LEVELS[vert], "t": k / res.body_layers})
    return layers


def build_template(
    mean_points: np.ndarray,
    mean_faces: np.ndarray,
    landmarks: Landmarks,
    res: TemplateResolution,
    fibres: dict[str, int] | None = None,
) -> HexTemplate:
    """Assemble the template on a triangulated shape (the SSM mean): hex column placed by the endplate
    frames (before morphing), surface elements and ligaments from the shape's own vertices.  fibres: group ->
    fibres per ligament (config ``fe.ligaments.<group>.fibres``) of the bundles ALL, PLL, LF, CL, built at the
    insertion sites when the landmarks carry them (`spinecohort.mesh.ligament_sites`); else one spring each."""
    grid = ogrid(res)
    n2 = len(grid.nodes)
    layers = layer_plan(res)
    n_layers = len(layers)

    # --- hex connectivity: element layer between node layers L and L + 1
    elsets: dict[str, list] = {}
    hexes = []
    ids = np.arange(len(grid.quads))
    shell = grid.quad_ring == grid.shell_ring
    nucleus = grid.quad_ring <= grid.np_ring
    cep = grid.quad_ring <= grid.cep_ring
    n_disc = res.disc_layers + 2  # element layers per disc, CEPs included
    for L in range(n_layers - 1):
        top = layers[L + 1]
        hexes.append(np.concatenate([L * n2 + grid.quads, (L + 1) * n2 + grid.quads], 1))
        if top["kind"] == "body" and top["t"] > 0:
            lv = top["level"]
            elsets.setdefault(f"V_{lv}_CORE", []).append((L, ids[~shell]))
            elsets.setdefault(f"V_{lv}_SHELL", []).append((L, ids[shell]))
            continue
        # a disc element layer: below a disc node layer, or the last one below a vertebra's inferior endplate
        disc, k_top = (top["disc"], top["k"]) if top["kind"] == "disc" else (layers[L]["disc"], n_disc)
        name = _compact(disc)
        if k_top in (1, n_disc):  # a CEP layer: cartilage over the central endplate, the annulus reaching the rim
            elsets.setdefault(f"D_{name}_CEP", []).append((L, ids[cep]))
            if not cep.all():  # (a whole-layer CEP writes the sets in the decks' historical order)
                elsets.setdefault(f"D_{name}_{RIM_TISSUE}", []).append((L, ids[~cep]))
        else:
            elsets.setdefault(f"D_{name}_NP", []).append((L, ids[nucleus]))
            elsets.setdefault(f"D_{name}_AF", []).append((L, ids[~nucleus]))
    nq = len(grid.quads)
    hexes = np.concatenate(hexes)
    hex_sets = {k: np.concatenate([L * nq + i for L, i in v]) for k, v in elsets.items()}

    # --- initial placement of the hex nodes from the endplate frames of the shape
    pts = mean_points
    # the whole endplates: a rim band alone (a real endplate's clinical patch) can be a partial ring whose extents
    # differ from the facing endplate's by centimetres, which shears the disc's outer ring
    eps = {("S1", "sup"): fit_endplate(pts[landmarks.endplate_surface("sup", "S1")])}
    for lv in LEVELS:
        eps[(lv, "sup")] = fit_endplate(pts[landmarks.endplate_surface("sup", lv)])
        eps[(lv, "inf")] = fit_endplate(pts[landmarks.endplate_surface("inf", lv)])
    hex_nodes = np.empty((n_layers, n2, 3))
    for L, layer in enumerate(layers):
        if layer["kind"] == "s1":
            hex_nodes[L] = _place(grid.nodes, eps[("S1", "sup")])
        elif layer["kind"] == "body":
            hex_nodes[L] = _place_between(
                grid.nodes, eps[(layer["level"], "inf")], eps[(layer["level"], "sup")], layer["t"]
            )
    fill_discs(hex_nodes, layers, res.cep_thickness_mm, grid.rim_nodes())
    hex_nodes = hex_nodes.reshape(-1, 3)
    layer_of_node = np.repeat(np.arange(n_layers), n2)

    # --- surface elements: every triangle of a non-body part, nodes renumbered after the hex nodes
    part = landmarks.part
    names = landmarks.part_names
    is_body = np.array([n.startswith("body_") for n in names])
    keep_tri = ~np.any(is_body[part[mean_faces]], axis=1)
    tris_v = mean_faces[keep_tri]
    surf_vertices = np.unique(tris_v)
    remap = np.full(len(pts), -1)
    remap[surf_vertices] = hex_nodes.shape[0] + np.arange(len(surf_vertices))
    tris = remap[tris_v]
    tri_part = np.array(names)[part[tris_v[:, 0]]]
    tri_sets: dict[str, np.ndarray] = {}
    for label in np.unique(tri_part):
        if label.startswith("posterior_"):
            key = f"POST_{label.split('_')[1]}"
        elif label.startswith("femoral_head_"):
            key = f"FH_{label[-1]}"
        else:
            key = label.upper()
        tri_sets[key] = np.flatnonzero(tri_part == label)

    # --- ligaments between adjacent levels: single springs at the anchors, or bundles at the insertion sites
    lig, lig_group, sites, counts = ls.template_ligaments(landmarks, remap, pts, grid, layers, eps, fibres or {})
    ligaments = np.asarray(lig, dtype=np.int64).reshape(-1, 2)
    lig_group = np.array(lig_group)
    if np.any(ligaments < 0):
        raise ValueError("a ligament anchor is not on a surface part of the mesh")

    elsets_all: dict[str, np.ndarray] = dict(hex_sets)
    kind = {k: "hex" for k in hex_sets}
    for k, v in tri_sets.items():
        elsets_all[k], kind[k] = v, "tri"
    for g in LIGAMENT_GROUPS:
        elsets_all[f"LIG_{g}"], kind[f"LIG_{g}"] = np.flatnonzero(lig_group == g), "lig"

    nsets = {"EP_SUP_S1": np.arange(n2)}
    for lv in LEVELS:
        nsets[f"EP_INF_{lv}"] = _layer_index(layers, lv, 0.0) * n2 + np.arange(n2)
        nsets[f"EP_SUP_{lv}"] = _layer_index(layers, lv, 1.0) * n2 + np.arange(n2)
    for key in ("FH_L", "FH_R", "SACRUM"):
        if key in tri_sets:
            nsets[key] = np.unique(tris[tri_sets[key]])

    nodes = np.concatenate([hex_nodes, pts[surf_vertices]])
    return HexTemplate(
        nodes,
        hexes,
        tris,
        ligaments,
        elsets_all,
        kind,
        nsets,
        hex_nodes.shape[0],
        surf_vertices,
        layer_of_node,
        layers,
        grid,
        res,
        meta={"ligament_fibres": counts} if sites else {},
        sites=sites,
    )


def local_faces(faces: np.ndarray, vertices: np.ndarray) -> np.ndarray:
    """The triangles with all three vertices in ``vertices``, re-indexed into that subset."""
    keep = np.isin(faces, vertices).all(1)
    remap = np.full(faces.max() + 1, -1)
    remap[vertices] = np.arange(len(vertices))
    return remap[faces[keep]]


def _layer_index(layers: list[dict], level: str, t: float) -> int:
    for i, layer in enumerate(layers):
        if layer["kind"] == "body" and layer["level"] == level and abs(layer["t"] - t) < 1e-12:
            return i
    raise KeyError((level, t))


def _place(grid_nodes: np.ndarray, ep: Endplate) -> np.ndarray:
    local = np.c_[grid_nodes * ep.half_axes, np.zeros(len(grid_nodes))]
    return ep.centre + local @ ep.frame.T


def _place_between(grid_nodes: np.ndarray, lower: Endplate, upper: Endplate, t: float) -> np.ndarray:
    from scipy.spatial.transform import Rotation, Slerp

    rot = Slerp([0.0, 1.0], Rotation.from_matrix(np.stack([lower.frame, upper.frame])))(t).as_matrix()
    half = (1 - t) * lower.half_axes + t * upper.half_axes
    centre = (1 - t) * lower.centre + t * upper.centre
    local = np.c_[grid_nodes * half, np.zeros(len(grid_nodes))]
    return centre + local @ rot.T


def disc_runs(layers: list[dict]):
    """(first, end) node-layer index ranges of every disc's interior layers: the endplates bounding a disc
    are layers ``first - 1`` and ``end``."""
    L = 0
    while L < len(layers):
        if layers[L]["kind"] != "disc":
            L += 1
            continue
        first = L
        while layers[L]["kind"] == "disc":
            L += 1
        yield first, L


def fill_discs(hex_nodes: np.ndarray, layers: list[dict], cep_mm: float, rim: np.ndarray | None = None) -> None:
    """Place every disc node layer between its two endplate layers, in place.

    hex_nodes: (..., n_layers, n2, 3) (a leading batch axis is allowed).  The CEP layers sit ``cep_mm``
    from each endplate along the node's own line (so the CEP thickness is exact at every node), and the
    interior layers are evenly spaced between them.  rim: (n2,) bool, the nodes outside a partial CEP
    (`OGrid.rim_nodes`): there the annulus reaches the bone, and every disc layer is evenly spaced, so the
    annulus' insertion is not a 0.7 mm element layer (such thin hexes invert next to a potted vertebra;
    docs/explanation/hex-mesh.md).
    """
    for first, L in disc_runs(layers):
        lower, upper = hex_nodes[..., first - 1, :, :], hex_nodes[..., L, :, :]
        n = layers[first]["n"]
        d = upper - lower
        h = np.linalg.norm(d, axis=-1, keepdims=True)
        s_cep = np.minimum(cep_mm / np.maximum(h, 1e-9), 0.25)
        if rim is not None and rim.any():
            s_cep = np.where(rim[:, None], 1.0 / n, s_cep)
        for k in range(1, n):
            if k == 1:
                s = s_cep
            elif k == n - 1:
                s = 1.0 - s_cep
            else:
                s = s_cep + (1.0 - 2.0 * s_cep) * (k - 1) / (n - 2)
            hex_nodes[..., first + k - 1, :, :] = lower + s * d
