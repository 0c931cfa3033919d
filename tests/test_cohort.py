"""Cohort loading and each bad input's error (file named, problem named)."""

import shutil

import numpy as np
import pandas as pd
import pytest

from spinecohort.cohort.landmarks import Landmarks
from spinecohort.cohort.loading import CohortInputError, load_cohort, load_cohort_npz, save_cohort, write_cohort_folder
from spinecohort.cohort.stl_io import write_stl


@pytest.fixture()
def folder(tmp_path, small_cohort):
    c = small_cohort
    d = tmp_path / "cohort"
    write_cohort_folder(d, c.ids[:4], c.vertices[:4], c.faces, c.landmarks, c.table.head(4))
    return d


def _load(d, **kw):
    return load_cohort(sorted(d.glob("*.stl")), d / "patients.csv", d / "landmarks.json", **kw)


def test_folder_loads_and_round_trips_through_npz(folder, tmp_path, small_cohort):
    c = _load(folder)
    assert c.ids == ["P01", "P02", "P03", "P04"]
    assert np.abs(c.points - small_cohort.vertices[:4]).max() < 3.1e-5  # float32 STL storage
    save_cohort(tmp_path / "c.npz", c)
    back = load_cohort_npz(tmp_path / "c.npz")
    assert np.array_equal(back.points, c.points) and back.ids == c.ids
    assert back.table["PI"].tolist() == pytest.approx(c.table["PI"].tolist())
    assert np.array_equal(back.landmarks.endplate_sup["S1"], c.landmarks.endplate_sup["S1"])
    # the landmarks alone (what a shard job reads), without the meshes: the same index sets
    alone = Landmarks.from_cohort(tmp_path / "c.npz")
    assert alone.to_dict() == c.landmarks.to_dict()


def test_nan_coordinates(folder, small_cohort):
    v = small_cohort.vertices[1].copy()
    v[10] = np.nan
    write_stl(folder / "P02.stl", v, small_cohort.faces)
    with pytest.raises(CohortInputError, match=r"P02\.stl: \d+ triangles have NaN or infinite"):
        _load(folder)


def test_different_vertex_count_means_no_correspondence(folder, small_cohort):
    f = small_cohort.faces[:-200]
    used = np.unique(f)
    remap = np.full(len(small_cohort.vertices[2]), -1)
    remap[used] = np.arange(len(used))
    write_stl(folder / "P03.stl", small_cohort.vertices[2][used], remap[f])
    with pytest.raises(CohortInputError, match=r"P03\.stl: \d+ vertices but .*P01\.stl has \d+.*correspondence"):
        _load(folder)


def test_same_count_other_order_means_no_correspondence(folder, small_cohort):
    rng = np.random.default_rng(0)
    perm = rng.permutation(len(small_cohort.faces))
    write_stl(folder / "P04.stl", small_cohort.vertices[3], small_cohort.faces[perm])
    with pytest.raises(CohortInputError, match=r"P04\.stl: .*correspondence"):
        _load(folder)


def test_metres_are_recognised_and_units_convert(folder, small_cohort):
    for k in range(4):
        write_stl(folder / f"P0{k + 1}.stl", small_cohort.vertices[k] / 1000.0, small_cohort.faces)
    with pytest.raises(CohortInputError, match=r"P01\.stl: largest extent is 0\.\d+ mm.*looks like metres"):
        _load(folder)
    c = _load(folder, units="m")  # the documented fix works
    assert np.abs(c.points[0] - small_cohort.vertices[0]).max() < 1e-3


def test_degenerate_faces(folder, small_cohort):
    v = small_cohort.vertices[0].copy()
    f = small_cohort.faces
    # collapse 2 % of the triangles onto their first vertex's position (zero area)
    bad = f[: len(f) // 50]
    v[bad[:, 1]] = v[bad[:, 0]] + 1e-7
    v[bad[:, 2]] = v[bad[:, 0]] - 1e-7
    write_stl(folder / "P01.stl", v, f)
    with pytest.raises(CohortInputError, match=r"P01\.stl: \d+ of \d+ triangles .* are degenerate"):
        _load(folder)


def test_sheet_ids_must_match_the_files(folder):
    t = pd.read_csv(folder / "patients.csv")
    t.loc[1, "ID"] = "P99"
    t.to_csv(folder / "patients.csv", index=False)
    with pytest.raises(
        CohortInputError, match=r"patients\.csv: patient IDs do not match .*no row for P02.*no STL for P99"
    ):
        _load(folder)


def test_landmarks_must_fit_the_meshes(folder, tmp_path, small_cohort):
    other = tmp_path / "other"
    shutil.copytree(folder, other)
    (other / "landmarks.json").write_text("{not json")
    with pytest.raises(ValueError, match="landmarks.json: not a readable landmark file"):
        _load(other)
