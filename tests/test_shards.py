"""The virtual-cohort shard step, one pass: sample -> check/repair -> Table 3 -> measure -> store, on the small cohort."""

import numpy as np
import pandas as pd
import pytest

from spinecohort.cli import main
from spinecohort.cohort.landmarks import Landmarks
from spinecohort.measure.spinopelvic import measure
from spinecohort.measure.tables import parse_range, query_models, tri_vs_hex_summary, virtual_cohort_table
from spinecohort.mesh.hex_ssm import HexSSM, transfer_fields
from spinecohort.mesh.quality.verdict import scaled_jacobian
from spinecohort.mesh.repair import boundary_nodes
from spinecohort.store.zarr_store import ShardWriter, create_store, error_bound_mm, read_shard
from spinecohort.virtual.shard_job import (
    _param_diff,
    check_and_repair,
    hex_landmarks,
    measure_shard,
    process_shard,
    sample_points,
    shard_models_of,
)

LEVELS = [-1.0, 0.0, 1.0]  # 3 modes x 3 levels = 27 models, shards of 9: shard 1 = IDs 9..17, mean = 13
N_MODES = 3


@pytest.fixture(scope="module")
def hex_ssm(template, ssm, small_cohort):
    # the unmorphed template on the SSM mean is a valid hex mesh: enough for the shard logic
    return transfer_fields(template, template.nodes, ssm, small_cohort.landmarks, N_MODES, "smooth")


@pytest.fixture(scope="module")
def one_pass(tmp_path_factory, ssm, hex_ssm, template, small_cohort):
    """Shard 1 processed in one pass (batches of 6 models = 2 store chunks of 3, the last batch 3)."""
    path = tmp_path_factory.mktemp("store") / "cohort.zarr"
    create_store(
        path,
        ssm.mean.shape[0],
        hex_ssm.mean.shape[0],
        N_MODES,
        LEVELS,
        shard_models=9,
        surface_vertex=template.surface_vertex,
    )
    ids, w = shard_models_of(path, 1)
    lm = small_cohort.landmarks
    writer = ShardWriter(path, 1)
    assert writer.chunk == 3  # the 3 levels of the last mode
    quality, params, diff, timing = process_shard(
        ssm, hex_ssm, template, w, ids, lm, hex_landmarks(template, lm), writer=writer, batch=6
    )
    writer.close()
    # the tables are columns; read them as a user does
    return path, ids, w, pd.DataFrame(quality), pd.DataFrame(params), pd.DataFrame(diff)


@pytest.fixture(scope="module")
def shard1(one_pass):
    return one_pass[:4]


def test_shard_ids_and_weights_come_from_the_store(shard1):
    path, ids, w, _ = shard1
    assert ids.tolist() == list(range(9, 18))
    assert w[4].tolist() == [0.0, 0.0, 0.0]  # model 13 = digits (1, 1, 1) = all weights 0
    assert w[0].tolist() == [0.0, -1.0, -1.0]  # model 9 = digits (1, 0, 0)


def test_stored_models_equal_the_ssm_formula_within_the_error_bound(shard1, ssm, hex_ssm, template):
    path, ids, w, quality = shard1
    bound = error_bound_mm("float32-q10")  # half the 2^-10 mm quantum = 0.00049 mm
    tri = read_shard(path, 1, "tri/points")
    hexp = read_shard(path, 1, "hex")
    assert np.abs(tri - ssm.sample(w)).max() <= bound
    untouched = ~quality["repaired"].to_numpy()
    assert np.abs(hexp[untouched] - hex_ssm.sample(w[untouched])).max() <= bound
    # only the volume nodes are stored again: the surface nodes are the tri vertices, bitwise
    import zarr

    assert zarr.open_group(str(path), mode="r")["hex/volume_points"].shape[1] == template.n_hex_nodes
    assert np.array_equal(hexp[:, template.n_hex_nodes :], tri[:, template.surface_vertex])
    # the batched float32 sampler is the formula too (before any quantization: float32 rounding only)
    t32, h32 = sample_points(ssm, hex_ssm, w, chunk=4)
    assert np.abs(t32 - ssm.sample(w)).max() < 1e-4 and np.abs(h32 - hex_ssm.sample(w)).max() < 1e-4


def test_every_stored_model_has_positive_scaled_jacobians(shard1, template):
    path, _, _, quality = shard1
    hexp = read_shard(path, 1, "hex").astype(float)
    n = template.n_hex_nodes
    sj = np.array([scaled_jacobian(h[:n], template.hexes).min() for h in hexp])
    assert (sj > 0).all() and (quality["invalid_after"] == 0).all()
    # the table's value is the stored model's, up to the 0.001 mm quantum
    assert np.abs(sj - quality["min_sj_after"].to_numpy()).max() < 1e-3
    assert {"min_sj_vertebra", "min_sj_NP", "min_sj_AF", "min_sj_CEP"} <= set(quality.columns)


def test_mean_model_measured_from_the_store_equals_the_ssm_mean(shard1, ssm, template, small_cohort):
    path, ids, w, _ = shard1
    lm = small_cohort.landmarks
    params, diff = map(
        pd.DataFrame,
        measure_shard(
            read_shard(path, 1, "tri/points"), read_shard(path, 1, "hex"), w, ids, lm, hex_landmarks(template, lm)
        ),
    )
    row = params.set_index("model_id").loc["model_00013"]
    truth = measure(ssm.mean, lm).iloc[0]
    for col in ("PI", "PT", "SS", "LL", "LL_L4S1", "GT", "TPA", "Cobb"):
        assert row[col] == pytest.approx(truth[col], abs=1e-3), col  # deg; float32 + 0.001 mm quantum
    # thoracic endplates are small (~10 mm): 0.5 um rounding tilts a plane fit by up to ~1e-3 deg each,
    # and kyphosis adds two of them
    assert row["TK_T4T12"] == pytest.approx(truth["TK_T4T12"], abs=3e-3)
    assert row["GAP_assumed_age"] == truth["GAP_assumed_age"]
    d = diff.set_index("parameter")["max_abs_diff"]
    # femoral heads are surface nodes = SSM vertices in both models: same sphere fit up to the quantum
    assert d["FH_radius_L"] < 1e-3 and d["HA_width"] < 1e-3
    assert len(params) == 9 and list(params.columns[:4]) == ["model_id", "w1", "w2", "w3"]


def test_parameters_of_the_one_pass_equal_those_of_the_stored_coordinates(one_pass, template, small_cohort):
    """The shard job measures the float64 samples; a user measures what the store holds (rounded to 2^-10
    mm): every angle agrees within 1e-3 deg and every length within 1e-3 mm."""
    from spinecohort.measure.spinopelvic import UNITS

    path, ids, w, _, params, diff = one_pass
    lm = small_cohort.landmarks
    again, diff_again = map(
        pd.DataFrame,
        measure_shard(
            read_shard(path, 1, "tri/points"), read_shard(path, 1, "hex"), w, ids, lm, hex_landmarks(template, lm)
        ),
    )
    assert params["model_id"].tolist() == again["model_id"].tolist() == [f"model_{i:05d}" for i in range(9, 18)]
    checked = set()
    for col in params.columns[1 + N_MODES :]:
        if not pd.api.types.is_numeric_dtype(params[col]) or pd.api.types.is_bool_dtype(params[col]):
            assert params[col].tolist() == again[col].tolist(), col
            continue
        a, b = params[col].to_numpy(float), again[col].to_numpy(float)
        assert np.array_equal(np.isnan(a), np.isnan(b)), col
        if np.isnan(a).all():
            continue
        unit = UNITS.get(col, "")
        # degrees and mm: the 1e-3; other units (%, points, ratios): 1e-3 relative
        tol = 1e-3 if unit in ("deg", "mm") else 1e-3 * max(1.0, float(np.nanmax(np.abs(a))))
        assert np.nanmax(np.abs(a - b)) <= tol, (col, unit, np.nanmax(np.abs(a - b)))
        checked.add(unit)
    assert {"deg", "mm"} <= checked
    assert diff["parameter"].tolist() == diff_again["parameter"].tolist()


def test_hex_landmarks_name_the_same_places_as_the_tri_landmarks(template, small_cohort):
    lm = small_cohort.landmarks
    hl = hex_landmarks(template, lm)
    hl.validate(template.n_nodes, "hex landmarks")
    for side in ("L", "R"):  # surface nodes carry the mean's vertices exactly
        assert np.array_equal(
            template.nodes[hl.femoral_head[side]],
            template.nodes[template.n_hex_nodes :][np.searchsorted(template.surface_vertex, lm.femoral_head[side])],
        )
    n2 = len(template.grid.nodes)  # an endplate is a whole O-grid layer, its rim the outer ring
    assert len(hl.endplate_sup["L4"]) == n2 and len(hl.rim_sup["L4"]) == len(template.grid.outer)
    assert set(hl.rim_inf["T7"]) <= set(hl.endplate_inf["T7"])
    bad = Landmarks(**{**lm.__dict__, "pubic_symphysis": lm.body["L3"][:3]})  # body vertices: no surface node
    with pytest.raises(ValueError, match="pubic_symphysis are not surface nodes"):
        hex_landmarks(template, bad)


def test_deliberately_inverted_elements_are_untangled(template, hex_ssm):
    n = template.n_hex_nodes
    interior = np.setdiff1d(np.arange(n), boundary_nodes(template.hexes))
    node = interior[len(interior) // 2]
    # mode 1 drags one interior node 1.5 edge lengths sideways: its elements fold at w1 = +1
    nb = np.unique(template.hexes[np.any(template.hexes == node, axis=1)])
    edge = np.median(np.linalg.norm(hex_ssm.mean[nb] - hex_ssm.mean[node], axis=1))
    fields = hex_ssm.fields.copy()
    fields[0, node] += [1.5 * edge, 0.0, 0.0]
    bent = HexSSM(hex_ssm.mean, fields, hex_ssm.eigenvalues, "test")
    w = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    pts = bent.sample(w).astype(np.float32)
    raw = pd.DataFrame(check_and_repair(pts.copy(), template, bent, w, np.array([5, 6]), repair=False))
    assert raw.loc[0, "invalid_before"] > 0 and raw.loc[0, "invalid_after"] == raw.loc[0, "invalid_before"]
    # the same decision as the plain scaled Jacobian of those coordinates
    assert raw["invalid_before"].tolist() == [int((scaled_jacobian(p[:n], template.hexes) <= 0).sum()) for p in pts]
    q = pd.DataFrame(check_and_repair(pts, template, bent, w, np.array([5, 6])))
    assert q.loc[0, "invalid_before"] > 0 and q.loc[0, "invalid_after"] == 0 and q.loc[0, "repaired"]
    assert q.loc[0, "nodes_moved"] >= 1 and scaled_jacobian(pts[0, :n].astype(float), template.hexes).min() > 0
    # the valid model is untouched
    assert q.loc[1, "invalid_before"] == 0 and q.loc[1, "nodes_moved"] == 0 and not q.loc[1, "repaired"]
    assert np.array_equal(pts[1], bent.sample(w[1]).astype(np.float32))


def test_bad_weights_are_rejected(ssm, hex_ssm):
    with pytest.raises(ValueError, match="weights have 9 modes but the SSM has only"):
        sample_points(ssm, hex_ssm, np.zeros((2, 9)))
    with pytest.raises(ValueError, match="non-finite"):
        sample_points(ssm, hex_ssm, np.full((1, 3), np.nan))


def test_tri_vs_hex_summary_pools_shards_of_unequal_size_by_their_models():
    """The cohort's mean |tri - hex| is the mean over every model, whatever the shards' sizes (the default cut
    is 8,407 + 8,400): shards of 5 and 2 models pooled give the mean of the 7 values, not of the two means."""
    rng = np.random.default_rng(3)
    tri = {"PI": rng.normal(50, 10, 7), "GAP": np.full(7, np.nan), "TK": rng.normal(40, 5, 7)}
    hexp = {k: v + rng.normal(0, 1e-3, 7) for k, v in tri.items()}
    hexp["TK"][[1, 5]] = np.nan  # a parameter a hex model could not measure: out of the mean and the count
    cut = [slice(0, 5), slice(5, 7)]
    shards = [pd.DataFrame(_param_diff({k: v[s] for k, v in tri.items()}, {k: v[s] for k, v in hexp.items()}))
              for s in cut]  # fmt: skip
    assert list(shards[0]["n_models"]) == [5, 0, 4] and list(shards[1]["n_models"]) == [2, 0, 1]
    out = tri_vs_hex_summary(shards).set_index("parameter")
    d = {k: np.abs(tri[k] - hexp[k]) for k in tri}
    assert out.loc["PI", "mean_abs_diff"] == pytest.approx(d["PI"].mean(), rel=1e-12)
    assert out.loc["TK", "mean_abs_diff"] == pytest.approx(np.nanmean(d["TK"]), rel=1e-12)
    assert out.loc["PI", "max_abs_diff"] == d["PI"].max() and np.isnan(out.loc["GAP", "mean_abs_diff"])
    # the unweighted mean of the two shard means is measurably different here (the test can fail)
    assert abs(shards[0]["mean_abs_diff"][0] / 2 + shards[1]["mean_abs_diff"][0] / 2 - d["PI"].mean()) > 1e-6


def test_parse_range_and_query():
    assert parse_range("50:60") == (50.0, 60.0) and parse_range("25:") == (25.0, None)
    assert parse_range(":-5") == (None, -5.0)
    for bad in ("50", ":", "a:b", "60:50"):
        with pytest.raises(ValueError):
            parse_range(bad, "PI")
    t = pd.DataFrame(
        {
            "model_id": ["model_00000", "model_00001", "model_00002"],
            "PI": [49.9, 50.0, 61.0],
            "PT": [30.0, 24.9, np.nan],
        }
    )
    assert query_models(t, {"PI": (50.0, 60.0)}) == ["model_00001"]  # inclusive bounds
    assert query_models(t, {"PT": (25.0, None)}) == ["model_00000"]  # NaN never matches
    with pytest.raises(ValueError, match="no numeric column 'XX'"):
        query_models(t, {"XX": (0.0, None)})


def test_virtual_table_joins_quality_and_cli_query_prints_ids(tmp_path, capsys):
    params = [
        pd.DataFrame({"model_id": ["model_00001", "model_00000"], "w1": [0.0, -1.0], "PI": [55.0, 52.0]}),
        pd.DataFrame({"model_id": ["model_00002"], "w1": [1.0], "PI": [58.0]}),
    ]
    quality = [
        pd.DataFrame(
            {
                "model_id": [0, 1, 2],
                "min_sj_before": [0.3, -0.1, 0.4],
                "min_sj_after": [0.3, 0.2, 0.4],
                "invalid_before": [0, 3, 0],
                "invalid_after": [0, 0, 0],
                "nodes_moved": [0, 12, 0],
                "max_displacement_mm": [0.0, 1.5, 0.0],
                "repaired": [False, True, False],
            }
        )
    ]
    v = virtual_cohort_table(params, quality)
    assert v["model_id"].tolist() == ["model_00000", "model_00001", "model_00002"]
    assert v.loc[1, "invalid_before"] == 3 and v.loc[1, "nodes_moved"] == 12
    with pytest.raises(ValueError, match="duplicate model IDs"):
        virtual_cohort_table(params + params[1:], quality)
    v.to_csv(tmp_path / "virtual_cohort.csv", index=False)
    assert main(["query", "--PI", "53:", "--w1", ":0.5", "--results", str(tmp_path)]) == 0
    assert capsys.readouterr().out.split() == ["model_00001"]
    assert main(["query", "--PI", "oops", "--results", str(tmp_path)]) == 2


def test_one_pass_check_decisions_equal_the_formula_kernel(shard1, template, hex_ssm):
    """The one-pass check (``model_quality`` on the float64 batch) decides as the former check, the fused
    morph kernel on the SSM formula: the same inverted-hex counts and the same minimum scaled Jacobians
    (up to the round-off of BLAS against numba summing the modes)."""
    from spinecohort.mesh.quality.kernels import morph_scaled_jacobian_nb

    path, ids, w, quality = shard1
    n = template.n_hex_nodes
    mean, fields = np.ascontiguousarray(hex_ssm.mean[:n]), np.ascontiguousarray(hex_ssm.fields[:N_MODES, :n])
    sj = morph_scaled_jacobian_nb(mean, fields, np.ascontiguousarray(w), np.ascontiguousarray(template.hexes))
    assert quality["invalid_before"].tolist() == (sj <= 0).sum(axis=1).tolist()
    assert np.abs(quality["min_sj_before"].to_numpy() - sj.min(axis=1)).max() < 1e-12
    tissue = template.part_of_hex()
    for t in np.unique(tissue):
        assert np.abs(quality[f"min_sj_{t}"].to_numpy() - sj[:, tissue == t].min(axis=1)).max() < 1e-12


def test_per_model_table3_matches_the_pooled_summary_of_each_model(shard1, template, ssm, hex_ssm):
    """The quality table's Table 3 columns of a model equal ``table3_summary`` of that model alone (the
    pooled-metrics implementation used for the template's own Table 3)."""
    from spinecohort.mesh.quality.table3 import hex_quality_metrics, table3_summary

    path, ids, w, quality = shard1
    tissue = template.part_of_hex()
    # the rows come from the float64 formula (this hex SSM has no contact map, and no model needed repair)
    assert hex_ssm.contact is None and not quality["repaired"].any()
    for k in (0, 4):
        pts = hex_ssm.sample(w[k])
        ref = table3_summary(hex_quality_metrics(pts, template.hexes, certify=False), tissue).set_index("part")
        for part in ("vertebra", "AF", "NP", "CEP"):
            for col in ("pct_errors", "pct_warnings", "pct_edge_ratio_gt_10", "pct_max_face_angle_gt_160"):
                assert quality.loc[k, f"{col}_{part}"] == pytest.approx(ref.loc[part, col], abs=1e-9), (col, part)
            for col in ("nodal_jacobian_ratio_min", "gauss_jacobian_ratio_min"):
                assert quality.loc[k, f"{col}_{part}"] == pytest.approx(ref.loc[part, col], rel=1e-9), (col, part)


def test_the_shard_job_does_not_import_what_it_never_calls():
    """Start-up paid by every shard job: untangling (scipy.optimize, scipy.sparse, pyvista), template building
    (scipy.optimize, scipy.spatial.transform) and the hex-SSM transfer (scipy.spatial) import their modules
    where they are used; measured ~0.8 s of the job's 1.9-2.3 s of imports."""
    import subprocess
    import sys

    heavy = ("pyvista", "vtk", "scipy.optimize", "scipy.sparse", "scipy.spatial")
    code = (
        f"import sys; import spinecohort.virtual.shard_job; print(' '.join(m for m in {heavy!r} if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.split() == []


def test_concat_columns_joins_batches_in_order_and_refuses_other_columns():
    """A shard's table is its batches' columns one after the other, in the first batch's column order."""
    from spinecohort.store.columns import concat_columns

    columns = {"model_id": np.array([3, 4, 5]), "angle": np.array([1.5, np.nan, -np.inf])}
    halves = concat_columns([{k: v[:1] for k, v in columns.items()}, {k: v[1:] for k, v in columns.items()}])
    assert list(halves) == ["model_id", "angle"]
    assert np.array_equal(halves["model_id"], [3, 4, 5]) and np.array_equal(
        halves["angle"], columns["angle"], equal_nan=True
    )
    assert concat_columns([]) == {}
    with pytest.raises(ValueError, match=r"part 1 has columns \['angle', 'model_id'\]"):
        concat_columns([columns, {"angle": np.zeros(1), "model_id": np.zeros(1)}])
