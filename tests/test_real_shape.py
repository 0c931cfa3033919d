"""Per-patient shape of the real-bone column: drawn disc heights and wedges, rigid plates, rigid arches."""

from __future__ import annotations

import numpy as np
import pytest

from spinecohort.cohort.shape import (
    CLIP_SD,
    DISC_HEIGHT_MEAN_MM,
    DISC_HEIGHT_SD_MM,
    LIFT_MAX_MM,
    LIFT_MIN_MM,
    WEDGE_SD_DEG,
    Shape,
    body_map,
    draw_shape,
    plate_motion,
    shaped_frames,
    shaped_vertices,
)


@pytest.fixture(scope="module")
def setup():
    from spinecohort.anatomy.reference import load_reference
    from spinecohort.cohort.real import first_use_reference, joint_pivots, reference_frames

    ref = first_use_reference(load_reference())
    fr = reference_frames(ref)
    return ref, fr, body_map(ref, fr), joint_pivots(ref)


def test_published_disc_heights_grow_caudally_and_are_thin_in_the_thorax():
    # Kunkel 2011: thoracic discs 4.5-7.2 mm; Twomey and Taylor 1985: lumbar 9.2-11.3 mm
    assert DISC_HEIGHT_MEAN_MM[0] == 4.5 and DISC_HEIGHT_MEAN_MM[10] == 7.2
    assert np.all(np.diff(DISC_HEIGHT_MEAN_MM[:11]) > 0) and DISC_HEIGHT_MEAN_MM[11:].min() >= 8.2
    assert len(DISC_HEIGHT_MEAN_MM) == len(DISC_HEIGHT_SD_MM) == 17


def test_drawn_disc_heights_and_wedges_have_the_configured_mean_and_sd():
    n = 2000
    rng = np.random.default_rng(1)
    disc, wedge = map(np.array, zip(*[draw_shape(rng) for _ in range(n)]))
    # the mean of n draws lies within 4 standard errors (SD / sqrt(n)) of the configured mean
    assert np.all(np.abs(disc.mean(0) - DISC_HEIGHT_MEAN_MM) < 4 * DISC_HEIGHT_SD_MM / np.sqrt(n))
    assert np.all(np.abs(wedge.mean(0)) < 4 * WEDGE_SD_DEG / np.sqrt(n))
    # clipping at 2.5 SD leaves 0.966 of the SD; the SD of n normal draws has a standard error of SD/sqrt(2n)
    tol = 4 / np.sqrt(2 * n)
    assert np.all(np.abs(disc.std(0, ddof=1) / DISC_HEIGHT_SD_MM - 0.966) < tol)
    assert np.all(np.abs(wedge.std(0, ddof=1) / WEDGE_SD_DEG - 0.966) < tol)
    assert np.all(np.abs(disc - DISC_HEIGHT_MEAN_MM) <= CLIP_SD * DISC_HEIGHT_SD_MM + 1e-12)


def test_plates_move_rigidly_and_the_arch_stays(setup):
    from spinecohort.cohort.landmarks import LEVELS

    ref, fr, bm, _ = setup
    rng = np.random.default_rng(2)
    shape = Shape(rng.normal(0, 2, 17), rng.normal(0, 2, 17), rng.normal(0, 3, 17))
    v = shaped_vertices(ref.vertices, fr, bm, shape)
    vertebra = ref.level >= 0
    # every vertex of the posterior elements (facets, laminae, processes) keeps its place: the facets hinge
    from spinecohort.anatomy.labels import region_id
    from spinecohort.cohort.shape import DEFORMABLE

    arch = vertebra & ~np.isin(ref.region, [region_id(r) for r in DEFORMABLE])
    assert arch.sum() > 0.4 * vertebra.sum()
    assert np.array_equal(v[arch], ref.vertices[arch])
    assert np.array_equal(v[~vertebra], ref.vertices[~vertebra])  # sacrum, hip bones, femurs
    frs = shaped_frames(fr, bm, shape)
    for i, lv in enumerate(LEVELS):
        for key, sets in (("sup", (ref.landmarks.endplate_sup, ref.landmarks.endplate_full_sup)), ("inf", None)):
            sets = sets or (ref.landmarks.endplate_inf, ref.landmarks.endplate_full_inf)
            rot, t = plate_motion(fr, bm, shape, i, key)
            idx = np.union1d(sets[0][lv], sets[1][lv])
            # the whole plate (rim band and concave plate) is carried by one rigid motion, to float precision
            assert np.abs(v[idx] - (ref.vertices[idx] @ rot.T + t)).max() < 1e-9, (lv, key)
            # so the least-squares plane of the moved rim band is the moved reference plane (the truth)
            rim = v[sets[0][lv]]
            c = rim.mean(0)
            n = np.linalg.svd(rim - c)[2][-1]
            n *= np.sign(n[2])
            assert np.abs(c - frs.centre[(lv, key)]).max() < 1e-9
            assert np.degrees(np.arccos(min(1.0, n @ frs.normal[(lv, key)]))) < 1e-5
            assert abs(np.linalg.det(rot) - 1.0) < 1e-12


def test_the_posed_discs_take_the_drawn_heights_and_the_bodies_the_difference(setup):
    from spinecohort.cohort.real import aim, draw_real_patient, pose_column, posed_chain, reach_discs

    ref, fr, bm, pivots = setup
    s1 = ref.vertices[ref.landmarks.rim_sup["S1"]]
    rng = np.random.default_rng(4)
    for _ in range(3):
        p, turn = draw_real_patient(rng, "x", fr)
        disc, wedge = draw_shape(rng)
        neutral = Shape(np.zeros(17), np.zeros(17), wedge)
        q = aim(p, turn, shaped_frames(fr, bm, neutral), pivots, s1)
        rigid = posed_chain(*_pose(q, turn, fr, bm, neutral, pivots, pose_column))
        shape = reach_discs(q, turn, fr, bm, neutral, disc, pivots)
        chain = posed_chain(*_pose(q, turn, fr, bm, shape, pivots, pose_column))
        # three fixed-point steps on a map whose slope is 1 up to the cosine of the plate tilts: < 0.01 mm, where
        # the lift is inside its range; where it is not, the disc stays taller than drawn
        free = (shape.lift_inf > LIFT_MIN_MM) & (shape.lift_inf < LIFT_MAX_MM)
        got = chain.lengths[0::2][::-1]
        assert free.sum() >= 13 and np.abs(got - disc)[free].max() < 0.01
        low, high = shape.lift_inf <= LIFT_MIN_MM, shape.lift_inf >= LIFT_MAX_MM
        assert np.all(got[low] > disc[low]) and np.all(got[high] < disc[high])
        # the lifts move no joint pivot: each body grows by what its lower disc loses (the arch is rigid), up to
        # the cosine between the lift (the body's mid-axis) and the disc's and body's mean normals, which differ
        # by up to 15 deg at L5-S1 (1 - cos 15 deg = 3.4 %)
        body_change = (chain.lengths[1::2] - rigid.lengths[1::2])[::-1]
        disc_change = (chain.lengths[0::2] - rigid.lengths[0::2])[::-1]
        assert np.all(np.abs(body_change + disc_change) <= 0.04 * np.abs(disc_change) + 0.01)
        # and the endplate normals, hence every angle of the alignment, stay
        assert np.abs(chain.normals - rigid.normals).max() < 1e-12


def _pose(q, turn, fr, bm, shape, pivots, pose_column):
    frs = shaped_frames(fr, bm, shape)
    pose, _ = pose_column(q, turn, frs, pivots, np.zeros(17))
    return pose, frs


def test_no_vertebra_folds_at_the_ends_of_its_lift_range(setup):
    """Each vertebra alone, its inferior plate lifted to either end of its range with the largest wedge change of
    either sign: VTK finds no crossing triangle pair in it (the ranges were scanned so, with 0.5 mm margin)."""
    from spinecohort.anatomy.surface import self_intersections

    ref, fr, bm, _ = setup
    for i, ii in enumerate(bm.idx):
        mask = np.zeros(len(ref.vertices), bool)
        mask[ii] = True
        local = np.full(len(mask), -1)
        local[ii] = np.arange(len(ii))
        faces = local[ref.faces[np.all(mask[ref.faces], axis=1)]]
        for lift in (LIFT_MIN_MM[i], LIFT_MAX_MM[i]):
            for wedge in (-CLIP_SD * WEDGE_SD_DEG, CLIP_SD * WEDGE_SD_DEG):
                one = np.arange(17) == i
                shape = Shape(np.zeros(17), np.where(one, lift, 0.0), np.where(one, wedge, 0.0))
                assert self_intersections(shaped_vertices(ref.vertices, fr, bm, shape)[ii], faces) == 0, (i, lift)
