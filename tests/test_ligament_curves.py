"""The lumbar segments' ligament curves of the same-geometry model (`spinecohort.fe.ligament_curves`): the law's
closed forms, the vendored table as its README describes it, and which segments and springs get them."""

from __future__ import annotations

import importlib.util
import os
from collections import Counter
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from spinecohort.cohort.landmarks import LEVELS
from spinecohort.fe.ligament_curves import (
    SegmentLigament,
    curve_table,
    ligament_segments,
    load_segment_ligaments,
    segment_force_n,
    toe_linear_n,
)
from spinecohort.fe.materials import DEFAULT_MATERIALS, FEMaterials, ligament_table, spring_table

ROOT = Path(__file__).resolve().parents[1]


def test_toe_linear_law_closed_form():
    # the toe k s^2 / (2 e_t) meets the line k (s - e_t / 2) at e_t in force (k e_t / 2) and slope (k)
    k, et = 100.0, 0.1
    s = np.array([-0.1, 0.0, 0.05, et, 0.3])
    np.testing.assert_allclose(toe_linear_n(s, et, k), [0.0, 0.0, 100 * 0.05**2 / 0.2, 5.0, 25.0])
    h = 1e-7
    left = (toe_linear_n(et, et, k) - toe_linear_n(et - h, et, k)) / h
    right = (toe_linear_n(et + h, et, k) - toe_linear_n(et, et, k)) / h
    assert left == pytest.approx(k, rel=1e-5) and right == pytest.approx(k, rel=1e-5)


def test_slack_ligament_pulls_after_its_laxity():
    # reference strain +0.5 on a 2 mm spring: rest length 3 mm, so nothing until 1 mm of elongation; at the end
    # of the toe (1 mm + 3 mm x 0.2) the two springs pull 2 x k e_t / 2
    lig = SegmentLigament(
        springs=2, mean_length_mm=2.0, reference_strain=0.5, transition_strain=0.2, stiffness_n_per_spring=50.0
    )
    np.testing.assert_allclose(segment_force_n(lig, [-1.0, 0.0, 0.99, 1.0]), 0.0, atol=1e-12)
    assert segment_force_n(lig, 1.0 + 3.0 * 0.2) == pytest.approx(2 * 50.0 * 0.2 / 2)


def test_taut_ligament_acts_from_the_neutral_posture_and_unloads():
    # reference strain -0.2 on a 10 mm spring: rest length 8 mm, strain 0.25 in the neutral posture (past the
    # toe, 0.1): force 0 there, slope springs x k / rest length, and fully unloaded (-k (0.25 - 0.05)) once it has
    # shortened by 2 mm
    lig = SegmentLigament(
        springs=1, mean_length_mm=10.0, reference_strain=-0.2, transition_strain=0.1, stiffness_n_per_spring=80.0
    )
    assert segment_force_n(lig, 0.0) == pytest.approx(0.0, abs=1e-12)
    assert segment_force_n(lig, 0.4) == pytest.approx(80.0 * 0.4 / 8.0)
    assert segment_force_n(lig, -2.0) == pytest.approx(-80.0 * (0.25 - 0.05))
    assert segment_force_n(lig, -5.0) == pytest.approx(-80.0 * (0.25 - 0.05))


def test_curve_table_splits_the_force_over_the_fibres():
    lig = SegmentLigament(
        springs=9, mean_length_mm=15.0, reference_strain=-0.03, transition_strain=0.08, stiffness_n_per_spring=291.0
    )
    one, three = np.array(curve_table(lig, 1, 15.0)), np.array(curve_table(lig, 3, 15.0))
    np.testing.assert_allclose(three[:, 0], one[:, 0] / 3)
    assert np.all(np.diff(one[:, 1]) > 0) and np.all(np.diff(one[:, 0]) >= 0)  # ascending elongation, force
    assert one[0, 1] == -15.0 and one[-1, 1] == pytest.approx(30.0)  # -rest length .. max strain 2
    np.testing.assert_allclose(np.interp([0.0], one[:, 1], one[:, 0]), 0.0, atol=1e-12)
    with pytest.raises(ValueError, match="1 fibre"):
        curve_table(lig, 0, 15.0)


def test_vendored_table_is_the_readme_s():
    # data/ligaments/README.md: five segments x seven groups; the spring counts, the reference strains by group
    # and the stiffness range quoted there
    laws = load_segment_ligaments()
    assert len(laws) == 35 and {s for s, _ in laws} == {"L1-L2", "L2-L3", "L3-L4", "L4-L5", "L5-S1"}
    springs = {"CL": 20, "ITL": 4, "ALL": 9, "PLL": 5, "LF": 11, "ISL": 8, "SSL": 1}
    eps_r = {"SSL": -0.08, "LF": -0.03, "ISL": -0.02, "ALL": -0.03, "CL": 0.55, "PLL": 0.12, "ITL": 0.02}
    for (seg, g), lig in laws.items():
        assert lig.springs == springs[g] and lig.reference_strain == eps_r[g], (seg, g)
    k = [lig.stiffness_n_per_spring for lig in laws.values()]
    assert min(k) == laws[("L4-L5", "ISL")].stiffness_n_per_spring == 2.5 and max(k) == 582.0
    with pytest.raises(ValueError, match="unknown source"):
        load_segment_ligaments("goel1995")


def test_every_ligament_joins_two_neighbouring_bones(template):
    segs = ligament_segments(template)
    bones = [*LEVELS, "S1"]
    pairs = {f"{a}-{b}" for a, b in zip(bones[:-1], bones[1:])}
    assert set(segs) <= pairs and len(segs) == len(template.ligaments)
    # the single-spring ligaments: one per segment (ISL, SSL) or per side (ITL, none at L5-S1: no transverse process)
    for g, per_segment in (("ISL", 1), ("SSL", 1)):
        assert set(Counter(segs[template.elsets[f"LIG_{g}"]]).values()) == {per_segment}


def test_spring_table_takes_the_segment_curve_where_there_is_one():
    lumbar = spring_table(DEFAULT_MATERIALS, "ISL", "L4-L5", 1, 8.7)
    assert lumbar == curve_table(DEFAULT_MATERIALS.segment_ligaments[("L4-L5", "ISL")], 1, 8.7)
    thoracic = spring_table(DEFAULT_MATERIALS, "ISL", "T6-T7", 1, 8.7)
    assert thoracic == ligament_table(DEFAULT_MATERIALS.ligaments["ISL"], 8.7)
    assert spring_table(FEMaterials(segment_ligaments={}), "ISL", "L4-L5", 1, 8.7) == thoracic


REMUS_REPO = Path(
    os.environ.get("SPINECOHORT_REMUS_REPO", "/work/.mirror/RemusR9+artisynth_lumbosacralSpineModel/repo")
)


@pytest.mark.skipif(not REMUS_REPO.exists(), reason="the Remus repository's git directory (SPINECOHORT_REMUS_REPO)")
def test_the_script_rebuilds_the_vendored_table():
    # scripts/build_lumbar_ligaments.py on the upstream repository gives the vendored CSV exactly
    spec = importlib.util.spec_from_file_location("build", ROOT / "scripts" / "build_lumbar_ligaments.py")
    build = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(build)
    pd.testing.assert_frame_equal(build.table(REMUS_REPO), pd.read_csv(build.OUT), check_dtype=False)
