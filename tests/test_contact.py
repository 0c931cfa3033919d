"""Disc contact: a disc the linear SSM collapses is opened by a distraction that keeps every angle.

Closed-form cases (two parallel endplate patches, a tilted plate) and the small cohort's SSM at +-3 SD,
whose L5-S1 disc collapses in the linear model (8 patients extrapolate badly)."""

import numpy as np
import pytest

from spinecohort.cohort.landmarks import DISCS
from spinecohort.fe.models import hex_points_checked
from spinecohort.measure.spinopelvic import measure
from spinecohort.mesh.contact import disc_gaps, distraction_summary, level_offsets, resolve_contact
from spinecohort.mesh.hex_ssm import contact_offsets, transfer_fields
from spinecohort.mesh.quality.verdict import scaled_jacobian
from spinecohort.store.zarr_store import grid_weights
from spinecohort.virtual.shard_job import hex_landmarks, sample_points


def plate(z, tilt_deg=0.0, n=7):
    """A square 20 x 20 mm patch of n x n points at height z, tilted about x by tilt_deg."""
    u, v = np.meshgrid(np.linspace(-10, 10, n), np.linspace(-10, 10, n))
    t = np.radians(tilt_deg)
    return np.c_[u.ravel(), v.ravel() * np.cos(t), z + v.ravel() * np.sin(t)]


def test_gap_of_parallel_and_tilted_plates():
    lower, upper = plate(0.0), plate(4.0)
    pts = np.concatenate([lower, upper])[None]
    lo, up = np.arange(49), np.arange(49, 98)
    gaps, normals = disc_gaps(pts, [up], [lo])
    assert gaps[0, 0] == pytest.approx(4.0, abs=1e-12) and normals[0, 0] == pytest.approx([0, 0, 1])
    # an upper plate tilted 10 deg about its centre at 1 mm: its low edge is 1 - 10 sin(10 deg) = -0.736 mm
    pts = np.concatenate([lower, plate(1.0, 10.0)])[None]
    gaps, _ = disc_gaps(pts, [up], [lo])
    assert gaps[0, 0] == pytest.approx(1.0 - 10 * np.sin(np.radians(10)), abs=1e-12)


def endplate_plane(points: np.ndarray, patch: np.ndarray, towards: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares plane of the vertices ``patch`` of every model: centre (B, 3) and unit normal (B, 3)
    oriented towards ``towards`` (B, 3) (the other endplate's centre).  points (B, N, 3) mm."""
    p = points[:, patch].astype(np.float64)
    centre = p.mean(axis=1)
    x = p - centre[:, None]
    _, vecs = np.linalg.eigh(np.einsum("bki,bkj->bij", x, x))  # ascending: column 0 = plane normal
    normal = vecs[:, :, 0]
    flip = np.einsum("bc,bc->b", normal, towards - centre) < 0
    normal[flip] *= -1.0
    return centre, normal


def test_batched_disc_gaps_equal_the_plane_fit_disc_by_disc_bit_for_bit():
    """disc_gaps fits all discs in one numba pass + one batched eigh; the reference is endplate_plane and the
    numpy gap, disc by disc.  Ragged sets (patches of 49, 30 and 12 vertices), float64 and float32 points far
    from the origin (0.4 m, where summation order would show), 5 models: identical to the bit."""
    rng = np.random.default_rng(3)
    base = np.concatenate([plate(0.0), plate(5.0, 8.0), plate(11.0, -4.0), plate(16.0, 3.0)])
    pts = 400.0 + base[None] + rng.normal(0.0, 0.3, size=(5, len(base), 3))
    lower = [np.arange(49), np.arange(49, 79), np.arange(98, 110)]
    upper = [np.arange(49, 98), np.arange(98, 147), np.arange(147, 196)[::2]]
    for points in (pts, pts.astype(np.float32)):
        gaps, normals = disc_gaps(points, upper, lower)
        for j, (up, lo) in enumerate(zip(upper, lower)):
            centre, n = endplate_plane(points, lo, points[:, up].astype(np.float64).mean(axis=1))
            ref = np.einsum("bkc,bc->bk", points[:, up] - centre[:, None], n).min(axis=1)
            assert np.array_equal(normals[:, j], n) and np.array_equal(gaps[:, j], ref), j
        # the plate at 5 mm tilted 8 deg: its low edge 5 - 10 sin(8 deg) = 3.61 mm, less the noise (0.3 mm sd)
        assert 2.5 < gaps[0, 0] < 3.7


def test_level_offsets_open_each_disc_to_the_minimum_and_accumulate_cranially():
    gaps = np.full((1, 17), 5.0)
    gaps[0, 16] = -2.0  # L5-S1 interpenetrates by 2 mm
    gaps[0, 10] = 0.5  # T11-T12 just too thin
    normals = np.tile([0.0, 0.0, 1.0], (1, 17, 1))
    off = level_offsets(gaps, normals, 1.0)
    # L5 rises by 1 - (-2) = 3 mm; T12..L4 by the same; T11 and above by 3 + 0.5 mm
    assert off[0, 16, 2] == pytest.approx(3.0) and off[0, 11, 2] == pytest.approx(3.0)
    assert off[0, 10, 2] == pytest.approx(3.5) and off[0, 0, 2] == pytest.approx(3.5)
    s = distraction_summary(gaps, off)
    assert s["discs_opened"][0] == "T11-T12;L5-S1" and s["distraction_mm"][0] == pytest.approx(3.5)
    assert s["min_disc_gap_before_mm"][0] == -2.0
    assert not level_offsets(np.full((1, 17), 1.0), normals, 1.0).any()  # exactly at the minimum: untouched


@pytest.fixture(scope="module")
def extreme(ssm, template, small_cohort):
    """The hex SSM of the unmorphed template with and without contact, at the corners of a 3-mode grid."""
    w = grid_weights(3, [-3, 0, 3]).astype(float)
    with_c = transfer_fields(template, template.nodes, ssm, small_cohort.landmarks, 3, "smooth", 1.0)
    without = transfer_fields(template, template.nodes, ssm, small_cohort.landmarks, 3, "smooth", None)
    return w, with_c, without


def test_linear_models_collapse_and_distracted_ones_keep_every_disc_open(extreme, ssm, template, small_cohort):
    w, with_c, without = extreme
    gaps, off = contact_offsets(with_c, w)
    collapsed = gaps.min(axis=1) < 0
    # the 8-patient SSM at +-3 SD brings some upper endplate through the one below (that is why this exists)
    assert collapsed.sum() >= 1
    tri, hexp, g_before, applied = sample_points(ssm, with_c, w, return_contact=True)
    assert np.allclose(g_before, gaps) and np.allclose(applied, off)
    g_after, _ = disc_gaps(hexp.astype(float), with_c.contact.upper, with_c.contact.lower)
    assert g_after.min() >= 1.0 - 1e-4  # float32 storage
    # models that needed nothing are exactly the linear formula
    untouched = ~np.abs(off).max(axis=(1, 2)).astype(bool)
    t_lin, h_lin = sample_points(ssm, without, w)
    assert np.array_equal(hexp[untouched], h_lin[untouched]) and np.array_equal(tri[untouched], t_lin[untouched])
    # the sacrum, pelvis and femoral heads never move; only vertebrae (and discs) do
    fixed = with_c.contact.tri_level < 0
    assert np.array_equal(tri[:, fixed], t_lin[:, fixed])


def test_distraction_keeps_the_spinopelvic_angles(extreme, ssm, template, small_cohort):
    w, with_c, without = extreme
    tri, hexp = sample_points(ssm, with_c, w)
    t_lin, _ = sample_points(ssm, without, w)
    moved = np.flatnonzero(np.abs(tri - t_lin).max(axis=(1, 2)) > 0)
    assert len(moved) >= 1
    a = measure(tri[moved].astype(float), small_cohort.landmarks)
    b = measure(t_lin[moved].astype(float), small_cohort.landmarks)
    # a translation of whole vertebrae: endplate orientations, hence every angle, are unchanged
    for p in ("PI", "PT", "SS", "LL", "TK_T4T12", "Cobb"):
        assert np.abs(a[p] - b[p]).max() < 1e-3, p
    # on the hex model every disc's anterior and posterior heights are at least the 1 mm minimum gap
    # (heights are measured at rim points, the gap is the smallest over the whole endplate)
    hl = hex_landmarks(template, small_cohort.landmarks)
    h = measure(hexp[moved].astype(float), hl)
    heights = h[[c for c in h.columns if c.startswith(("DHa_", "DHp_"))]].to_numpy()
    assert heights.shape[1] == 2 * len(DISCS) and heights.min() >= 1.0 - 1e-3


def test_every_extreme_model_is_valid_after_distraction(extreme, template):
    w, with_c, without = extreme
    n = template.n_hex_nodes
    inv_linear = [(scaled_jacobian(without.sample(wi)[:n], template.hexes) <= 0).any() for wi in w]
    assert any(inv_linear)  # without contact some corner model inverts its L5-S1 disc
    distracted = 0
    for wi in w[np.flatnonzero(inv_linear)]:
        pts, rep = hex_points_checked(template, with_c, wi)  # distraction, then untangling of what is left
        assert rep["invalid_after"] == 0 and scaled_jacobian(pts[:n], template.hexes).min() > 0
        distracted += rep["distraction_mm"] > 0
    assert distracted >= 1


def test_in_place_offsets_equal_the_dense_formula_to_the_bit(extreme, ssm):
    """The shard job's in-place kernels (two levels per hex node, a gather per vertex) against the dense
    definition ``points + einsum(hex, offsets)`` / ``points + offsets[tri_level]``: the same float64 bits,
    since the dense sum's other 15-17 terms are exact zeros."""
    w, with_c, _ = extreme
    c = with_c.contact
    t = ssm.mean + np.tensordot(w, ssm.deformation_fields(w.shape[1]), axes=(1, 0))
    h = with_c.mean + np.tensordot(w, with_c.fields[: w.shape[1]], axes=(1, 0))
    gaps, off = c.level_offsets(h)
    moved = np.flatnonzero(np.abs(off).max(axis=(1, 2)) > 0)
    assert 1 <= len(moved) < len(w)  # some models distracted, some not
    dense_h, dense_t = h.copy(), t.copy()
    dense_h[moved] += c.hex_offsets(off[moved])
    dense_t[moved] += c.tri_offsets(off[moved])
    assert (c.hex != 0).sum(axis=1).max() == 2  # disc nodes follow two levels
    g, o = resolve_contact(t, h, c)
    assert np.array_equal(g, gaps) and np.array_equal(o, off)
    assert h.tobytes() == dense_h.tobytes() and t.tobytes() == dense_t.tobytes()
    # float32 points (fe.models passes them too) take the dense path cast to float32
    h32 = (with_c.mean + np.tensordot(w, with_c.fields[: w.shape[1]], axes=(1, 0))).astype(np.float32)
    want, (_, off32) = h32.copy(), c.level_offsets(h32)
    m32 = np.flatnonzero(np.abs(off32).max(axis=(1, 2)) > 0)
    want[m32] += c.hex_offsets(off32[m32]).astype(np.float32)
    resolve_contact(None, h32, c)
    assert len(m32) and np.array_equal(h32, want)


def test_contact_map_round_trips_through_npz(extreme, tmp_path):
    _, with_c, _ = extreme
    with_c.save(tmp_path / "h.npz")
    from spinecohort.mesh.hex_ssm import HexSSM

    back = HexSSM.load(tmp_path / "h.npz")
    c, d = with_c.contact, back.contact
    assert d.min_height_mm == 1.0 and np.array_equal(c.tri_level, d.tri_level)
    assert np.allclose(c.hex, d.hex, atol=1e-7) and all(np.array_equal(a, b) for a, b in zip(c.upper, d.upper))
    assert len(d.lower) == len(DISCS)
