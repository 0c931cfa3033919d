import numpy as np
import pytest

from spinecohort.cohort.stl_io import MeshInputError, merge_vertices, read_stl, write_stl


@pytest.mark.parametrize("ascii", [False, True])
def test_round_trip_preserves_vertex_order(tmp_path, small_cohort, ascii):
    v, f = small_cohort.vertices[0], small_cohort.faces
    path = tmp_path / "p.stl"
    write_stl(path, v, f, ascii=ascii)
    v2, f2 = read_stl(path)
    assert np.array_equal(f2, f)  # same vertex order, same triangles
    # float32 storage: |error| <= half an ulp of float32 at ~600 mm = 3.1e-5 mm
    assert np.abs(v2 - v).max() < 3.1e-5


def test_binary_stl_is_reproducible(tmp_path, small_cohort):
    v, f = small_cohort.vertices[0], small_cohort.faces
    write_stl(tmp_path / "a.stl", v, f)
    write_stl(tmp_path / "b.stl", v, f)
    data = (tmp_path / "a.stl").read_bytes()
    assert data == (tmp_path / "b.stl").read_bytes()  # no time stamp in the header
    assert len(data) == 84 + 50 * len(f)


def test_merge_numbers_vertices_by_first_occurrence():
    tri = np.array([[[5, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 0], [1, 0, 0], [9, 9, 9]]], float)
    v, f = merge_vertices(tri)
    assert v.tolist() == [[5, 0, 0], [1, 0, 0], [0, 1, 0], [9, 9, 9]]  # not sorted: first occurrence
    assert f.tolist() == [[0, 1, 2], [2, 1, 3]]


def test_broken_files_name_the_file_and_the_problem(tmp_path, small_cohort):
    good = tmp_path / "good.stl"
    write_stl(good, small_cohort.vertices[0], small_cohort.faces)
    cases = {
        "empty.stl": (b"", "empty file"),
        "trunc.stl": (good.read_bytes()[:5000], "truncated or corrupted"),
        "tiny.stl": (b"\x00" * 40, "truncated STL"),
        "text.stl": (b"solid x\n facet normal 0 0 1\n outer loop\n vertex 1 2\n", "not a valid STL"),
    }
    for name, (data, msg) in cases.items():
        (tmp_path / name).write_bytes(data)
        with pytest.raises(MeshInputError, match=msg) as err:
            read_stl(tmp_path / name)
        assert name in str(err.value)
    with pytest.raises(MeshInputError, match="cannot read"):
        read_stl(tmp_path / "missing.stl")
