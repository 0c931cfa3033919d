"""Deliberate-inversion tests of spinecohort.mesh.repair (hex-quality.md section 3.3, 'How to test in CI')."""

import numpy as np
import pytest

from spinecohort.mesh import repair as r
from spinecohort.mesh.quality.certificate import certify_valid
from spinecohort.mesh.quality.element import HEX_CORNER_UVW
from spinecohort.mesh.quality.verdict import scaled_jacobian
from spinecohort.testing import hex_grid_node_id, unit_cube_grid

N = 10  # elements per side
M = N + 1  # nodes per side


nid = hex_grid_node_id((N, N, N))


def reference_mesh():
    """Graded, sheared and bent 10^3 hex block: a valid, non-trivial 'mean mesh' (min sJ 0.80)."""
    IJK, H = unit_cube_grid(N)
    I, J, K = IJK.T.astype(np.int64)
    g = np.cumsum(np.r_[0.0, 1.1 ** np.arange(N)])
    x = g[I] / g[-1] * N  # graded spacing, ratio 1.1
    y = J + 0.04 * x**2  # curved shear
    R = 8.0  # bend about the y axis, so the z = 0 face stays planar
    P = np.stack([(R + x) * np.cos(K / R) - R, y, (R + x) * np.sin(K / R)], 1)
    return P, H


REF, HEX = reference_mesh()
BOUNDARY = r.boundary_nodes(HEX)
SJ_REF = scaled_jacobian(REF, HEX)
TAU = 0.05


def patch_nodes(X, report):
    """Nodes of the elements bad before repair grown by the rings used: the only nodes allowed to move."""
    _, _, bad = r._bad_elements(X, HEX, np.minimum(TAU, 0.5 * SJ_REF))
    seed = np.zeros(len(X), bool)
    seed[HEX[bad].ravel()] = True
    return np.flatnonzero(r._grow(seed, r._incidence(HEX, len(X)), report.patch_rings))


def check_repaired(X, Y, report, n_invalid):
    sj = scaled_jacobian(Y, HEX)
    assert report.invalid_before == n_invalid
    assert report.invalid_after == 0
    assert sj.min() > TAU and report.min_scaled_jacobian_after == pytest.approx(sj.min())
    assert np.all(certify_valid(Y, HEX) == 1)  # exact: det J > 0 inside every element
    ok_before = scaled_jacobian(X, HEX) > TAU
    assert np.all(sj[ok_before] > TAU)  # no element that was fine got spoiled
    moved = np.flatnonzero(np.any(Y != X, axis=1))
    assert np.array_equal(moved, report.moved_nodes)
    assert np.all(np.isin(moved, patch_nodes(X, report)))  # purely local
    assert report.max_displacement_mm == pytest.approx(np.linalg.norm(Y - X, axis=1).max())
    assert np.array_equal(report.displacement_mm, Y[moved] - X[moved])  # the sparse correction to store
    Y2, report2 = r.untangle(Y, HEX, REF)  # idempotent: nothing left to repair
    assert np.array_equal(Y2, Y) and report2.n_nodes_moved == 0


def push(node, towards, factor):
    X = REF.copy()
    X[node] += factor * (REF[towards] - REF[node])
    return X


def test_reference_mesh_is_valid_and_surface_is_found():
    assert SJ_REF.min() == pytest.approx(0.8020, abs=1e-4)
    assert len(BOUNDARY) == M**3 - (M - 2) ** 3  # 602 surface nodes of a 10^3 block
    assert len(r.boundary_faces(HEX)) == 6 * N * N


def test_interior_node_pushed_through_neighbour():
    X = push(nid(5, 5, 5), nid(6, 5, 5), 1.6)  # 0.6 edge lengths beyond its +x neighbour
    Y, rep = r.untangle(X, HEX, REF)
    check_repaired(X, Y, rep, n_invalid=4)  # the 4 elements between the node and its neighbour
    assert not rep.sliding and rep.patch_rings == 1
    assert np.array_equal(Y[BOUNDARY], X[BOUNDARY])  # fixed surface


def test_subsurface_node_pushed_through_surface():
    X = push(nid(5, 5, 1), nid(5, 5, 0), 1.6)  # through the z = 0 surface
    Y, rep = r.untangle(X, HEX, REF)
    check_repaired(X, Y, rep, n_invalid=4)
    assert not rep.sliding
    assert np.array_equal(Y[BOUNDARY], X[BOUNDARY])


def test_localised_large_shear_mode():
    # u_x = w (z - zc)/s exp(-|x - c|^2 / 2 s^2): d u_x / d x < -1 near the centre for w = 6 -> folds
    c, s, w = REF[nid(5, 5, 5)], 1.5, 6.0
    d = REF - c
    X = REF.copy()
    X[:, 0] += w * d[:, 2] / s * np.exp(-(d**2).sum(1) / (2 * s * s))
    n_invalid = int((scaled_jacobian(X, HEX) <= 0).sum())
    Y, rep = r.untangle(X, HEX, REF)
    check_repaired(X, Y, rep, n_invalid=n_invalid)
    assert n_invalid >= 10
    assert np.array_equal(Y[BOUNDARY], X[BOUNDARY])


def test_surface_fold_needs_sliding_and_stays_on_plane():
    # a node of the planar z = 0 face dragged 1.3 edge lengths within the face folds 2 surface quads:
    # impossible with a fixed surface, so the escalation goes straight to tangent sliding
    X = push(nid(5, 5, 0), nid(6, 5, 0), 1.3)
    Y, rep = r.untangle(X, HEX, REF)
    check_repaired(X, Y, rep, n_invalid=2)
    assert rep.sliding
    face = [nid(i, j, 0) for i in range(M) for j in range(M)]
    assert np.abs(Y[face, 2]).max() < 1e-9  # slid within the plane z = 0
    assert len(rep.attempts) == 1  # fixed-surface attempts skipped


def test_valid_mesh_is_returned_unchanged():
    Y, rep = r.untangle(REF, HEX, REF)
    assert np.array_equal(Y, REF) and rep.invalid_before == 0 and rep.n_nodes_moved == 0


def test_unrepairable_mesh_raises_naming_the_failure():
    # a single hex has only surface nodes: with sliding excluded from the plan nothing can move
    P = HEX_CORNER_UVW.copy()
    X = P.copy()
    X[6] = [-0.5, -0.5, -0.5]
    with pytest.raises(r.RepairError, match="untangling failed"):
        r.untangle(X, np.arange(8)[None], P, plan=((1, False),))


def test_surface_fold_without_sliding_raises_naming_remaining_elements():
    X = push(nid(5, 5, 0), nid(6, 5, 0), 1.3)  # needs surface sliding, which this plan forbids
    with pytest.raises(r.RepairError, match=r"\d+ invalid elements remain \(input had 2; e\.g\. elements \[\d+"):
        r.untangle(X, HEX, REF, plan=((1, False),), max_outer=3)


def test_invalid_reference_is_rejected():
    bad_ref = push(nid(5, 5, 5), nid(6, 5, 5), 1.6)
    with pytest.raises(ValueError, match="reference mesh has 4 invalid elements"):
        r.untangle(REF, HEX, bad_ref)


def test_energy_gradient_matches_finite_differences():
    rng = np.random.default_rng(1)
    Xe = HEX_CORNER_UVW + rng.normal(0, 0.4, (3, 8, 3))  # some corners inverted
    Winv = np.linalg.inv(np.einsum("knj,enx->ekxj", r._G, 1.3 * np.broadcast_to(HEX_CORNER_UVW, (3, 8, 3))))
    F, grad, _ = r.winslow_energy(Xe, Winv, eps=0.3)
    num = np.zeros_like(Xe)
    for idx in np.ndindex(Xe.shape):
        dX = np.zeros_like(Xe)
        dX[idx] = 1e-6
        num[idx] = (r.winslow_energy(Xe + dX, Winv, 0.3)[0] - r.winslow_energy(Xe - dX, Winv, 0.3)[0]) / 2e-6
    assert np.abs(num - grad).max() < 1e-6 * np.abs(grad).max()


def test_energy_of_target_shape_is_its_minimum_value():
    # T = I at all 9 points: |I|^2 / 3 + lam (1 + 1) / 2 = 1 + 1 per point with eps -> 0
    Winv = np.linalg.inv(np.einsum("knj,enx->ekxj", r._G, HEX_CORNER_UVW[None]))
    F, grad, d = r.winslow_energy(HEX_CORNER_UVW[None], Winv, eps=1e-8)
    assert F == pytest.approx(18.0, rel=1e-12) and np.abs(grad).max() < 1e-10 and np.allclose(d, 1.0)


def test_sliding_on_curved_surface_stays_on_input_surface():
    # node of the curved x = max face (cylinder R = 18) dragged along the bend by 1.3 edge lengths
    X = push(nid(N, 5, 5), nid(N, 5, 6), 1.3)
    Y, rep = r.untangle(X, HEX, REF)
    check_repaired(X, Y, rep, n_invalid=2)
    assert rep.sliding
    moved_surface = np.intersect1d(rep.moved_nodes, BOUNDARY)
    assert len(moved_surface) > 1
    # slid nodes are projected back onto the sample's own triangulated surface (pyvista closest point)
    surface = r._surface_near(X, r.boundary_faces(HEX), np.ones(len(X), bool))
    _, closest = surface.find_closest_cell(Y[moved_surface], return_closest_point=True)
    assert np.linalg.norm(closest - Y[moved_surface], axis=1).max() < 1e-9
    # the block's edges and corners are surface features and never slide
    edge_nodes = [nid(N, 0, k) for k in range(M)] + [nid(N, j, 0) for j in range(M)]
    assert np.array_equal(Y[edge_nodes], X[edge_nodes])


def test_prepared_context_gives_the_same_repair():
    # the cohort reuses one context (topology + reference quality) for all samples
    ctx = r.prepare_untangle(HEX, REF)
    assert np.array_equal(np.flatnonzero(ctx.is_boundary), BOUNDARY)
    X = push(nid(5, 5, 5), nid(6, 5, 5), 1.6)
    Y1, _ = r.untangle(X, HEX, REF)
    Y2, _ = r.untangle(X, HEX, REF, context=ctx)
    assert np.array_equal(Y1, Y2)
    with pytest.raises(ValueError, match="context was prepared for"):
        r.untangle(X[:-1], HEX[:-1], REF[:-1], context=ctx)


def test_fold_pinned_by_a_feature_node_is_repaired_by_letting_features_slide():
    # a node of the block's edge (y = 0, z = 0: two faces at 90 deg, a feature) dragged 1.3 edge lengths along
    # the edge folds the edge hexes; fixed feature nodes cannot undo it (the rim fold under L5's flared
    # endplate at 3 SD on the real-bone grid is of this kind), sliding them on the sample's surface can
    X = push(nid(5, 0, 0), nid(6, 0, 0), 1.3)
    n_invalid = int((scaled_jacobian(X, HEX) <= 0).sum())
    with pytest.raises(r.RepairError, match="invalid elements remain"):
        r.untangle(X, HEX, REF, free_features=False)
    Y, rep = r.untangle(X, HEX, REF)
    check_repaired(X, Y, rep, n_invalid=n_invalid)
    assert n_invalid == 1 and rep.sliding  # the edge hex between the node and its +x neighbour
    assert any("features sliding" in a for a in rep.attempts)
    # the slid nodes stay on the sample's own surface
    moved_surface = np.intersect1d(rep.moved_nodes, BOUNDARY)
    surface = r._surface_near(X, r.boundary_faces(HEX), np.ones(len(X), bool))
    _, closest = surface.find_closest_cell(Y[moved_surface], return_closest_point=True)
    assert np.linalg.norm(closest - Y[moved_surface], axis=1).max() < 1e-9


def test_second_pass_failure_names_the_input_count_first():
    # an interior fold (4 hexes, repaired by the first pass) and a surface fold (2 hexes, which this plan cannot
    # repair): the first pass leaves 3 (the fold and a neighbour its fixed-surface attempt pushed to sJ -0.001),
    # the second fails on those 3; the caller keeps the input with all 6, so the message leads with 6, not with
    # the second pass's "input had 3"
    X = push(nid(5, 5, 5), nid(6, 5, 5), 1.6)
    X[nid(5, 5, 0)] += 1.3 * (REF[nid(6, 5, 0)] - REF[nid(5, 5, 0)])
    assert int((scaled_jacobian(X, HEX) <= 0).sum()) == 6
    with pytest.raises(r.RepairError) as err:
        r.untangle(X, HEX, REF, plan=((1, False),))
    msg = str(err.value)
    assert msg.startswith("untangling failed: the 6 invalid elements of the input were cut to 3 by the first pass")
    assert "second pass: untangling failed: 3 invalid elements remain (input had 3;" in msg
