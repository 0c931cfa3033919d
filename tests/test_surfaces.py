import numpy as np

from spinecohort.cohort.surfaces import (
    closed_loft,
    edge_check,
    segment_superellipsoid,
    signed_volume,
    superellipse_ring,
    torus,
    uv_sphere,
)


def test_sphere_is_closed_oriented_and_on_radius():
    v, f = uv_sphere(np.array([1.0, 2.0, 3.0]), 25.0, 48, 23)
    assert edge_check(f) == (True, True)
    # every vertex exactly on the sphere (femoral-head sphere fits rely on it)
    assert np.allclose(np.linalg.norm(v - [1, 2, 3], axis=1), 25.0, atol=1e-12)
    # inscribed polyhedron: volume within 1 % below 4/3 pi r^3 = 65449.8 mm^3
    vol = signed_volume(v, f)
    assert 0.98 * 65449.85 < vol < 65449.85


def test_torus_volume_matches_closed_form():
    v, f = torus(np.zeros(3), [0.3, 0.2, 1.0], 20.0, 5.0, 96, 32)
    assert edge_check(f) == (True, True)
    # 2 pi^2 R r^2 = 9869.6 mm^3; the polyhedral approximation is within 1 %
    assert abs(signed_volume(v, f) - 2 * np.pi**2 * 20 * 25) / 9869.6 < 0.01


def test_planar_cap_is_centrally_symmetric_so_its_mean_is_the_centre():
    ring = superellipse_ring(20.0, 15.0, 48, 2.6)
    assert np.allclose(ring[:24], -ring[24:], atol=1e-9)
    rings = np.stack([np.c_[ring, np.full(48, z)] for z in np.linspace(0, 25, 8)])
    v, f, info = closed_loft(rings, bottom_cap_rings=4, top_cap_rings=4)
    assert edge_check(f) == (True, True)
    assert np.allclose(v[info["top_cap"]].mean(0), [0, 0, 25], atol=1e-9)
    assert np.allclose(v[info["top_cap"], 2], 25.0)


def test_segment_superellipsoid_spans_its_segment():
    p0, p1 = np.array([0.0, 0, 0]), np.array([30.0, 0, 10])
    v, f = segment_superellipsoid(p0, p1, 5.0, 2.0, np.array([0, 0, 1.0]))
    assert edge_check(f) == (True, True)
    axis = (p1 - p0) / np.linalg.norm(p1 - p0)
    proj = (v - p0) @ axis
    # the rounded tips reach half_thickness (2 mm) beyond both ends
    assert np.isclose(proj.min(), -2.0) and np.isclose(proj.max(), np.linalg.norm(p1 - p0) + 2.0)
