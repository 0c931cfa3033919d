"""Chords of a closed surface (spinecohort.anatomy.isthmus) on shapes with closed-form answers."""

from __future__ import annotations

import numpy as np
import pytest
import pyvista as pv

from spinecohort.anatomy import isthmus as I


def _triangles(mesh: pv.PolyData) -> np.ndarray:
    mesh = mesh.triangulate().clean()
    return np.asarray(mesh.points, float)[mesh.faces.reshape(-1, 4)[:, 1:]]


def test_line_crossings_of_a_box_and_the_chords():
    # box a in [-1, 1], r in [-2, 2], s in [-3, 3]; the transverse line through (0, -5, 0.3) crosses r = -2, +2
    tri = _triangles(pv.Box(bounds=(-1, 1, -2, 2, -3, 3), level=2, quads=False))
    ts = I.line_crossings(tri, np.array([[0.0, -5.0, 0.3], [0.2, 0.0, 0.1]]), np.array([0.0, 1.0, 0.0]))
    np.testing.assert_allclose(ts[0], [3.0, 7.0], atol=1e-9)
    assert I.first_chord_ahead(ts[0]) == pytest.approx((3.0, 7.0))
    assert np.isnan(I.chord_through(ts[0])[0])  # the origin is outside the box
    assert I.chord_through(ts[1]) == pytest.approx((-2.0, 2.0))  # the origin is inside
    assert np.isnan(I.first_chord_ahead(ts[1])[0])


def test_isthmus_of_a_converging_pedicle_is_its_true_width():
    """A closed cylinder of radius 4 mm (64-gon) whose axis converges anteriorly by 20 deg, 12 mm right of the
    mid-line: the isthmus is 8 mm wide and 8 mm high, found by the line turned by 20 deg; a transverse line
    alone would cross it obliquely, 8 / cos 20 = 8.51 mm."""
    theta = np.radians(20.0)
    axis = (np.cos(theta), -np.sin(theta), 0.0)  # anterior and medial for the right pedicle
    tri = _triangles(pv.Cylinder(center=(-20.0, 12.0, 0.0), direction=axis, radius=4.0, height=14.0, resolution=64))
    ist = I.pedicle_isthmus(tri, +1.0, height_mm=1.0, a_wall=-10.0, a_back=-30.0)
    assert ist.width == pytest.approx(8.0, abs=0.02)
    assert ist.height == pytest.approx(8.0, abs=0.02)
    assert ist.medial_angle_deg == 20.0
    assert ist.centre[2] == pytest.approx(0.0, abs=1e-6)  # re-centred from the 1 mm guess
    transverse = I.pedicle_isthmus(tri, +1.0, 1.0, -10.0, -30.0, angles_deg=(0.0,))
    assert transverse.width == pytest.approx(8.0 / np.cos(theta), abs=0.03)


def test_canal_midline_and_its_search_for_a_lamina():
    # body box a in [-15, 15]; lamina box a in [-33, -27], s in [3.8, 10]: from the body centre at s = 0 the
    # mid-line passes below the lamina, so the nearest height on the 0.5 mm search grid with a lamina behind
    # (s = 4) is used
    body = _triangles(pv.Box(bounds=(-15, 15, -20, 20, -12, 12), level=4, quads=False))
    lamina = _triangles(pv.Box(bounds=(-33, -27, -14, 14, 3.8, 10), level=4, quads=False))
    tri = np.concatenate([body, lamina])
    wall, lam, height = I.canal_midline(tri, np.array([0.0, 0.0, 0.0]))
    assert (wall, lam, height) == pytest.approx((-15.0, -27.0, 4.0))
    with pytest.raises(ValueError, match="no canal found"):
        I.canal_midline(body, np.array([0.0, 0.0, 0.0]))
