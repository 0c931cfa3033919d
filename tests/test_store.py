"""The sharded cohort store: IDs, quantized round trip against the SSM formula, core Zarr v3 codecs only
(bytes identical to zarr-python's own write, read by tensorstore), concurrent shard writes, checksums and
rebuild after an interrupted or corrupted shard, refusal of an older store format."""

import itertools
import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import google_crc32c
import numpy as np
import pytest
import zarr

from spinecohort.ssm.model import build_ssm
from spinecohort.ssm.procrustes import procrustes_align
from spinecohort.store import zarr_store as S

# Half the 2^-10 mm quantum; the rounded value is exact in float32 (|x| * 2^10 < 2^24), so nothing else adds.
# 2^-11 mm = 0.00049 mm: inside the 0.001 mm tolerance of "the same coordinates".
BOUND_MM = 2.0**-11
#: the codecs of the Zarr v3 core specification (https://zarr-specs.readthedocs.io/en/latest/v3/codecs/)
CORE_CODECS = {"bytes", "transpose", "blosc", "zstd", "gzip", "crc32c", "sharding_indexed"}


# ------------------------------------------------------------------------------------------------ IDs
def test_model_ids_follow_the_design_formula():
    # sum_i (w_i + 3) 7^(5-i): all -3 -> 0, all +3 -> 7^5 - 1, all 0 -> 3 * (7^4+7^3+7^2+7+1) = 8403
    w = np.array([[-3] * 5, [3] * 5, [0] * 5, [-3, -3, -3, -3, -2], [-2, -3, -3, -3, -3], [1, -1, 2, 0, -3]])
    expected = [0, 16806, 8403, 1, 2401, 4 * 2401 + 2 * 343 + 5 * 49 + 3 * 7 + 0]
    assert S.model_id(w).tolist() == expected
    assert S.model_name(16806) == "model_16806" and S.model_name([0, 7])[1] == "model_00007"


def test_ids_and_weights_round_trip_over_the_whole_grid():
    g = S.grid_weights()
    assert g.shape == (16807, 5)
    assert np.array_equal(S.model_id(g), np.arange(16807))
    # row order is itertools.product order over the levels, mode 1 slowest
    assert np.array_equal(g, np.array(list(itertools.product(range(-3, 4), repeat=5)), float))
    # a non-default grid from config: 3 modes at 5 half-SD levels
    lv = (-1.0, -0.5, 0.0, 0.5, 1.0)
    g3 = S.grid_weights(3, lv)
    assert len(g3) == 125 and np.array_equal(S.model_id(g3, lv), np.arange(125))
    assert S.weights_of(np.int64(124), 3, lv).tolist() == [1.0, 1.0, 1.0]


def test_bad_ids_and_weights_raise():
    with pytest.raises(ValueError, match="off the grid"):
        S.model_id([0, 0, 0, 0, 4])
    with pytest.raises(ValueError, match="off the grid"):
        S.model_id([0, 0.5, 0, 0, 0])
    with pytest.raises(ValueError, match="must lie in"):
        S.weights_of(16807)
    with pytest.raises(ValueError, match="integers"):
        S.weights_of(1.5)
    with pytest.raises(ValueError, match="strictly increasing"):
        S.grid_weights(2, (0, -1))


def test_shards_are_contiguous_id_ranges():
    assert S.n_shards(16807, 343) == 49
    assert S.shard_range(0, 343, 16807) == (0, 343)
    assert S.shard_range(48, 343, 16807) == (16464, 16807)
    # a shard of 343 fixes modes 1 and 2: shard 24 is w1 = 0 (24 // 7 = 3 -> 0 SD), w2 = 0 (24 % 7 = 3)
    w = S.weights_of(np.arange(*S.shard_range(24, 343)))
    assert np.all(w[:, :2] == 0) and len(np.unique(w[:, 2:], axis=0)) == 343
    assert S.n_shards(27, 10) == 3 and S.shard_range(2, 10, 27) == (20, 27)
    with pytest.raises(ValueError, match="out of range"):
        S.shard_range(49, 343, 16807)


# ------------------------------------------------------------------------------------- store contents
@pytest.fixture(scope="module")
def ssm(small_cohort):
    return build_ssm(procrustes_align(small_cohort.vertices).aligned)


def _hex_stand_in(tri):
    """Every third surface node as a stand-in hex node set (hex has its own node count)."""
    return tri[:, ::3]


def test_model_read_back_equals_the_ssm_formula_within_the_quantization_bound(ssm, tmp_path):
    # grid of 2 modes x 7 levels = 49 models in shards of 7 -> 7 shards
    levels = tuple(range(-3, 4))
    n_tri = ssm.mean.shape[0]
    n_hex = _hex_stand_in(ssm.mean[None]).shape[1]
    path = tmp_path / "cohort.zarr"
    S.create_store(
        path,
        n_tri,
        n_hex,
        n_modes=2,
        levels=levels,
        shard_models=7,
        attrs={"ssm_sha256": "0" * 64, "template_sha256": "1" * 64},
    )
    assert S.check_store(path) == list(range(7))  # nothing written yet
    for s in range(7):
        shapes = ssm.sample(S.weights_of(np.arange(*S.shard_range(s, 7)), 2, levels))
        S.write_shard(path, s, shapes, _hex_stand_in(shapes))
    assert S.check_store(path) == []
    root = zarr.open(str(path))
    assert root.attrs["error_bound_mm"] == pytest.approx(BOUND_MM, rel=1e-12)
    assert root.attrs["units"] == "mm" and root.attrs["ssm_sha256"] == "0" * 64
    assert root["weights"][40].tolist() == [2.0, 2.0]  # 40 = 5 * 7 + 5 -> levels index (5, 5)
    errs = []
    for i in (0, 24, 40, 48):
        truth = ssm.sample(S.weights_of(i, 2, levels))
        tri, hexp = S.read_model(path, i)
        assert tri.dtype == np.float32 and tri.shape == (n_tri, 3) and hexp.shape == (n_hex, 3)
        errs.append(np.abs(tri - truth).max())
        assert np.abs(hexp - _hex_stand_in(truth[None])[0]).max() <= BOUND_MM
        # a plain zarr read decodes to the same millimetres without project code
        assert np.array_equal(root["tri/points"][i], tri)
    # within the bound, and genuinely quantized: the worst rounding comes close to half a quantum
    assert max(errs) <= BOUND_MM < 1e-3 and max(errs) > 0.00045
    assert np.array_equal(S.read_shard(path, 3, "hex"), root["hex/volume_points"][21:28])


def _shared_surface_store(path, seed=7):
    """A store whose hex model (12 volume nodes + 20 surface nodes) shares its surface nodes with the 50 tri
    vertices, as the template's skins do: 3 modes x 3 levels = 27 models in shards of 9, chunks of 3."""
    rng = np.random.default_rng(seed)
    sv = rng.permutation(50)[:20]
    S.create_store(path, 50, 32, 3, (-1, 0, 1), 9, chunk_models=3, surface_vertex=sv)
    data = {}
    for s in range(3):
        tri = rng.uniform(-400, 400, (9, 50, 3))
        hexp = np.concatenate([rng.uniform(-400, 400, (9, 12, 3)), tri[:, sv]], axis=1)
        S.write_shard(path, s, tri, hexp)
        data[s] = tri, hexp
    return sv, data


def test_the_hex_models_surface_nodes_are_stored_once_and_read_back_exactly(tmp_path):
    path = tmp_path / "c.zarr"
    sv, data = _shared_surface_store(path)
    assert S.check_store(path) == []
    root = zarr.open_group(str(path), mode="r")
    # stored: 12 volume nodes per model, not 32; the 20 others come from tri/points through hex/surface_vertex
    assert root["hex/volume_points"].shape == (27, 12, 3) and root.attrs["n_hex_nodes"] == 32
    assert np.array_equal(root["hex/surface_vertex"][:], sv)
    for s, (_, hexp) in data.items():
        _, hexa = S.read_model(path, 9 * s + 4)
        assert hexa.shape == (32, 3) and np.array_equal(hexa, S.quantize_mm(hexp[4]))
        assert np.array_equal(S.read_shard(path, s, "hex"), S.quantize_mm(hexp))
    # the documented recipe, with zarr-python alone
    i = 13
    recipe = np.concatenate([root["hex/volume_points"][i], root["tri/points"][i][root["hex/surface_vertex"][:]]])
    assert np.array_equal(recipe, S.read_model(path, i)[1])
    # the shard objects hold 12 + 50 nodes per model; a store that kept all 32 hex nodes holds 82 and is larger
    # (at this size blosc's headers and the shard index are a good part of either; the default store's ratio
    # is the benchmark's)
    full = tmp_path / "full.zarr"
    S.create_store(full, 50, 32, 3, (-1, 0, 1), 9, chunk_models=3)
    for s, (tri, hexp) in data.items():
        S.write_shard(full, s, tri, hexp)
    size = [sum(o.stat().st_size for o in S._shard_objects(x, 1)[:2]) for x in (path, full)]
    assert size[0] < size[1], size


def test_a_hex_surface_node_that_is_not_its_tri_vertex_is_refused_and_the_shard_kept(tmp_path):
    path = tmp_path / "c.zarr"
    sv, data = _shared_surface_store(path)
    before = _files(path)
    tri, hexp = data[1]
    bad = hexp.copy()
    bad[5, 12 + 7, 2] += 0.01  # 10 um off its tri vertex: more than the 2^-10 mm quantum, so it would be lost
    with pytest.raises(ValueError, match=r"model_00014: hex node 19 is not its tri vertex \d+ as stored"):
        S.write_shard(path, 1, tri, bad)
    assert _files(path) == before and S.check_store(path) == []
    # a difference below the rounding is the same stored value: accepted
    near = hexp.copy()
    near[:, 12:] = S.quantize_mm(near[:, 12:]).astype(np.float64) + 1e-6
    S.write_shard(path, 1, tri, near)
    assert np.array_equal(S.read_shard(path, 1, "hex"), S.quantize_mm(hexp))


def test_a_second_zarr_implementation_assembles_the_hex_model(tmp_path):
    """tensorstore reads the three arrays and the documented recipe gives the hex model zarr-python gives."""
    ts = pytest.importorskip("tensorstore")
    path = tmp_path / "c.zarr"
    _, data = _shared_surface_store(path, seed=11)

    def arr(name):
        return ts.open({"driver": "zarr3", "kvstore": {"driver": "file", "path": str(path / name)}}).result()

    sv = arr("hex/surface_vertex").read().result()
    assert sv.dtype == np.int32
    for i in (0, 13, 26):
        tri = arr("tri/points")[i].read().result()
        hexa = np.concatenate([arr("hex/volume_points")[i].read().result(), tri[sv]])
        assert np.array_equal(hexa, S.read_model(path, i)[1])
        assert np.abs(hexa - data[i // 9][1][i % 9]).max() <= BOUND_MM


def test_bad_surface_vertex_is_refused(tmp_path):
    with pytest.raises(ValueError, match="surface_vertex must index the 10 tri vertices"):
        S.create_store(tmp_path / "a.zarr", 10, 8, 2, (0, 1), 2, surface_vertex=[0, 10])
    with pytest.raises(ValueError, match="leave no volume node"):
        S.create_store(tmp_path / "b.zarr", 10, 2, 2, (0, 1), 2, surface_vertex=[0, 1])


def test_float32_encoding_round_trips_within_one_float32_rounding(tmp_path):
    rng = np.random.default_rng(5)
    x = rng.uniform(-470, 470, size=(4, 300, 3))
    path = tmp_path / "c.zarr"
    S.create_store(path, 300, 300, n_modes=2, levels=(0, 1), shard_models=4, encoding="float32")
    assert S.error_bound_mm("float32") == pytest.approx(2.0**-24 * 512)
    S.write_shard(path, 0, x, -x)
    tri, hexp = S.read_model(path, 3)
    assert np.array_equal(tri, x[3].astype(np.float32)) and np.array_equal(hexp, (-x[3]).astype(np.float32))


def test_quantization_is_exact_rounding_to_multiples_of_2_pow_minus_10_mm():
    x = np.array([0.0, 1.0 / 2048, 3.0 / 2048, -469.123456, 511.9999, 1e-7, 0.6 / 1024, 1.4 / 1024])
    q = S.quantize_mm(x)
    # ties round to even multiples (numpy rint): 1/2048 -> 0, 3/2048 -> 2/1024; 0.6/1024 and 1.4/1024 -> 1/1024
    assert q.dtype == np.float32 and q.tolist()[:3] == [0.0, 0.0, 2.0 / 1024] and q.tolist()[-2:] == [1 / 1024] * 2
    assert np.all(q.astype(np.float64) * 1024 == np.rint(q.astype(np.float64) * 1024))  # exact multiples
    assert np.abs(q - x).max() <= BOUND_MM
    # the worst case is a tie: exactly half a quantum, 2^-11 mm = 0.00049 mm
    assert np.abs(q[1] - x[1]) == BOUND_MM


def test_q9_encoding_stores_multiples_of_2_pow_minus_9_mm_within_half_of_it(tmp_path):
    rng = np.random.default_rng(9)
    x = rng.uniform(-470, 470, size=(4, 300, 3))
    path = tmp_path / "q9.zarr"
    S.create_store(path, 300, 300, n_modes=2, levels=(0, 1), shard_models=4, encoding="float32-q9")
    # half the 2^-9 mm quantum: 2^-10 mm = 0.00098 mm, recorded in the store's attributes
    assert S.error_bound_mm("float32-q9") == 2.0**-10
    assert zarr.open_group(str(path), mode="r").attrs["quantum_mm"] == 2.0**-9
    S.write_shard(path, 0, x, -x)
    tri, hexp = S.read_model(path, 2)
    assert np.all(tri.astype(np.float64) * 512 == np.rint(tri.astype(np.float64) * 512))  # exact multiples
    assert np.abs(tri - x[2]).max() <= 2.0**-10 and np.abs(hexp + x[2]).max() <= 2.0**-10
    assert np.array_equal(tri, S.quantize_mm(x[2], "float32-q9"))


def _store_with_shards(path, n_tri, n_hex, n_modes, levels, shard_models, chunk_models, seed=0):
    S.create_store(path, n_tri, n_hex, n_modes, levels, shard_models, chunk_models=chunk_models)
    total = S.n_models(n_modes, levels)
    rng = np.random.default_rng(seed)
    data = {}
    for s in range(S.n_shards(total, shard_models)):
        a, b = S.shard_range(s, shard_models, total)
        data[s] = (rng.uniform(-400, 400, (b - a, n_tri, 3)), rng.uniform(-400, 400, (b - a, n_hex, 3)))
        S.write_shard(path, s, *data[s])
    return data


def test_shard_objects_are_byte_identical_to_zarr_pythons_own_write(tmp_path):
    # 27 models in shards of 10 (the last one partial: 7 models) and chunks of 5 (a partial boundary chunk
    # and one chunk slot beyond the array in the last shard)
    ours, theirs = tmp_path / "ours.zarr", tmp_path / "zarr.zarr"
    data = _store_with_shards(ours, 40, 25, 3, (-1, 0, 1), 10, 5)
    S.create_store(theirs, 40, 25, 3, (-1, 0, 1), 10, chunk_models=5)
    z = zarr.open_group(str(theirs), mode="r+")
    for s, (tri, hexp) in data.items():
        a, b = S.shard_range(s, 10, 27)
        z["tri/points"][a:b] = S.quantize_mm(tri)
        z["hex/volume_points"][a:b] = S.quantize_mm(hexp)
    for s in data:
        for obj in S._shard_objects(ours, s)[:2]:
            assert obj.read_bytes() == (theirs / obj.relative_to(ours)).read_bytes(), obj


@pytest.mark.parametrize("encoding", S.ENCODINGS)
@pytest.mark.parametrize("shard_models, chunk", [(9, 3), (10, 5), (14, 7)])
def test_linear_points_are_stored_as_their_float64_formula_is(tmp_path, encoding, shard_models, chunk):
    """ShardWriter.add(LinearPoints) forms every chunk straight from mean + fields . w (+ the level offsets of
    the distracted models); its shard objects are byte-identical to writing the float64 formula (numpy), for
    the unrolled 7-model chunk and the general one, a partial boundary chunk (27 models in shards of 10: the
    last holds 7 = a chunk of 5 and one of 2), node blocks of 512 with a partial last one (1,100 nodes), three
    modes (zero terms in front of them) and both encodings."""
    rng = np.random.default_rng(7)
    n_tri, n_vol, n_levels = 1100, 30, 4
    mean = rng.uniform(-300, 300, (n_tri, 3))
    fields = rng.normal(0.0, 4.0, (3, n_tri, 3))
    level = rng.integers(-1, n_levels, n_tri)
    terms = S.linear_fields(mean, fields)
    assert terms.shape == (6, 3, n_tri) and not terms[:2].any()  # 3 fields + the mean, after 2 zero terms
    stores = {k: tmp_path / f"{k}.zarr" for k in ("floats", "linear")}
    for path in stores.values():
        S.create_store(path, n_tri, n_vol, 3, (-1, 0, 1), shard_models, encoding=encoding, chunk_models=chunk)
    for shard in range(S.n_shards(27, shard_models)):
        a, b = S.shard_range(shard, shard_models, 27)
        w = S.weights_of(np.arange(a, b), 3, (-1, 0, 1)) * 1.7
        offsets = rng.normal(0.0, 2.0, (b - a, n_levels, 3)) * (rng.random((b - a, 1, 1)) < 0.5)
        tri = mean + np.tensordot(w, fields, axes=(1, 0))
        for k in range(b - a):
            if np.abs(offsets[k]).max() > 0:
                tri[k, level >= 0] += offsets[k, level[level >= 0]]
        vol = rng.uniform(-100, 100, (b - a, n_vol, 3))
        for kind, path in stores.items():
            writer = S.ShardWriter(path, shard)
            writer.add(tri if kind == "floats" else S.LinearPoints(terms, w, level, offsets), vol)
            writer.close()
        for obj in S._shard_objects(stores["floats"], shard)[:2]:
            assert obj.read_bytes() == (stores["linear"] / obj.relative_to(stores["floats"])).read_bytes(), obj
    # and what is stored reads back as the formula within the quantization bound
    z = zarr.open_group(str(stores["linear"]), mode="r")
    assert np.abs(z["tri/points"][26] - tri[-1]).max() <= S.error_bound_mm(encoding, 512.0)


def test_linear_points_out_of_range_or_non_finite_are_refused(tmp_path):
    path = tmp_path / "c.zarr"
    S.create_store(path, 20, 5, 2, (-1, 0, 1), 3, chunk_models=3)
    mean, fields = np.zeros((20, 3)), np.zeros((2, 20, 3))
    fields[1, 4, 2] = 400.0  # the third model (w2 = 1.5) puts node 4 at z = 600 mm
    w = np.array([[-1.0, -1.0], [-1.0, 0.0], [-1.0, 1.5]])
    writer = S.ShardWriter(path, 0)
    with pytest.raises(ValueError, match=r"tri/points of shard 0 exceeds the store's max_abs_mm=512.0 .*600\.0\]"):
        writer.add(S.LinearPoints(S.linear_fields(mean, fields), w), np.zeros((3, 5, 3)))
    writer.abort()
    fields[0, 7, 0] = np.nan
    writer = S.ShardWriter(path, 0)
    with pytest.raises(ValueError, match="tri/points of shard 0 has non-finite coordinates"):
        writer.add(S.LinearPoints(S.linear_fields(mean, fields), w), np.zeros((3, 5, 3)))
    writer.abort()
    assert S.shard_problems(path)[0]  # nothing was kept: the shard reads as not written


def test_every_array_uses_core_zarr_v3_codecs_only(tmp_path):
    path = tmp_path / "c.zarr"
    S.create_store(path, 30, 20, 2, (-1, 0, 1), 3)

    def names(codecs):
        for c in codecs:
            yield c["name"]
            for key in ("codecs", "index_codecs"):
                yield from names(c.get("configuration", {}).get(key, []))

    for arr in ("weights", "tri/points", "hex/volume_points", "hex/surface_vertex"):
        meta = json.loads((path / arr / "zarr.json").read_text())
        assert set(names(meta["codecs"])) <= CORE_CODECS, arr
        assert meta["zarr_format"] == 3 and meta["data_type"] in ("float32", "float64", "int32")


def test_a_second_zarr_implementation_reads_the_store(tmp_path):
    """tensorstore (Google's C++ Zarr v3 driver, not zarr-python) decodes the same float32 millimetres."""
    ts = pytest.importorskip("tensorstore")  # in the [test] extra
    path = tmp_path / "c.zarr"
    data = _store_with_shards(path, 40, 25, 3, (-1, 0, 1), 9, 3, seed=3)
    for arr, k in (("tri/points", 0), ("hex/volume_points", 1)):
        t = ts.open({"driver": "zarr3", "kvstore": {"driver": "file", "path": str(path / arr)}}).result()
        assert t.dtype == ts.float32 and t.shape == (27, (40, 25)[k], 3)
        got = t[9:18].read().result()  # shard 1, all three chunks
        assert np.array_equal(got, S.quantize_mm(data[1][k]))
        assert np.abs(got - data[1][k]).max() <= BOUND_MM
    w = ts.open({"driver": "zarr3", "kvstore": {"driver": "file", "path": str(path / "weights")}}).result()
    assert np.array_equal(w[26].read().result(), [1.0, 1.0, 1.0])


def test_a_store_of_the_older_format_is_refused_with_a_rebuild_message(tmp_path):
    path = tmp_path / "old.zarr"
    S.create_store(path, 30, 20, 2, (-1, 0, 1), 3)
    meta = json.loads((path / "zarr.json").read_text())
    # 1: int32 deltas with numcodecs filters; 2: blosc clevel 1 on 1 MiB blocks (a rewrite would mix encodings);
    # 3: hex/points held the surface nodes too (a format-4 reader would find no hex/volume_points)
    for old in ("spinecohort.cohort-store/1", "spinecohort.cohort-store/2", "spinecohort.cohort-store/3"):
        meta["attributes"]["format"] = old
        (path / "zarr.json").write_text(json.dumps(meta))
        for call in (lambda: S.read_model(path, 0), lambda: S.check_store(path), lambda: S.ShardWriter(path, 0)):
            with pytest.raises(S.StoreVersionError, match=rf"{old[-7:]}.*Rebuild it"):
                call()


def test_bad_input_raises_value_error(tmp_path):
    path = tmp_path / "c.zarr"
    with pytest.raises(ValueError, match="unknown encoding"):
        S.create_store(path, 10, 10, n_modes=2, levels=(0, 1), shard_models=2, encoding="float16")
    with pytest.raises(ValueError, match="must be >= 1 and divide shard_models"):
        S.create_store(tmp_path / "q.zarr", 10, 10, n_modes=2, levels=(0, 1), shard_models=4, chunk_models=3)
    with pytest.raises(ValueError, match="not a cohort store"):
        S.read_model(tmp_path / "nothing.zarr", 0)
    S.create_store(path, 10, 5, n_modes=2, levels=(0, 1), shard_models=2)
    with pytest.raises(ValueError, match="already exists"):
        S.create_store(path, 10, 5, n_modes=2, levels=(0, 1), shard_models=2)
    ok = np.zeros((2, 10, 3))
    with pytest.raises(ValueError, match=r"hex points of shard 0 must have shape \(2, 5, 3\)"):
        S.write_shard(path, 0, ok, np.zeros((2, 10, 3)))
    with pytest.raises(ValueError, match="non-finite"):
        S.write_shard(path, 0, np.full((2, 10, 3), np.nan), ok[:, :5])
    with pytest.raises(ValueError, match="max_abs_mm"):
        S.write_shard(path, 0, ok + 600.0, ok[:, :5])
    with pytest.raises(ValueError, match="out of range"):
        S.write_shard(path, 2, ok, ok[:, :5])
    with pytest.raises(ValueError, match="out of range"):
        S.read_model(path, 4)


# ------------------------------------------------------------------------ concurrency and fault tolerance
N_TRI, N_HEX, SHARD_MODELS = 2000, 700, 9
_WRITER = f"""
import sys, numpy as np
from spinecohort.store.zarr_store import write_shard, shard_range
path, shard = sys.argv[1], int(sys.argv[2])
rng = np.random.default_rng(shard)
a, b = shard_range(shard, {SHARD_MODELS})
write_shard(path, shard, rng.uniform(-400, 400, (b - a, {N_TRI}, 3)), rng.uniform(-400, 400, (b - a, {N_HEX}, 3)))
"""


def _expected(shard):
    rng = np.random.default_rng(shard)
    a, b = S.shard_range(shard, SHARD_MODELS)
    return rng.uniform(-400, 400, (b - a, N_TRI, 3)), rng.uniform(-400, 400, (b - a, N_HEX, 3))


def _new_store(path):
    # 2 modes x 3 levels = 9 models -> one shard; 3 modes x 3 levels = 27 -> 3 shards of 9
    S.create_store(path, N_TRI, N_HEX, n_modes=3, levels=(-1, 0, 1), shard_models=SHARD_MODELS)


def _files(path):
    return {str(f.relative_to(path)): f.read_bytes() for f in sorted(Path(path).rglob("*")) if f.is_file()}


def test_shards_written_by_concurrent_processes_do_not_interfere(tmp_path):
    path = tmp_path / "c.zarr"
    _new_store(path)
    procs = [
        subprocess.Popen([sys.executable, "-c", _WRITER, str(path), str(s)], stderr=subprocess.PIPE) for s in (2, 0, 1)
    ]
    for p in procs:
        assert p.wait(timeout=120) == 0, p.stderr.read().decode()
    assert S.check_store(path) == []
    for s in range(3):
        tri, hexp = _expected(s)
        a, b = S.shard_range(s, SHARD_MODELS)
        assert np.abs(S.read_shard(path, s) - tri).max() <= BOUND_MM
        assert np.abs(S.read_shard(path, s, "hex") - hexp).max() <= BOUND_MM
        assert np.array_equal(zarr.open(str(path))["weights"][a:b], S.weights_of(np.arange(a, b), 3, (-1, 0, 1)))


def test_corrupted_missing_and_interrupted_shards_are_detected_and_rebuilt_byte_identically(tmp_path):
    ref, work = tmp_path / "ref.zarr", tmp_path / "work.zarr"
    for path in (ref, work):
        _new_store(path)
        for s in range(3):
            S.write_shard(path, s, *_expected(s))
    assert _files(ref) == _files(work)  # the encoding is deterministic

    # one flipped byte in shard 1's hex data, shard 2's tri file gone
    f = work / "hex/volume_points/c/1/0/0"
    data = bytearray(f.read_bytes())
    data[len(data) // 2] ^= 0x01
    f.write_bytes(bytes(data))
    (work / "tri/points/c/2/0/0").unlink()
    assert S.check_store(work) == [1, 2]

    # shard 0 "killed mid-write": truncated object, zarr's temporary file left behind, no sidecar
    f0 = work / "tri/points/c/0/0/0"
    f0.write_bytes(f0.read_bytes()[:1000])
    (f0.parent / "0.deadbeef.partial").write_bytes(b"half a shard")
    for p in (work / "checksums/shard_00000").iterdir():
        p.unlink()
    (work / "checksums/shard_00000").rmdir()
    assert S.check_store(work) == [0, 1, 2]

    for s in S.check_store(work):
        S.write_shard(work, s, *_expected(s))
    assert S.check_store(work) == []
    assert _files(ref) == _files(work)


def test_a_shard_job_killed_mid_write_leaves_no_sidecar_and_its_rerun_matches_an_uninterrupted_run(tmp_path):
    ref, work = tmp_path / "ref.zarr", tmp_path / "work.zarr"
    for path in (ref, work):
        _new_store(path)
    subprocess.run([sys.executable, "-c", _WRITER, str(ref), "0"], check=True)
    # (1) SIGKILL between the two arrays' objects (fault injection at the worst point: tri in place, hex not)
    env = {**os.environ, S.FAULT_KILL_ENV: "0"}
    proc = subprocess.run([sys.executable, "-c", _WRITER, str(work), "0"], env=env)
    assert proc.returncode == -signal.SIGKILL  # killed, not finished
    assert (work / "tri/points/c/0/0/0").exists() and not (work / "hex/volume_points/c/0/0/0").exists()
    assert list((work / "hex/volume_points/c/0/0").glob("0.*.partial"))  # the killed writer's leftover
    assert not (work / "checksums/shard_00000").exists()
    assert S.check_store(work) == [0, 1, 2]  # shards 1 and 2 were never written in either store
    # (2) the rerun starts from nothing: same bytes as the uninterrupted run, no leftover
    subprocess.run([sys.executable, "-c", _WRITER, str(work), "0"], check=True)
    assert S.check_store(work) == S.check_store(ref) == [1, 2]
    assert _files(ref) == _files(work)


def test_rejected_input_leaves_a_finished_shard_untouched(tmp_path):
    path = tmp_path / "c.zarr"
    _new_store(path)
    S.write_shard(path, 0, *_expected(0))
    before = _files(path)
    tri, hexp = _expected(0)
    with pytest.raises(ValueError, match="non-finite"):
        S.write_shard(path, 0, np.where(tri > 399.9, np.inf, tri), hexp)
    assert _files(path) == before and S.check_store(path) == [1, 2]


def test_object_crc32c_is_the_crc32c_of_the_whole_file(tmp_path):
    # the shard records' checksum: google_crc32c of the whole file is the reference, across read blocks
    rng = np.random.default_rng(3)
    for size in (0, 1, 4096, (8 << 20) + 12345):
        data = rng.bytes(size)
        (tmp_path / "x.bin").write_bytes(data)
        assert S.object_crc32c(tmp_path / "x.bin") == f"{google_crc32c.value(data):08x}", size
