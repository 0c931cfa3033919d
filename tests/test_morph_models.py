"""Morphing the template onto the SSM mean, and single models on demand (with Jacobian repair)."""

from dataclasses import replace

import numpy as np
import pytest

from spinecohort.cohort.landmarks import LEVELS
from spinecohort.cohort.stl_io import read_stl
from spinecohort.fe.models import hex_points_checked, parse_model_id, virtual_model, write_model
from spinecohort.mesh.hex_ssm import transfer_fields
from spinecohort.mesh.morph import MorphParameters, morph_template, ray_weights
from spinecohort.mesh.quality.kernels import morph_scaled_jacobian_nb
from spinecohort.mesh.quality.verdict import scaled_jacobian
from spinecohort.mesh.repair import RepairError
from spinecohort.mesh.template import TEMPLATE_RESOLUTIONS, build_template
from spinecohort.ssm.model import build_ssm
from spinecohort.ssm.procrustes import procrustes_align
from spinecohort.store.zarr_store import grid_weights


@pytest.fixture(scope="module")
def morphed(small_cohort):
    ssm = build_ssm(procrustes_align(small_cohort.vertices).aligned)
    t = build_template(ssm.mean, small_cohort.faces, small_cohort.landmarks, TEMPLATE_RESOLUTIONS["coarse"])
    nodes, report = morph_template(
        t, ssm.mean, small_cohort.faces, small_cohort.landmarks, MorphParameters(max_iter=40, max_layers=2)
    )
    return ssm, t, nodes, report


def test_morphed_mean_is_on_the_surface_and_valid(morphed):
    _, t, nodes, report = morphed
    assert len(report) == 18  # 17 bodies + the S1 plate
    # the seed's bound: mean surface distance < 0.04 mm; after projection it is round-off
    assert (report["distance_final_mean_mm"] < 0.04).all() and (report["distance_final_max_mm"] < 1e-6).all()
    assert (report["distance_before_mm"] > 0.1).all() or report["part"].tolist()[-1] == "S1"
    sj = scaled_jacobian(nodes, t.hexes)
    assert sj.min() > 0.2  # no inverted element, none nearly so
    # discs re-filled between the morphed endplates: CEP 0.7 mm at every node above the S1 plate
    n2 = len(t.grid.nodes)
    layers = nodes[: t.n_hex_nodes].reshape(-1, n2, 3)
    assert np.allclose(np.linalg.norm(layers[1] - layers[0], axis=1), 0.7, atol=1e-9)
    # surface-element nodes are untouched SSM vertices
    assert np.array_equal(nodes[t.n_hex_nodes :], t.nodes[t.n_hex_nodes :])


def test_the_default_morph_does_not_amplify_round_off(small_cohort):
    # config's morph (no BCPD layer on the interior): a 1e-12 mm perturbation of the mean moves no node by more
    # than 1e-9 mm, so the mean model is the same on every CPU.  With BCPD layers (the `morphed` fixture's
    # max_layers=2) the same perturbation moved interior nodes by up to 4.4 mm here and 3.4 mm on the default
    # cohort (docs/explanation/hex-mesh.md): the BLAS kernels decided the model.
    ssm = build_ssm(procrustes_align(small_cohort.vertices).aligned)
    t = build_template(ssm.mean, small_cohort.faces, small_cohort.landmarks, TEMPLATE_RESOLUTIONS["coarse"])
    noise = np.random.default_rng(1).normal(0, 1e-12, ssm.mean.shape)
    a, _ = morph_template(t, ssm.mean, small_cohort.faces, small_cohort.landmarks)
    b, _ = morph_template(t, ssm.mean + noise, small_cohort.faces, small_cohort.landmarks)
    assert np.abs(a - b).max() < 1e-9
    assert scaled_jacobian(a, t.hexes).min() > 0.45  # measured 0.503 (one BCPD layer: 0.482)


def test_ray_fractions_run_from_core_to_surface(morphed):
    _, t, _, _ = morphed
    outer_of, frac = ray_weights(t.grid, t.resolution.core_cells)
    assert np.all(frac[t.grid.outer] == pytest.approx(1.0))
    ring = frac[outer_of >= 0]
    assert ring.min() > 0 and ring.max() == pytest.approx(1.0)
    # shell: the ring just inside the surface sits at 1 - shell_fraction of the ray
    assert np.unique(np.round(ring, 6)).tolist()[-2] == pytest.approx(1 - t.resolution.shell_fraction)


def test_model_ids_and_repair_of_an_inverted_model(morphed, small_cohort, tmp_path):
    ssm, t, nodes, _ = morphed
    assert parse_model_id("model_08403", 5, [-3, -2, -1, 0, 1, 2, 3]) == 8403
    with pytest.raises(ValueError, match="outside the grid of 27 models"):
        parse_model_id("model_00027", 3, [-3, 0, 3])
    hssm = transfer_fields(t, nodes, ssm, small_cohort.landmarks, 3, "smooth")
    # A deliberate inversion: mode 1 pushes one interior nucleus node of the L3-L4 disc 1.6 element
    # heights through its upper neighbour.
    n2 = len(t.grid.nodes)
    layer = next(i for i, ly in enumerate(t.layers) if ly["kind"] == "disc" and ly["disc"] == "L3-L4" and ly["k"] == 2)
    node = layer * n2 + 0  # core corner node, interior to the mesh
    up = nodes[node + n2] - nodes[node]
    hssm.fields[:] = 0.0
    hssm.fields[0, node] = 1.6 * up
    pts, rep = hex_points_checked(t, hssm, np.array([1.0, 0.0, 0.0]))
    assert rep["invalid_before"] > 0 and rep["invalid_after"] == 0 and rep["min_sj_after"] > 0
    assert scaled_jacobian(pts[: t.n_hex_nodes], t.hexes).min() > 0
    assert rep["nodes_moved"] >= 1 and rep["max_displacement_mm"] > 0


def test_extreme_models_of_a_tiny_ssm_are_refused_by_name(morphed, small_cohort, tmp_path):
    """With 8 patients, +-3 SD of the first modes pushes L5 into the sacrum in the triangulated SSM itself
    (a collapsed L5-S1 disc): without the disc-contact distraction (tests/test_contact.py) no untangling
    can fix the deepest of those collapses (the model with the most inverted hexes: 61 of the 4 such
    models' 155), and the error names the model."""
    ssm, t, nodes, _ = morphed
    hssm = transfer_fields(t, nodes, ssm, small_cohort.landmarks, 3, "smooth")
    w = grid_weights(3, [-3, 0, 3]).astype(float)
    sj = morph_scaled_jacobian_nb(hssm.mean[: t.n_hex_nodes], hssm.fields[:, : t.n_hex_nodes], w, t.hexes)
    bad = np.flatnonzero((sj <= 0).any(1))
    good = np.flatnonzero(~(sj <= 0).any(1))
    assert len(good) > 20
    vm = virtual_model(int(good[0]), ssm, hssm, t, 3, [-3, 0, 3])
    out = write_model(vm, "stl", tmp_path / "m.stl", t, small_cohort.faces)
    v, f = read_stl(out)
    assert np.array_equal(f, small_cohort.faces) and np.abs(v - ssm.sample(w[good[0]])).max() < 3.1e-5
    deepest = int(bad[np.argmax((sj[bad] <= 0).sum(1))])
    with pytest.raises(RepairError, match=f"model_{deepest:05d} .* cannot be repaired"):
        virtual_model(deepest, ssm, hssm, t, 3, [-3, 0, 3])


def test_a_rim_band_endplate_morphs_through_the_whole_endplate(small_cohort):
    # A real endplate's clinical patch is its rim band (the ring apophysis, docs/explanation/anatomy.md); the whole
    # concave endplate is `endplate_full_*`.  Here the synthetic patches play the whole endplates and their outer
    # rings the rim bands: the template must be placed and morphed exactly as on the whole patches (the rim band's
    # ring only would pull the endplate layers' core nodes out onto the ring and invert the bodies and discs).
    lm = small_cohort.landmarks
    banded = replace(
        lm,
        endplate_sup={**{lv: lm.rim_sup[lv] for lv in LEVELS}, "S1": lm.endplate_sup["S1"]},
        endplate_inf={lv: lm.rim_inf[lv] for lv in LEVELS},
        endplate_full_sup=lm.endplate_sup,
        endplate_full_inf=lm.endplate_inf,
    )
    ssm = build_ssm(procrustes_align(small_cohort.vertices).aligned)
    res = TEMPLATE_RESOLUTIONS["coarse"]
    t = build_template(ssm.mean, small_cohort.faces, lm, res)
    expected, _ = morph_template(t, ssm.mean, small_cohort.faces, lm)
    tb = build_template(ssm.mean, small_cohort.faces, banded, res)
    assert np.array_equal(tb.nodes, t.nodes)
    nodes, _ = morph_template(tb, ssm.mean, small_cohort.faces, banded)
    assert np.array_equal(nodes, expected)
    assert scaled_jacobian(nodes, tb.hexes).min() > 0.45  # as the default morph (0.503)
    rim_only = replace(banded, endplate_full_sup={}, endplate_full_inf={})
    ring, _ = morph_template(
        build_template(ssm.mean, small_cohort.faces, rim_only, res), ssm.mean, small_cohort.faces, rim_only
    )
    assert (scaled_jacobian(ring, tb.hexes) <= 0).sum() > 100


def test_wall_nodes_move_along_their_rays_on_a_waisted_body():
    # A vertebral body's wall is waisted: radius 20 - 3 sin(pi z / 20) mm over z 0..20 mm (the waist 3 mm deep at
    # mid-height).  Closest points of nodes on a cylinder of radius 22 mm slide towards the rims (by up to a few mm
    # in height, more than a coarse layer's quarter of the body); the ray from the layer's centre keeps each node's
    # height and lands on the wall at that height: radius 20 - 3 sin(pi z / 20).
    from spinecohort.mesh.morph import _closest_points, _ray_points

    theta = np.linspace(0.0, 2.0 * np.pi, 121)[:-1]
    z = np.linspace(0.0, 20.0, 81)
    radius = 20.0 - 3.0 * np.sin(np.pi * z / 20.0)
    verts = np.stack(
        [radius[:, None] * np.cos(theta), radius[:, None] * np.sin(theta), np.broadcast_to(z[:, None], (81, 120))], -1
    ).reshape(-1, 3)
    i, j = np.meshgrid(np.arange(80), np.arange(120), indexing="ij")
    a, b = i * 120 + j, i * 120 + (j + 1) % 120
    faces = np.concatenate([np.stack([a, b, b + 120], -1), np.stack([a, b + 120, a + 120], -1)]).reshape(-1, 3)
    heights = np.array([2.5, 5.0, 7.5, 12.5, 15.0, 17.5])
    nodes = np.stack([np.full(6, 22.0), np.zeros(6), heights], 1)
    centres = np.stack([np.zeros(6), np.zeros(6), heights], 1)
    on_ray = _ray_points(nodes, centres, verts, faces)
    assert np.allclose(on_ray[:, 2], heights, atol=1e-9) and np.allclose(on_ray[:, 1], 0.0, atol=1e-9)
    # on the facetted wall: between the chord (cos of half the 3 deg sector, here 0 deg: a vertex column) and the
    # linear interpolation of the radius between rows 0.25 mm apart (error < 3 (pi/20)^2 0.25^2 / 8 = 0.0023 mm)
    assert np.allclose(on_ray[:, 0], 20.0 - 3.0 * np.sin(np.pi * heights / 20.0), atol=3e-3)
    closest = _closest_points(nodes, verts, faces)
    assert np.abs(closest[:, 2] - heights).max() > 1.0  # the closest points slide along the waist
