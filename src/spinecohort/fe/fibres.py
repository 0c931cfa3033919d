"""Annulus collagen fibres as tension-only springs embedded in the annulus hexes (the default of every deck).

Why (docs/explanation/fe-model.md): ccx 2.20's built-in fibre law ``umat_elastic_fiber`` tests
``xk2 * v4br**2 > 227`` before it assigns ``xk2``, so it aborts runs at random fibre states ("fiber extension is too
large", exit 201, not an increment cutback): with the tied C3D20R nucleus, three thoracic unit cases stopped at
66.5-96.5 % of the load in every retry.  Cable or spring fibres are the classic alternative (Shirazi-Adl et al. 1986;
Goel et al. 1995 used tension-only cable elements), and SPRINGA springs are what the ligaments already are.

The same energy as the continuum law: per annulus hex and per family (+-angle to the transverse plane, in the
circumferential-axial plane of the disc's cylindrical system), one spring of rest length L through the hex centroid
along the fibre direction, or four through the centres of the hex's in-layer quarters (``per_hex``), each with
its share V_q of the volume.  One spring is a one-point rule for the fibre energy: where the disc bends, the fibre
stretch varies across the hex, and a tension-only spring on the neutral axis stores nothing of the half of the
hex in tension, so the coarse mesh was the more flexible (docs/explanation/validation.md, mesh convergence).  Its end nodes are new and move with the hex by trilinear interpolation (``*EQUATION``
u_end = sum_i N_i(xi) u_i over the 8 corners, `FEModel.embedded_ties`), so the spring's stretch is the hex's
fibre stretch lambda (exactly so under a homogeneous deformation).  With the Holzapfel-Gasser-Ogden fibre energy
per unit volume Psi(lambda) = k1 / (2 k2) (exp(k2 (lambda^2 - 1)^2) - 1) and the hex's reference volume V, the
spring force F = (V / L) dPsi/dlambda = (V / L) 2 k1 lambda (lambda^2 - 1) exp(k2 (lambda^2 - 1)^2) stores
V * Psi: the fibre energy ccx's ELASTIC_FIBER law stores in that hex, with the total stretch instead of the
isochoric one.  Zero force for lambda <= 1 (tension only in an NLGEOM step).  The ground substance stays the
same Neo-Hooke (C10, D1), as ccx's native ``*HYPERELASTIC, NEO HOOKE``.

A SPRINGA table is force vs elongation, so it depends on V / L: the springs share one table per bin of
k1 * V / L and rest length (bins `BIN_RATIO` wide, <= 1 % from each spring's own value): 763 tables for the 21,760
springs of the whole-spine deck instead of one per spring.  Units: mm, N, MPa.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from spinecohort.mesh.quality.element import HEX_CORNER_UVW
from spinecohort.mesh.quality.verdict import hex_volumes

#: natural coordinates (-1..1) of the 8 corners of a C3D8 hex, Abaqus/ccx node order (quality's 0..1 corners)
HEX8_NATURAL = 2.0 * HEX_CORNER_UVW - 1.0
#: fibre springs' rest length (mm), halved in a hex too thin for it (`embedded_segments`)
FIBRE_LENGTH_MM = 1.0
#: the segment ends stay within this natural coordinate of the hex (its inner half)
MAX_NATURAL = 0.5
#: at most this many halvings of FIBRE_LENGTH_MM (1/8 mm)
MAX_HALVINGS = 3
#: width of the force-scale bins that share one spring table (ratio of neighbouring bins)
BIN_RATIO = 1.02
#: fibre strains of the force tables: dense where the annulus works (< 15 %), then to 30 %; ccx holds the
#: force constant beyond the last row
TABLE_STRAINS = np.concatenate([np.linspace(0.0, 0.15, 31), [0.2, 0.25, 0.3]])


#: natural coordinates of the fibre springs' centres in a hex, by the number of springs per hex and family: its
#: centre, or the centres of its four in-layer quarters (2 x 2 across the lamella and round the disc, one through
#: the layer's height; the corners' third natural coordinate is the layer's stacking direction)
QUADRATURE = {
    1: np.zeros((1, 3)),
    4: np.array([[-0.5, -0.5, 0.0], [0.5, -0.5, 0.0], [0.5, 0.5, 0.0], [-0.5, 0.5, 0.0]]),
}


def trilinear_weights(xi: np.ndarray) -> np.ndarray:
    """(..., 8) shape functions of a C3D8 hex at natural coordinates `xi` (..., 3)."""
    xi = np.asarray(xi, dtype=np.float64)
    return np.prod(1.0 + xi[..., None, :] * HEX8_NATURAL, axis=-1) / 8.0


def fibre_directions(centroids_mm: np.ndarray, axis_a_mm: np.ndarray, axis_b_mm: np.ndarray, angle_deg: float):
    """(E, 2, 3) unit directions of the two fibre families of each hex: cos(angle) e_circ +- sin(angle) e_axial,
    with e_axial the disc axis a -> b (per hex, (E, 3) each) and e_circ = e_axial x e_radial at the centroid."""
    c = np.asarray(centroids_mm, dtype=np.float64)
    a, b = np.asarray(axis_a_mm, dtype=np.float64), np.asarray(axis_b_mm, dtype=np.float64)
    ez = (b - a) / np.linalg.norm(b - a, axis=-1, keepdims=True)
    r = (c - a) - np.sum((c - a) * ez, axis=-1, keepdims=True) * ez
    et = np.cross(ez, r / np.linalg.norm(r, axis=-1, keepdims=True))
    t = np.radians(angle_deg)
    return np.stack([np.cos(t) * et + np.sin(t) * ez, np.cos(t) * et - np.sin(t) * ez], axis=1)


def jacobian_at(corners: np.ndarray, xi: np.ndarray) -> np.ndarray:
    """(E, 3, 3) dx/dxi of hexes with `corners` (E, 8, 3) mm at one natural point `xi` (3,)."""
    s = HEX8_NATURAL  # (8, 3)
    factors = 1.0 + s * np.asarray(xi, dtype=np.float64)  # (8, 3)
    grad = np.stack([s[:, i] * np.prod(np.delete(factors, i, axis=1), axis=1) for i in range(3)], axis=1) / 8.0
    return np.einsum("eki,kj->eij", corners, grad)


def _natural_extent(jac: np.ndarray, directions: np.ndarray, length_mm: float) -> np.ndarray:
    """(E, F, 3) natural-coordinate step of half a `length_mm` segment along each direction from the hex centre."""
    return np.linalg.solve(jac[:, None], 0.5 * length_mm * directions[..., None])[..., 0]


def in_lamella(jac: np.ndarray, directions: np.ndarray, length_mm: float) -> np.ndarray:
    """(E, F, 3) the directions closest to `directions` that stay in the hex's layer: the component along the
    gradient of the natural coordinate a segment leaves fastest (the lamella's normal, for an annulus hex the
    radial one) removed, so the segment runs at constant natural coordinate across the layer's thickness."""
    dxi = _natural_extent(jac, directions, length_mm)
    worst = np.argmax(np.abs(dxi), axis=-1)  # (E, F)
    grad = np.linalg.inv(jac)  # (E, 3, 3): row i is the gradient of xi_i (1/mm)
    normal = np.take_along_axis(grad[:, None], worst[..., None, None], axis=2)[..., 0, :]  # (E, F, 3)
    normal = normal / np.linalg.norm(normal, axis=-1, keepdims=True)
    d = directions - np.sum(directions * normal, axis=-1, keepdims=True) * normal
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def embedded_segments(
    points_mm: np.ndarray,
    hexes8: np.ndarray,
    directions: np.ndarray,
    length_mm: float = FIBRE_LENGTH_MM,
    hex_ids: np.ndarray | None = None,
    centre_xi: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """End points of one segment per hex and direction, centred on the natural point `centre_xi` (default the
    hex's centre, xi = 0) along the direction.  Its length is `length_mm` halved until both ends lie within the
    inner half of the hex (|xi| <= `MAX_NATURAL`; a thin outer lamella or a skewed hex needs 1/2 or 1/4 of it),
    or, off the centre, within the inner half of the hex's quarter round `centre_xi` (|xi - centre_xi| <=
    `MAX_NATURAL` / 2, one halving more allowed).  A direction that
    crosses its hex's layer so steeply that even 1/2**MAX_HALVINGS of the length leaves the inner half (a disc wall
    sheared across a thin outer ring: fibres run in their lamella, not across it) is replaced by its closest
    direction in the layer (`in_lamella`).  Returns ``(ends_mm (E, F, 2, 3), weights (E, F, 2, 8), halvings (E, F),
    in_layer (E, F) bool)``: each end lies where the hex's trilinear map puts its natural coordinates, so
    ``ends = weights @ corners`` exactly (the tie is exact in the reference state), and the segment's length is
    length_mm / 2**halvings to first order in the hex's distortion.  hex_ids: (E,) the ids an error names (default
    0..E-1)."""
    corners = np.asarray(points_mm, dtype=np.float64)[np.asarray(hexes8, dtype=np.int64)]  # (E, 8, 3)
    centre = np.zeros(3) if centre_xi is None else np.asarray(centre_xi, dtype=np.float64)
    room, most = (MAX_NATURAL, MAX_HALVINGS) if not centre.any() else (MAX_NATURAL / 2, MAX_HALVINGS + 1)
    jac = jacobian_at(corners, centre)  # dx/dxi at the segment's centre, (E, 3, 3)
    directions = np.asarray(directions, dtype=np.float64)  # (E, F, 3)
    dxi = _natural_extent(jac, directions, length_mm)
    in_layer = np.abs(dxi).max(axis=-1) > room * 2.0**most
    if in_layer.any():
        e = np.flatnonzero(in_layer.any(axis=1))
        projected = in_lamella(jac[e], directions[e], length_mm)
        directions = directions.copy()
        directions[e] = np.where(in_layer[e, :, None], projected, directions[e])
        dxi[e] = _natural_extent(jac[e], directions[e], length_mm)
    extent = np.abs(dxi).max(axis=-1)
    halvings = np.maximum(0, np.ceil(np.log2(extent / room))).astype(np.int64)
    if halvings.max() > most:
        worst = int(np.argmax(extent.max(axis=1)))
        name = worst if hex_ids is None else int(np.asarray(hex_ids)[worst])
        raise ValueError(
            f"annulus hex {name} is too thin or distorted for a fibre spring: a {length_mm} mm segment in its "
            f"layer reaches natural coordinate {extent.max():.1f}"
        )
    dxi = dxi / 2.0 ** halvings[..., None]
    xi = centre + np.stack([-dxi, dxi], axis=2)  # (E, F, 2, 3)
    weights = trilinear_weights(xi)
    ends = np.einsum("efsk,ekj->efsj", weights, corners)
    return ends, weights, halvings, in_layer


def fibre_force_n(stretch: np.ndarray, k1_mpa: float, k2: float, force_scale_mm2: float) -> np.ndarray:
    """Spring force (N) at fibre stretch lambda: force_scale (V / L, mm^2) x dPsi/dlambda of the HGO fibre energy
    (module docstring); zero for lambda <= 1."""
    lam = np.asarray(stretch, dtype=np.float64)
    e4 = lam**2 - 1.0
    f = force_scale_mm2 * 2.0 * k1_mpa * lam * e4 * np.exp(k2 * e4**2)
    return np.where(lam > 1.0, f, 0.0)


def fibre_table(k1_mpa: float, k2: float, force_scale_mm2: float, length_mm: float) -> tuple[tuple[float, float], ...]:
    """(force N, elongation mm) rows of a fibre spring of rest length `length_mm`: zero force in compression,
    `fibre_force_n` at `TABLE_STRAINS`."""
    force = fibre_force_n(1.0 + TABLE_STRAINS, k1_mpa, k2, force_scale_mm2)
    rows = [(0.0, -float(length_mm))] + [(float(f), float(e * length_mm)) for f, e in zip(force, TABLE_STRAINS)]
    return tuple(rows)


@dataclass(frozen=True)
class EmbeddedFibres:
    """The fibre springs of a set of annulus hexes, ready to append to a model.

    points: (P, 3) end nodes (mm), to be appended after the model's nodes (their indices are then n + 0..P-1).
    springs: (S, 2) indices into `points`.  hosts: (P, 8) model node ids of each end's hex corners; weights:
    (P, 8) their trilinear weights.  tables: one force-elongation table per group; group: (S,) the table of each
    spring."""

    points: np.ndarray
    springs: np.ndarray
    hosts: np.ndarray
    weights: np.ndarray
    tables: list
    group: np.ndarray


def embedded_fibres(
    points_mm: np.ndarray,
    hexes8: np.ndarray,
    axis_a_mm: np.ndarray,
    axis_b_mm: np.ndarray,
    k1_mpa: np.ndarray,
    k2: float,
    angle_deg: float,
    length_mm: float = FIBRE_LENGTH_MM,
    hex_ids: np.ndarray | None = None,
    per_hex: int = 1,
) -> EmbeddedFibres:
    """`per_hex` fibre springs per family in each annulus hex (`hexes8` (E, 8), node ids into `points_mm`), at the
    `QUADRATURE` points, each carrying its share of the hex's volume (the Jacobian determinant there): the hex's
    disc axis a -> b (E, 3 each, mm) sets the families' directions at each point, `k1_mpa` (E,) their stiffness
    (a radial gradient per ring, or uniform); see the module docstring.  Springs are ordered point by point, two
    families per hex.  hex_ids: (E,) the hexes' ids in the model, for errors."""
    if per_hex not in QUADRATURE:
        raise ValueError(f"fibre springs per hex: {per_hex}, must be one of {sorted(QUADRATURE)}")
    hexes8 = np.asarray(hexes8, dtype=np.int64)
    n_hex = len(hexes8)
    pts = np.asarray(points_mm, dtype=np.float64)
    corners = pts[hexes8]
    k1 = np.broadcast_to(np.asarray(k1_mpa, dtype=np.float64), (n_hex,))
    det = np.stack([np.linalg.det(jacobian_at(corners, xi)) for xi in QUADRATURE[per_hex]], axis=1)  # (E, Q)
    share = hex_volumes(pts, hexes8)[:, None] * det / det.sum(axis=1, keepdims=True)  # (E, Q) mm^3
    ends, weights, halvings, scale = [], [], [], []
    for q, xi in enumerate(QUADRATURE[per_hex]):  # at most four points; every operation inside is over all hexes
        at = np.einsum("k,ekj->ej", trilinear_weights(xi), corners)
        dirs = fibre_directions(at, axis_a_mm, axis_b_mm, angle_deg)
        e, w, h, _ = embedded_segments(pts, hexes8, dirs, length_mm, hex_ids, centre_xi=xi)
        ends.append(e)
        weights.append(w)
        halvings.append(h)
        # k1 V / L per spring (N): its table is this times 2 lambda (lambda^2 - 1) exp(k2 (...)^2)
        scale.append(k1[:, None] * share[:, q, None] / (length_mm / 2.0**h))
    halvings, scale = np.concatenate(halvings), np.concatenate(scale)
    bins = np.round(np.log(scale.ravel()) / np.log(BIN_RATIO)).astype(np.int64)
    key = np.column_stack([halvings.ravel(), bins])
    uniq, group = np.unique(key, axis=0, return_inverse=True)
    tables = [fibre_table(1.0, k2, float(BIN_RATIO**b), length_mm / 2.0**h) for h, b in uniq]
    n_springs = 2 * n_hex * per_hex
    springs = np.arange(2 * n_springs).reshape(n_springs, 2)
    return EmbeddedFibres(
        points=np.concatenate(ends).reshape(-1, 3),
        springs=springs,
        hosts=np.tile(np.repeat(hexes8, 4, axis=0), (per_hex, 1)),
        weights=np.concatenate(weights).reshape(-1, 8),
        tables=tables,
        group=group.reshape(-1),
    )
