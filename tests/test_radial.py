"""The ray maps of a hex body block onto a body surface (spinecohort.mesh.radial), on closed forms and real bones."""

from __future__ import annotations

import numpy as np
import pytest
import pyvista as pv

from spinecohort.mesh.morph import MorphParameters, _block_hexes, morph_template
from spinecohort.mesh.quality.verdict import scaled_jacobian
from spinecohort.mesh.radial import (
    axial_map,
    farthest_hits,
    in_plane_map,
    plate_map,
    ring_lines,
    shared_outline,
)
from spinecohort.mesh.template import TEMPLATE_RESOLUTIONS, build_template, core_boundary_ids, ogrid

RADIUS_MM, HEIGHT_MM, DISH_MM = 20.0, 30.0, 2.0


def _dished_cylinder():
    """A closed cylinder (radius 20 mm, height 30 mm) whose top cap is a dish 2 mm deep at its centre:
    z = 15 - 2 (1 - r^2 / 20^2), the shape of a concave endplate."""
    cyl = pv.Cylinder(radius=RADIUS_MM, height=HEIGHT_MM, direction=(0, 0, 1), resolution=120, capping=True)
    mesh = cyl.triangulate().subdivide(4, "linear").clean()
    v = np.asarray(mesh.points, dtype=float)
    top = np.abs(v[:, 2] - HEIGHT_MM / 2) < 1e-6
    r2 = (v[top, :2] ** 2).sum(1)
    v[top, 2] -= DISH_MM * (1 - r2 / RADIUS_MM**2)
    return v, np.asarray(mesh.faces).reshape(-1, 4)[:, 1:]


def _block(grid, half_mm=(15.0, 12.0), height_mm=24.0, layers=5):
    """An O-grid prism (layers, n2, 3) smaller than the cylinder, centred on it."""
    z = np.linspace(-height_mm / 2, height_mm / 2, layers)
    xy = grid.nodes * np.asarray(half_mm)
    return np.stack([np.c_[xy, np.full(len(xy), zk)] for zk in z])


def test_farthest_hits_on_a_sphere_are_its_radius():
    sphere = pv.Sphere(radius=10.0, theta_resolution=90, phi_resolution=90)
    v, f = np.asarray(sphere.points, float), np.asarray(sphere.faces).reshape(-1, 4)[:, 1:]
    d = np.random.default_rng(3).normal(size=(200, 3))
    d /= np.linalg.norm(d, axis=1)[:, None]
    t = farthest_hits(np.zeros((200, 3)), d, v, f)
    # a ray from the centre leaves the sphere once, inside it by at most the sag of a facet spanning 4 degrees
    # (360 / 90) in longitude: 10 (1 - cos 4 deg) = 0.024 mm
    assert np.all((t <= 10.0 + 1e-9) & (t > 10.0 - 10.0 * (1 - np.cos(np.radians(4.0)))))
    # a ray that starts outside, pointing away, crosses nothing
    assert np.isinf(farthest_hits(np.array([[0.0, 0.0, 20.0]]), np.array([[0.0, 0.0, 1.0]]), v, f))[0]


def test_block_lands_on_wall_and_dished_endplate_without_folding():
    grid = ogrid(TEMPLATE_RESOLUTIONS["coarse"])
    cb = core_boundary_ids(TEMPLATE_RESOLUTIONS["coarse"].core_cells)
    m = len(grid.outer)
    n_core = len(grid.nodes) - grid.shell_ring * m
    inner = n_core + (grid.shell_ring - 2) * m + np.arange(m)
    body = _dished_cylinder()
    block = _block(grid)
    planar = in_plane_map(block, grid.outer, np.arange(n_core), ring_lines(grid, cb), body, rim_depth_mm=2.0)
    mapped = axial_map(planar, grid.outer, inner, body)
    # the wall nodes of the inner layers are on the cylinder (chord sag of 3-degree facets: 0.014 mm)
    r_wall = np.linalg.norm(mapped[1:-1][:, grid.outer, :2], axis=2)
    assert np.abs(r_wall - RADIUS_MM).max() < 0.02
    # the bottom layer on the flat cap, the top layer on the dish: z = 15 - 2 (1 - r^2/400) at every node inside
    # the shell (the outermost ring copies the ring inside it)
    keep = np.setdiff1d(np.arange(len(grid.nodes)), grid.outer)
    assert np.abs(mapped[0, keep, 2] + HEIGHT_MM / 2).max() < 1e-6
    r2 = (mapped[-1, keep, :2] ** 2).sum(1)
    assert np.abs(mapped[-1, keep, 2] - (HEIGHT_MM / 2 - DISH_MM * (1 - r2 / RADIUS_MM**2))).max() < 0.05
    # no element folds; the thin cortical ring keeps its share of the radius
    sj = scaled_jacobian(mapped.reshape(-1, 3), _block_hexes(grid, len(mapped)))
    assert sj.min() > 0.3


def _waisted_body(half_height_mm=15.0):
    """A closed body of revolution, flat caps at z = +-15 mm, its wall flaring towards the endplates as a vertebral
    body's does: r(z) = 14 + 0.02 z^2 mm (14 mm at mid-height, 18.5 mm at the caps)."""
    cyl = pv.Cylinder(radius=1.0, height=2 * half_height_mm, direction=(0, 0, 1), resolution=120, capping=True)
    mesh = cyl.triangulate().subdivide(4, "linear").clean()
    v = np.asarray(mesh.points, dtype=float)
    v[:, :2] *= (14.0 + 0.02 * v[:, 2] ** 2)[:, None]
    return v, np.asarray(mesh.faces).reshape(-1, 4)[:, 1:]


@pytest.mark.parametrize("layers", [4, 9, 15])
def test_endplate_outline_is_the_wall_at_the_rim_depth_whatever_the_layer_count(layers):
    """The endplate layers (z = +-12 mm) take the wall's radius 2 mm inside them, r(10) = 14 + 0.02 * 100 = 16 mm,
    with 3, 8 or 14 body element layers (the coarser, medium and fine presets); the radius of the layer next to
    them (r(4) = 14.32 mm with 3 layers, r(9) = 15.62 mm with 8) would make the outline a property of the mesh."""
    grid = ogrid(TEMPLATE_RESOLUTIONS["coarse"])
    cb = core_boundary_ids(TEMPLATE_RESOLUTIONS["coarse"].core_cells)
    n_core = len(grid.nodes) - grid.shell_ring * len(grid.outer)
    block = _block(grid, layers=layers)
    out = in_plane_map(block, grid.outer, np.arange(n_core), ring_lines(grid, cb), _waisted_body(), rim_depth_mm=2.0)
    r = np.linalg.norm(out[[0, -1]][:, grid.outer, :2], axis=2)
    # the facets are flat between vertex rings 1.875 mm apart (z = 9.375, 11.25): r = 16.016 mm on that chord at
    # z = 10, less at most 16 (1 - cos 1.5 deg) = 0.005 mm between the 3-degree facets' corners
    assert np.abs(r - 16.0).max() < 0.02
    assert np.allclose(out[[0, -1], :, 2], block[[0, -1], :, 2])  # in the layers' own planes
    with pytest.raises(ValueError, match="rim depth"):
        in_plane_map(block, grid.outer, np.arange(n_core), ring_lines(grid, cb), _waisted_body(), rim_depth_mm=12.0)


def test_shared_outline_is_the_mean_in_plane_shape_at_each_height():
    grid = ogrid(TEMPLATE_RESOLUTIONS["coarse"])
    lower = _block(grid, half_mm=(20.0, 16.0), height_mm=0.0, layers=1)[0]
    upper = _block(grid, half_mm=(16.0, 12.0), height_mm=0.0, layers=1)[0] + [1.0, 2.0, 8.0]
    lo, up = shared_outline(lower, upper)
    expected_xy = grid.nodes * np.array([18.0, 14.0])
    # the axis is tilted by the 1, 2 mm offset, so compare in the plane perpendicular to it
    axis = np.array([1.0, 2.0, 8.0]) / np.linalg.norm([1.0, 2.0, 8.0])
    for layer, centre in ((lo, lower.mean(0)), (up, upper.mean(0))):
        assert np.allclose(layer.mean(0), centre)
    d_lo, d_up = lo - lo.mean(0), up - up.mean(0)
    assert np.allclose(d_lo - (d_lo @ axis)[:, None] * axis, d_up - (d_up @ axis)[:, None] * axis)
    assert np.allclose(np.linalg.norm(d_lo - (d_lo @ axis)[:, None] * axis, axis=1).max(), 18.0, rtol=0.05)
    assert expected_xy.shape == (len(grid.nodes), 2)


def test_plate_lands_on_an_open_patch_along_its_normal():
    grid = ogrid(TEMPLATE_RESOLUTIONS["coarse"])
    plate = _block(grid, height_mm=0.0, layers=1)
    patch = pv.Plane(center=(0, 0, 3.0), direction=(0, 0, 1), i_size=60, j_size=60, i_resolution=30, j_resolution=30)
    patch = patch.triangulate()
    out = plate_map(plate, np.asarray(patch.points, float), np.asarray(patch.faces).reshape(-1, 4)[:, 1:])
    assert np.allclose(out[0, :, 2], 3.0) and np.allclose(out[0, :, :2], plate[0, :, :2])


@pytest.fixture(scope="module")
def real_mean():
    from spinecohort.cohort.real import generate_real_cohort
    from spinecohort.ssm.model import build_ssm
    from spinecohort.ssm.procrustes import procrustes_align

    c = generate_real_cohort(4, seed=11)
    return build_ssm(procrustes_align(c.vertices).aligned).mean, c


def test_rays_morph_real_lumbar_bodies_and_discs_without_inverted_elements(real_mean):
    mean, c = real_mean
    t = build_template(mean, c.faces, c.landmarks, TEMPLATE_RESOLUTIONS["coarse"])
    nodes, report = morph_template(t, mean, c.faces, c.landmarks, MorphParameters(max_layers=0, surface_map="rays"))
    sj = scaled_jacobian(nodes, t.hexes)
    lumbar = np.concatenate(
        [idx for name, idx in t.elsets.items() if t.elset_kind[name] == "hex" and name.split("_")[1][0] == "L"]
    )
    # every lumbar body and disc, L5-S1 included (real concave endplates, waisted walls): no inverted element
    assert sj[lumbar].min() > 0.0
    # the lumbar walls and endplates are met: mean surface distance well under a millimetre
    assert (report.set_index("part").loc[["L1", "L2", "L3", "L4", "L5"], "distance_final_mean_mm"] < 0.6).all()


def test_disc_area_of_a_real_mean_is_the_same_at_coarse_and_medium(real_mean):
    """The L3-L4 disc's cross-section (its endplate node layers' quad areas) at the coarse and medium presets
    (4 and 8 body element layers, 16 and 24 rim nodes): measured 1515 and 1530 mm^2 (1.0 %, what a polygon of 16
    against 24 nodes on the same oval loses, ~1.4 %); with the outline of the layer next to the endplate,
    1447 and 1546 mm^2 (6.8 %)."""
    from spinecohort.rom.convergence import disc_geometry

    mean, c = real_mean
    area = {}
    for name in ("coarse", "medium"):
        t = build_template(mean, c.faces, c.landmarks, TEMPLATE_RESOLUTIONS[name])
        nodes, _ = morph_template(t, mean, c.faces, c.landmarks, MorphParameters(max_layers=0, surface_map="rays"))
        area[name] = float(disc_geometry(t, nodes, ["L3-L4"]).upper_endplate_mm2.iloc[0])
    assert abs(area["medium"] / area["coarse"] - 1.0) < 0.02, area


def test_hex_endplate_planes_of_a_real_mean_follow_the_rim_band(real_mean):
    """The hex model's endplate planes, on the layer nodes nearest the rim band, tilt as the tri model's rim-band
    planes do; on the whole concave layer they would follow the concavity's asymmetry."""
    from spinecohort.measure.spinopelvic import measure
    from spinecohort.virtual.shard_job import hex_landmarks

    mean, c = real_mean
    t = build_template(mean, c.faces, c.landmarks, TEMPLATE_RESOLUTIONS["coarse"])
    nodes, _ = morph_template(t, mean, c.faces, c.landmarks, MorphParameters(max_layers=0, surface_map="rays"))
    tri = measure(mean[None], c.landmarks)
    hexm = measure(nodes[None], hex_landmarks(t, c.landmarks, nodes, mean))
    # measured on the default cohort's mean: PI, PT, SS within 1.6 deg, LL within 2.5 deg, L1-L5 lordosis 3.4 deg
    for key, bound in (("PI", 2.0), ("PT", 2.0), ("SS", 2.0), ("LL", 3.0), ("LL_L1L5", 4.0)):
        assert abs(float(np.asarray(tri[key])[0]) - float(np.asarray(hexm[key])[0])) < bound, key
