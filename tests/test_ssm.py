"""GPA, PCA and the SSM quality measures against known transforms, closed forms and brute force."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from spinecohort.ssm.model import SSM, build_ssm
from spinecohort.ssm.procrustes import apply_transform, kabsch, procrustes_align
from spinecohort.ssm.quality import generalization, generalization_errors, specificity


def test_kabsch_recovers_a_known_rigid_and_similarity_transform(rng):
    x = rng.normal(size=(500, 3)) * [40, 30, 200]
    r_true = Rotation.from_rotvec([0.3, -0.5, 1.1]).as_matrix()
    t_true = np.array([12.0, -40.0, 7.5])
    y = 1.3 * x @ r_true.T + t_true
    r, s, t = kabsch(x, y, scaling=True)
    assert np.allclose(r, r_true, atol=1e-12) and s == pytest.approx(1.3, abs=1e-12)
    assert np.allclose(t, t_true, atol=1e-9)
    r, s, t = kabsch(x, x @ r_true.T + t_true)
    assert s == 1.0 and np.allclose(r, r_true, atol=1e-12)


def test_gpa_undoes_known_rotations_and_translations(small_cohort, rng):
    shapes = small_cohort.vertices
    base = procrustes_align(shapes)
    rots = Rotation.random(len(shapes), random_state=3).as_matrix()  # arbitrary orientations
    trans = rng.normal(0, 100, size=(len(shapes), 3))
    moved = np.einsum("pij,pnj->pni", rots, shapes) + trans[:, None]
    res = procrustes_align(moved)
    # same aligned cohort up to one global rigid transform
    r, s, t = kabsch(res.aligned.reshape(-1, 3), base.aligned.reshape(-1, 3))
    err = np.abs(apply_transform(res.aligned.reshape(-1, 3), r, s, t) - base.aligned.reshape(-1, 3)).max()
    assert err < 1e-6
    # a cohort of rigidly moved copies of one shape aligns to identical shapes
    copies = np.einsum("pij,nj->pni", rots, shapes[0]) + trans[:, None]
    res = procrustes_align(copies)
    assert np.abs(res.aligned - res.aligned[0]).max() < 1e-8
    assert res.n_iterations <= 3 and res.mean_change_mm[-1] < 1e-6


def test_gpa_with_scaling_recovers_relative_scales(small_cohort):
    # scaled copies of one patient: similarity GPA must divide exactly the imposed scale out
    scaled = small_cohort.vertices[0] * np.array([1.0, 1.1, 0.9, 1.25])[:, None, None]
    rigid = procrustes_align(scaled)
    sim = procrustes_align(scaled, scaling=True)
    # similarity GPA divides the imposed scale out: s_i * scale_i is the same for every shape
    prod = sim.scales * np.array([1.0, 1.1, 0.9, 1.25])
    assert np.allclose(prod, prod[0], rtol=1e-9)
    assert np.abs(sim.aligned - sim.aligned[0]).max() < 1e-8
    assert np.all(rigid.scales == 1.0)


def test_pca_reconstructs_training_shapes_and_variance_sums_to_one(small_cohort):
    aligned = procrustes_align(small_cohort.vertices).aligned
    ssm = build_ssm(aligned)
    p = len(aligned)
    assert ssm.n_modes == p - 1  # P shapes span at most P - 1 directions around their mean
    assert ssm.explained_variance_ratio.sum() == pytest.approx(1.0, abs=1e-12)
    flat = ssm.modes.reshape(ssm.n_modes, -1)
    assert np.allclose(flat @ flat.T, np.eye(ssm.n_modes), atol=1e-10)
    w = ssm.project(aligned)  # all modes: exact reconstruction
    assert np.abs(ssm.sample(w) - aligned).max() < 1e-9
    # Equation 4 sampling: mode weights in SD units; sample weights have unit variance over the cohort
    assert np.allclose(w.std(0, ddof=1), 1.0, atol=1e-9)
    assert np.array_equal(ssm.sample(np.zeros(3)), ssm.mean)


def test_pca_finds_known_modes_and_variances(rng):
    n = 300
    mean = rng.normal(size=(n, 3))
    d1 = rng.normal(size=(n, 3))
    d1 /= np.linalg.norm(d1)
    d2 = rng.normal(size=(n, 3))
    d2 -= (d2 * d1).sum() * d1
    d2 /= np.linalg.norm(d2)
    a = np.array([-3.0, -1.0, 0.0, 1.0, 3.0])  # coefficients along d1, mean 0, variance 5
    b = np.array([1.0, 0.0, -2.0, 0.0, 1.0])  # along d2, orthogonal to a and to 1, variance 1.5
    shapes = mean + a[:, None, None] * d1 + b[:, None, None] * d2
    ssm = build_ssm(shapes)
    assert ssm.n_modes == 2
    assert ssm.eigenvalues == pytest.approx([5.0, 1.5], abs=1e-10)
    assert abs((ssm.modes[0] * d1).sum()) == pytest.approx(1.0, abs=1e-10)
    assert ssm.modes_for_variance(0.95) == 2 and ssm.modes_for_variance(0.75) == 1  # 5/6.5 = 77 %


def test_generalization_equals_brute_force_leave_one_out(small_cohort):
    aligned = procrustes_align(small_cohort.vertices).aligned
    errs = generalization_errors(aligned)
    for i, m in ((0, 1), (3, 2), (7, 5)):
        rest = build_ssm(np.delete(aligned, i, axis=0))
        rec = rest.sample(rest.project(aligned[i][None], m))[0]
        brute = np.sqrt(((rec - aligned[i]) ** 2).sum(1).mean())
        assert errs[i, m - 1] == pytest.approx(brute, rel=1e-8)
    table = generalization(aligned)
    assert np.all(np.diff(table["generalization_mm"]) <= 1e-12)  # more modes never generalize worse


def test_specificity_equals_brute_force(small_cohort):
    aligned = procrustes_align(small_cohort.vertices).aligned
    ssm = build_ssm(aligned)
    spec = specificity(ssm, aligned, n_samples=20, max_modes=3, seed=4)
    rng = np.random.default_rng(4)
    for m in (1, 2, 3):
        w = rng.standard_normal((20, m))
        samples = ssm.sample(w)
        d = np.sqrt(((samples[:, None] - aligned[None]) ** 2).sum(-1).mean(-1)).min(1)
        assert spec.loc[m - 1, "specificity_mm"] == pytest.approx(d.mean(), rel=1e-8)


def test_ssm_loads_only_its_leading_modes(small_cohort, tmp_path):
    """SSM.load(path, n_modes) keeps the first modes: the same arrays as slicing a full load (a shard job
    samples 5 of the default 41 modes)."""
    ssm = build_ssm(small_cohort.vertices)
    ssm.save(tmp_path / "ssm.npz")
    full, head = SSM.load(tmp_path / "ssm.npz"), SSM.load(tmp_path / "ssm.npz", n_modes=2)
    assert np.array_equal(head.modes, full.modes[:2]) and np.array_equal(head.eigenvalues, full.eigenvalues[:2])
    assert np.array_equal(head.mean, full.mean) and head.n_modes == 2 and head.modes.flags.writeable
    assert np.array_equal(head.sample(np.ones((1, 2))), full.sample(np.ones((1, 2))))
    for bad in (0, full.n_modes + 1):
        with pytest.raises(ValueError, match=rf"ssm\.npz: asked for {bad} modes, the SSM has {full.n_modes}"):
            SSM.load(tmp_path / "ssm.npz", n_modes=bad)
