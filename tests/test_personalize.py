"""Personalized models (spinecohort/personalize/): fits to parameters, projections, FE decks, CLI."""

from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml

from spinecohort.fe.inp_template import read_inp_nodes
from spinecohort.layout import Layout
from spinecohort.mesh.quality.verdict import scaled_jacobian
from spinecohort.mesh.template import HexTemplate
from spinecohort.personalize.cohort import shape_distances
from spinecohort.personalize.fit import PersonalizationModel, project_shapes
from spinecohort.personalize.parameters import (
    CORE_PARAMETERS,
    ParameterFunction,
    complete_pelvic_targets,
    landmark_vertices,
    pose,
)
from spinecohort.ssm.procrustes import procrustes_align

SHAPE_PARAMS = ["PI", "PT", "SS", "LL", "LL_L4S1", "TK_T4T12", "TK_T1T12"]


@pytest.fixture(scope="module")
def fn(ssm, small_cohort):
    return ParameterFunction.from_ssm(ssm, small_cohort.landmarks, 3)


def test_landmark_subset_measures_like_the_whole_mesh(ssm, small_cohort, fn):
    # the restriction only drops vertices measure() never reads: identical parameters (float round-off)
    from spinecohort.measure.spinopelvic import measure

    w = np.array([[1.0, -2.0, 0.5], [0.0, 0.0, 0.0]])
    full = measure(ssm.sample(w), small_cohort.landmarks)[SHAPE_PARAMS].to_numpy()
    assert np.abs(fn(w, SHAPE_PARAMS) - full).max() < 1e-9
    assert len(landmark_vertices(small_cohort.landmarks)) < ssm.mean.shape[0] / 2


def test_pelvic_identity_of_targets():
    assert complete_pelvic_targets({"PI": 55, "PT": 28})["SS"] == 27  # derived: PI = PT + SS exactly
    assert complete_pelvic_targets({"SS": 30, "PT": 20, "LL": 40})["PI"] == 50
    with pytest.raises(ValueError, match=r"PI \(50\) must equal PT \+ SS"):
        complete_pelvic_targets({"PI": 50, "PT": 25, "SS": 30})  # 5 deg apart: no model can reach it
    with pytest.raises(ValueError, match="'XX' is not a parameter"):
        complete_pelvic_targets({"XX": 1.0})


def test_posture_shifts_pt_and_ss_only(fn):
    # a sagittal turn about the frame's x axis moves PT and SS by -/+ the angle (x is the mean's left-right
    # axis to within the GPA's residual: 0.05 deg), PI and LL are shape
    f = ParameterFunction(fn.mean, fn.fields, fn.landmarks, posture=True)
    y = f(np.array([[0.5, 0.5, 0.5, 0.0], [0.5, 0.5, 0.5, 10.0]]), ["PI", "PT", "SS", "LL"])
    assert y[1] - y[0] == pytest.approx([0.0, -10.0, 10.0, 0.0], abs=0.05)
    assert np.allclose(np.linalg.norm(pose(fn.mean[None], [25.0])[0], axis=1), np.linalg.norm(fn.mean, axis=1))


def test_fit_recovers_weights_of_an_ssm_model(fn):
    # a model drawn from the SSM itself: seven parameters fix its three weights (no prior), so the fit must
    # return its weights (bound 0.02 SD) and its parameters (bound 0.01 deg, the refinement's tolerance is
    # 1e-8 in the variables); the quadratic surrogate alone is only good to ~0.3 deg
    model = PersonalizationModel(fn, SHAPE_PARAMS, prior=0.0, surrogate_samples=256)
    for w_true in ([1.2, -0.8, 0.5], [-2.0, 1.5, -1.0]):
        truth = fn.table(np.array([w_true])).iloc[0]
        res = model.fit({p: truth[p] for p in SHAPE_PARAMS})
        assert np.abs(res.weights - w_true).max() < 0.02, (w_true, res.weights)
        assert max(abs(res.achieved[p] - truth[p]) for p in SHAPE_PARAMS) < 0.01
        assert res.evaluations < 60 * 7  # a few dozen batched evaluations, not a sampling search


def test_fit_with_posture_matches_core_targets(fn):
    # PI, PT, SS, LL are 3 independent numbers; 3 weights + a posture reach them exactly (bound 0.01 deg)
    f = ParameterFunction(fn.mean, fn.fields, fn.landmarks, posture=True)
    model = PersonalizationModel(f, list(CORE_PARAMETERS), prior=0.05, surrogate_samples=256, posture_deg=30)
    truth = f.table(np.array([[0.7, -1.1, 0.4, 6.0]])).iloc[0]
    res = model.fit({"PI": truth.PI, "PT": truth.PT, "LL": truth.LL})  # SS derived from PI - PT
    assert max(abs(res.achieved[p] - truth[p]) for p in CORE_PARAMETERS) < 0.01
    assert np.all(np.abs(res.weights) <= 3.0) and abs(res.posture_deg) <= 30


def test_projection_of_training_shapes_reproduces_pca_scores(ssm, small_cohort):
    aligned = procrustes_align(small_cohort.vertices).aligned
    x = (aligned - aligned.mean(0)).reshape(len(aligned), -1)
    u, s, _ = np.linalg.svd(x, full_matrices=False)
    # PCA scores in SD: U S / sqrt(d) = U sqrt(P - 1) (signs as the SSM chose them)
    scores = u[:, : ssm.n_modes] * np.sqrt(len(aligned) - 1)
    sign = np.sign(np.sum(scores * ssm.project(aligned), axis=0))
    w, raw = project_shapes(ssm, aligned, ssm.n_modes, bound_sd=10.0)
    assert np.abs(raw - scores * sign).max() < 1e-8
    # with every mode the projection is the training shape itself (< 1e-9 mm)
    assert shape_distances(ssm.sample(w), aligned)["dist_placed_max_mm"].max() < 1e-9
    w3, raw3 = project_shapes(ssm, aligned, 3, bound_sd=0.5)
    assert np.abs(w3).max() <= 0.5 and np.array_equal(w3, np.clip(raw3, -0.5, 0.5))


# --------------------------------------------------------------------- the pipeline's outputs (test DAG)


def test_pipeline_personalization_table_and_errors(test_run):
    r = test_run / "results"
    L = Layout(r)
    t = pd.read_csv(L.personalization_csv, dtype={"ID": str})
    assert len(t) == 16 and set(t["method"]) == {"fit", "projection"}  # 8 patients x 2 methods
    assert {"ID", "method", "b1", "b2", "b3", "PI_target", "PI_achieved", "PI_error", "dist_mean_mm"} <= set(t.columns)
    fit, proj = t[t.method == "fit"], t[t.method == "projection"]
    # fit: 3 weights + posture against 3 independent targets -> exact (0.01 deg) wherever no weight sits at
    # +-3 SD; where one does, the 8-patient SSM cannot reach the patient's LL / PI inside the box (< 1 deg)
    err = fit[[f"{p}_error" for p in CORE_PARAMETERS]].abs().max(axis=1)
    assert (err[fit.at_bound == 0] < 0.01).all() and err.max() < 1.0
    assert (fit[["b1", "b2", "b3"]].abs() <= 3.0).all().all()
    # projection: least squares in mode space, so its placed RMS distance is at most the mean shape's
    # (b = 0 lies in the box); its parameters are off by the truncated modes and the GPA posture
    assert proj.dist_mean_mm.mean() < fit.dist_mean_mm.mean()
    assert (proj[[f"{p}_error" for p in CORE_PARAMETERS]].abs().max(axis=1) < 25).all()
    report = Path(L.personalization_report).read_text()
    assert "| PI | deg |" in report and "after repair 0" in report
    patients = pd.read_excel(L.descriptive_list, sheet_name="Patients")
    assert {"pers_fit_b1 [SD]", "pers_fit_PI_error [deg]", "pers_proj_dist_mean [mm]"} <= set(patients.columns)


def test_pipeline_personalized_decks_have_no_inverted_hexes(test_run):
    r = test_run / "results"
    L = Layout(r)
    template = HexTemplate.load(L.template)
    decks = sorted(Path(L.personalized_dir).glob("P*.inp"))
    assert [d.stem for d in decks] == [f"P{i:02d}" for i in range(1, 9)]
    t = pd.read_csv(L.personalization_csv, dtype={"ID": str}).set_index(["ID", "method"])
    for deck in decks[:3]:  # reading a deck back: ~0.3 s each
        _, nodes = read_inp_nodes(deck)
        sj = scaled_jacobian(nodes[: template.n_hex_nodes], template.hexes)
        assert sj.min() > 0, deck  # 0 inverted elements in what a user gets
        assert t.loc[(deck.stem, "fit"), "invalid_after"] == 0


def test_cli_personalize(test_run, tmp_path, capsys):
    from spinecohort.cli import main

    cfg = yaml.safe_load((test_run / "config" / "config.yaml").read_text())
    results = test_run / cfg["results"]
    # targets of a plausible model (the SSM mean's own parameters, shifted a little)
    t = pd.read_csv(Layout(results).personalization_csv).query("method == 'projection'")
    pi, pt, ll = (float(t[f"{p}_achieved"].median()) for p in ("PI", "PT", "LL"))
    out = tmp_path / "model.inp"
    args = [
        "personalize",
        "--PI",
        f"{pi:.2f}",
        "--PT",
        f"{pt:.2f}",
        "--LL",
        f"{ll:.2f}",
        "--config",
        str(test_run / "config" / "config.yaml"),
        "--results",
        str(results),
        "--out",
        str(out),
    ]
    assert main(args) == 0
    text = capsys.readouterr().out
    rows = {line.split()[0]: line.split() for line in text.splitlines() if line.split()[:1] in (["PI"], ["SS"])}
    assert float(rows["SS"][1]) == pytest.approx(pi - pt, abs=0.01)  # derived from PI = PT + SS
    assert abs(float(rows["PI"][3])) < 0.01
    _, nodes = read_inp_nodes(out)
    template = HexTemplate.load(Layout(results).template)
    assert scaled_jacobian(nodes[: template.n_hex_nodes], template.hexes).min() > 0
    assert (
        main(
            [
                "personalize",
                "--PI",
                "50",
                "--PT",
                "25",
                "--SS",
                "30",
                "--results",
                str(results),
                "--config",
                str(test_run / "config" / "config.yaml"),
            ]
        )
        == 2
    )
    assert "must equal PT + SS" in capsys.readouterr().err
