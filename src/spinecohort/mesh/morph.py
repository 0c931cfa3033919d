"""Morphing the hex template onto the triangulated SSM mean (the seed's Methods B, "multi-layer BCPD++").

Per vertebral body: the template's body block, already placed by the fitted endplate frames (our rigid +
scale pre-alignment, replacing the seed's fixed 90 deg rotation and large-lambda rigid BCPD), is
registered non-rigidly onto the mean's body surface: its surface nodes (the outer ring of every node layer
and the two endplate layers) are the BCPD source and the body's vertices the target.  The learned smooth
field moves every node of the block, interior ones included, so the cancellous core follows the cortex.
Registration is repeated with refined parameters until the mean surface distance is below the bound
(0.04 mm in the seed).  The S1 plate layer is registered onto the S1 endplate patch the same way.  Discs are
then re-filled between their morphed endplates (CEP 0.7 mm), exactly as the seed builds its IVDs from the
two adjacent endplates.  An optional final closest-point projection of the surface nodes (its displacement
spread to the interior by inverse-distance weighting within the body) closes any residual gap.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import numpy as np
import pandas as pd

from spinecohort.cohort.landmarks import LEVELS, Landmarks
from spinecohort.mesh.quality.verdict import scaled_jacobian
from spinecohort.mesh.radial import (
    RIM_DEPTH_MM,
    axial_map,
    closed_body,
    in_plane_map,
    plate_map,
    ring_lines,
    shared_outline,
)
from spinecohort.mesh.registration import nonrigid_register, surface_distance
from spinecohort.mesh.template import HexTemplate, OGrid, core_boundary_ids, fill_discs
from spinecohort.mesh.template import local_faces as _faces_of

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class MorphParameters:
    """The seed's Table 1 (BCPD option names) plus the multilayer bound."""

    lam: float = 8.0  # motion smoothing weight
    beta: float = 2.0  # interaction between the points (kernel width, normalised units)
    gamma: float = 2.0  # randomness of the matching at the start
    K: int = 70  # Nystrom samples for G
    w: float = 0.1  # expected outlier ratio
    max_iter: int = 1000
    tol: float = 1e-5
    downsample_radius_mm: float = 0.5
    kd_sigma: float = 0.2
    kd_scale: float = 7.0
    kd_radius: float = 0.2
    bound_mm: float = 0.04  # multilayer stop: mean surface distance
    max_layers: int = 0  # BCPD layers amplify round-off into mm of interior nodes (docs/explanation/hex-mesh.md)
    project: bool = True  # final closest-point projection of the surface nodes
    surface_map: str = "closest"  # bodies: closest (closest points, `project`) | rays (:mod:`spinecohort.mesh.radial`)
    min_scaled_jacobian: float = 0.3  # a registration layer is kept only if the block stays above this
    rim_depth_mm: float = RIM_DEPTH_MM  # surface_map rays: the endplate's outline is the wall's this far under the rim


def _closest_points(points: np.ndarray, target: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Closest point (mm) on a triangulated surface for each point (VTK static cell locator)."""
    import vtk

    from spinecohort.mesh.vtk_mesh import surface

    loc = vtk.vtkStaticCellLocator()
    loc.SetDataSet(surface(target, faces))
    loc.BuildLocator()
    closest = np.empty((len(points), 3))
    c = [0.0, 0.0, 0.0]
    cell, sub, d2 = vtk.reference(0), vtk.reference(0), vtk.reference(0.0)
    for k, p in enumerate(points):  # one C++ call per surface node (a few hundred per body)
        loc.FindClosestPoint(p, c, cell, sub, d2)
        closest[k] = c
    return closest


def _ray_points(points: np.ndarray, centres: np.ndarray, target: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Each point moved along its ray from its layer's centre (in-layer, radial) to the nearest crossing of the
    surface, inward or outward within the point's radius (mm); a ray that crosses nothing keeps its closest point.
    Unlike the closest point, it keeps each node at its height on a waisted or bulging wall."""
    import vtk

    from spinecohort.mesh.vtk_mesh import surface

    loc = vtk.vtkCellLocator()
    loc.SetDataSet(surface(target, faces))
    loc.BuildLocator()
    out = _closest_points(points, target, faces)
    t, x, pc, sub = vtk.reference(0.0), [0.0, 0.0, 0.0], [0.0, 0.0, 0.0], vtk.reference(0)
    for k, (p, c) in enumerate(zip(points, centres)):  # one C++ call per direction of a wall node
        best = np.inf
        for end in (c, p + (p - c)):
            if loc.IntersectWithLine(p, end, 1e-9, t, x, pc, sub) and np.linalg.norm(np.subtract(x, p)) < best:
                best = float(np.linalg.norm(np.subtract(x, p)))
                out[k] = x
    return out


def ray_weights(grid: OGrid, core_cells: int) -> tuple[np.ndarray, np.ndarray]:
    """For every 2-D O-grid node: the outer-boundary node of its ray (-1 for core nodes) and its radial
    fraction along the ray (0 on the core block's boundary, 1 on the outer boundary)."""
    ids, _, end, ring_frac = ring_lines(grid, core_boundary_ids(core_cells))
    outer_of = np.full(len(grid.nodes), -1)
    frac = np.zeros(len(grid.nodes))
    outer_of[ids], frac[ids] = end, ring_frac
    return outer_of, frac


def _project(
    points: np.ndarray,
    groups: list[tuple[np.ndarray, np.ndarray, np.ndarray]],
    spread: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
    wall_centres: np.ndarray | None = None,
) -> np.ndarray:
    """Snap each group of surface nodes onto its own target surface (endplate nodes onto the endplate
    patch, wall nodes onto the wall).  ``spread`` = (node ids, their outer node, weight): interior ring nodes
    take their ray's outer-node correction times their radial fraction, so thin shell rings move with the
    surface instead of being crushed.  wall_centres: (n, 3) the layer centre of each node of the last group (the
    wall), which then moves along its ray (`_ray_points`) instead of to its closest point."""
    out = points.copy()
    for k, (ids, tgt, faces) in enumerate(groups):
        if wall_centres is not None and k == len(groups) - 1:
            out[ids] = _ray_points(points[ids], wall_centres, tgt, faces)
        else:
            out[ids] = _closest_points(points[ids], tgt, faces)
    if spread is not None:
        ids, outer, w = spread
        out[ids] = points[ids] + w[:, None] * (out[outer] - points[outer])
        # endplate-layer nodes moved along their ray go back onto their (planar) patch
        for g_ids, tgt, faces in groups[:-1]:
            moved = np.intersect1d(g_ids, ids)
            out[moved] = _closest_points(out[moved], tgt, faces)
    return out


def _projection_groups(shape, grid, core_cells, name, landmarks, mean_points, mean_faces, target, faces):
    """(node ids, target vertices, target faces) per surface kind of one block."""
    nl, n2 = shape[:2]
    ids = np.arange(nl * n2).reshape(nl, n2)
    if name == "S1":
        return [(ids.ravel(), target, faces)], None
    groups = []
    # the whole endplate (a real one's concave surface, not only its rim band): the layer's core nodes land on it
    caps = [landmarks.endplate_surface(side, name) for side in ("inf", "sup")]
    for layer, patch in zip((0, nl - 1), caps):
        groups.append((ids[layer], mean_points[patch], _faces_of(mean_faces, patch)))
    caps = np.concatenate(caps)
    wall_faces = _faces_of(mean_faces, landmarks.body[name])
    keep = ~np.isin(landmarks.body[name][wall_faces], caps).all(1)  # triangles not lying in a cap
    groups.append((ids[1:-1, grid.outer].ravel(), target, wall_faces[keep]))
    outer_of, frac = ray_weights(grid, core_cells)
    inner = np.flatnonzero((outer_of >= 0) & (frac < 1.0))
    layer_ids = np.arange(nl)
    spread = (
        (layer_ids[:, None] * n2 + inner[None]).ravel(),
        (layer_ids[:, None] * n2 + outer_of[inner][None]).ravel(),
        np.tile(frac[inner], len(layer_ids)),
    )
    return groups, spread


def _block_hexes(grid: OGrid, n_layers: int) -> np.ndarray:
    """Hex connectivity of a block of ``n_layers`` node layers of the O-grid (local node ids)."""
    n2 = len(grid.nodes)
    if n_layers < 2:
        return np.zeros((0, 8), dtype=np.int64)
    return np.concatenate(
        [np.concatenate([k * n2 + grid.quads, (k + 1) * n2 + grid.quads], 1) for k in range(n_layers - 1)]
    )


def _multilayer_valid(flat, surf_ids, hexes, target, faces, params: MorphParameters, start_distance: float):
    """Multilayer BCPD (seed Methods B) that keeps a layer only if it brings the surface closer and leaves
    every element of the block valid; kernel width halves and the Nystrom rank grows per layer, and a
    rejected layer is retried narrower from the last accepted state.

    The loop lives here rather than in :func:`spinecohort.mesh.registration.multilayer_register` because the
    acceptance test needs the block's hexahedra.
    """
    current, best = flat, start_distance
    history = []
    beta, k = params.beta, params.K
    for layer in range(params.max_layers):
        if best < params.bound_mm:
            break
        res = nonrigid_register(
            current[surf_ids],
            target,
            faces,
            lam=params.lam,
            beta=beta,
            gamma=params.gamma,
            K=k,
            w=params.w,
            max_iter=params.max_iter,
            tol=params.tol,
            downsample_radius=params.downsample_radius_mm,
            kd_sigma=params.kd_sigma,
            kd_scale=params.kd_scale,
            kd_radius=params.kd_radius,
        )
        candidate = res.transform(current)
        dist = float(surface_distance(candidate[surf_ids], target, faces).mean())
        # valid = no element below the quality floor (scaled Jacobian), not merely non-inverted
        valid = bool(scaled_jacobian(candidate, hexes).min() > params.min_scaled_jacobian) if len(hexes) else True
        if valid and dist < best:
            current, best = candidate, dist
            history.append(dict(layer=layer, beta=beta, K=k, iterations=res.iterations, mean_distance=dist))
        else:  # rejected: the next, narrower kernel starts again from the last accepted state
            log.info("layer %d (beta %.3g) not applied: distance %.4f mm, elements valid: %s", layer, beta, dist, valid)
        beta, k = beta * 0.5, min(600, k * 4)
    return current, history


def ray_morphed_bodies(
    template: HexTemplate, mean_points, mean_faces, landmarks: Landmarks, rim_depth_mm: float
) -> dict[str, np.ndarray]:
    """Every body block mapped onto its closed body surface by rays (:mod:`spinecohort.mesh.radial`): in-plane,
    then the two endplate layers facing each other across each disc given a shared outline, then axial.
    Returns level -> (n_layers, n2, 3) mm."""
    grid, n2 = template.grid, len(template.grid.nodes)
    hex_layers = template.nodes[: template.n_hex_nodes].reshape(len(template.layers), n2, 3)
    lines = ring_lines(grid, core_boundary_ids(template.resolution.core_cells))
    n_core = len(grid.nodes) - grid.shell_ring * len(grid.outer)
    blocks, bodies = {}, {}
    for lv in LEVELS:
        ids = [i for i, ly in enumerate(template.layers) if ly["kind"] == "body" and ly["level"] == lv]
        body_ids = landmarks.body[lv]
        bodies[lv] = closed_body(mean_points[body_ids], _faces_of(mean_faces, body_ids))
        blocks[lv] = in_plane_map(hex_layers[ids], grid.outer, np.arange(n_core), lines, bodies[lv], rim_depth_mm)
    for upper, lower in zip(LEVELS[:-1], LEVELS[1:]):  # LEVELS run cranial to caudal
        blocks[lower][-1], blocks[upper][0] = shared_outline(blocks[lower][-1], blocks[upper][0])
    s1 = hex_layers[[i for i, ly in enumerate(template.layers) if ly["kind"] == "s1"]]
    # the S1 plate takes L5's outline: L5's inferior endplate keeps the rim its clinical plane is fitted on, and
    # the labeled S1 plate (the part of the sacrum facing L5) is no body outline to average with
    s1[0], blocks[LEVELS[-1]][0] = shared_outline(s1[0], blocks[LEVELS[-1]][0], lower_share=0.0)
    inner = n_core + (grid.shell_ring - 2) * len(grid.outer) + np.arange(len(grid.outer))  # the ring inside the shell
    out = {lv: axial_map(blocks[lv], grid.outer, inner, bodies[lv]) for lv in LEVELS}
    plate = landmarks.endplate_surface("sup", "S1")
    out["S1"] = plate_map(s1, mean_points[plate], _faces_of(mean_faces, plate))
    return out


def morph_template(
    template: HexTemplate,
    mean_points: np.ndarray,
    mean_faces: np.ndarray,
    landmarks: Landmarks,
    params: MorphParameters = MorphParameters(),
    progress=None,
) -> tuple[np.ndarray, pd.DataFrame]:
    """Morphed node coordinates (n_nodes, 3) mm and a per-part report (distances in mm, iterations)."""
    grid = template.grid
    n2 = len(grid.nodes)
    layers = template.layers
    nodes = template.nodes.copy()
    hex_layers = nodes[: template.n_hex_nodes].reshape(len(layers), n2, 3)
    rows = []
    parts = [
        (lv, [i for i, ly in enumerate(layers) if ly["kind"] == "body" and ly["level"] == lv], landmarks.body[lv])
        for lv in LEVELS
    ]
    parts.append(("S1", [0], landmarks.endplate_surface("sup", "S1")))
    rays = (
        ray_morphed_bodies(template, mean_points, mean_faces, landmarks, params.rim_depth_mm)
        if params.surface_map == "rays"
        else {}
    )
    for k, (name, layer_ids, target_ids) in enumerate(parts):
        block = hex_layers[layer_ids]  # (nl, n2, 3)
        is_surface = np.zeros(block.shape[:2], bool)
        is_surface[:, grid.outer] = True
        is_surface[[0, -1]] = True
        flat = block.reshape(-1, 3)
        surf_ids = np.flatnonzero(is_surface.ravel())
        target = mean_points[target_ids]
        faces = _faces_of(mean_faces, target_ids)
        t0 = time.perf_counter()
        before = float(surface_distance(flat[surf_ids], target, faces).mean())
        if name in rays:  # the ray maps start from the placed template; a BCPD layer would only be discarded
            moved, history = rays[name].reshape(-1, 3), []
        else:
            moved, history = _multilayer_valid(
                flat, surf_ids, _block_hexes(grid, block.shape[0]), target, faces, params, before
            )
        after_reg = history[-1]["mean_distance"] if history else before
        if name not in rays and params.project:
            groups, spread = _projection_groups(
                block.shape,
                grid,
                template.resolution.core_cells,
                name,
                landmarks,
                mean_points,
                mean_faces,
                target,
                faces,
            )
            projected = _project(moved, groups, spread)
            block_hexes = _block_hexes(grid, block.shape[0])
            if name != "S1" and scaled_jacobian(projected, block_hexes).min() <= 0:
                # closest points slide along a waisted real wall by more than a layer's height: the wall nodes
                # go along their in-layer rays instead, keeping their heights
                layer_of = groups[-1][0] // block.shape[1]
                centres = moved.reshape(block.shape).mean(axis=1)[layer_of]
                projected = _project(moved, groups, spread, wall_centres=centres)
            moved = projected
        dist = surface_distance(moved[surf_ids], target, faces)
        hex_layers[layer_ids] = moved.reshape(block.shape)
        rows.append(
            dict(
                part=name,
                surface_nodes=len(surf_ids),
                target_vertices=len(target_ids),
                distance_before_mm=before,
                distance_registered_mm=after_reg,
                distance_final_mean_mm=float(dist.mean()),
                distance_final_max_mm=float(dist.max()),
                layers=len(history),
                iterations=sum(h["iterations"] for h in history),
                seconds=time.perf_counter() - t0,
            )
        )
        log.info(
            "%s: surface distance %.3f -> %.4f mm (BCPD, %d layers accepted) -> %.2e mm",
            name,
            before,
            after_reg,
            len(history),
            dist.mean(),
        )
        if progress is not None:
            progress(k + 1, len(parts))
    fill_discs(hex_layers, layers, template.resolution.cep_thickness_mm, template.grid.rim_nodes())
    nodes[: template.n_hex_nodes] = hex_layers.reshape(-1, 3)
    return nodes, pd.DataFrame(rows)
