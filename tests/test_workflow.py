"""The Snakemake DAG end to end on the test configuration, and its behaviour on bad input."""

import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml

from spinecohort.layout import Layout

ROOT = Path(__file__).resolve().parents[1]
SNAKEMAKE = [sys.executable, "-m", "snakemake"]


def run(workdir, *args):
    return subprocess.run(
        [*SNAKEMAKE, "-s", str(ROOT / "Snakefile"), "--directory", str(workdir), "-j2", *args],
        capture_output=True,
        text=True,
        timeout=600,
    )


# test_run (the whole DAG on the test config, once per session) lives in conftest.py: tests/test_release.py
# uses its release too.


def test_dag_produces_every_stage_output(test_run):
    r = test_run / "results"
    L = Layout(r)
    assert len(list((r / "synthetic_cohort").glob("P*.stl"))) == 8
    with np.load(L.ssm) as z:
        assert z["eigenvalues"].shape == (7,)  # 8 patients -> 7 modes
        n = int(z["modes_for_threshold"])
    comp = pd.read_csv(L.compactness_csv)
    assert comp["cumulative_variance"].iloc[-1] == pytest.approx(1.0)
    assert comp["cumulative_variance"].iloc[n - 1] >= 0.95 > (comp["cumulative_variance"].iloc[n - 2] if n > 1 else 0)
    q = pd.read_csv(L.ssm_quality_csv)
    assert list(q.columns) == [
        "modes",
        "generalization_mm",
        "generalization_sd_mm",
        "specificity_mm",
        "specificity_sd_mm",
    ]
    for png in ("ssm/compactness.png", "ssm/quality.png", "figures/mode_variation.png"):
        data = (r / png).read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 20_000, png
    # patients measured through the STL round trip recover the generator's truth (float32 storage: 1e-4)
    comp = pd.read_csv(L.sheet_vs_measured).set_index("parameter")
    assert comp.loc[["PI", "PT", "SS", "LL", "TPA", "GT", "Cobb", "DH_L4-L5"], "max_abs_diff"].max() < 1e-4
    sheets = pd.read_excel(L.descriptive_list, sheet_name=None)
    assert list(sheets) == ["Virtual cohort", "Patients", "Notes"] and len(sheets["Patients"]) == 8
    # the virtual cohort: 3 modes x 3 levels = 27 models in 3 shards of 9, each measured and quality-checked
    virtual = sheets["Virtual cohort"]
    assert len(virtual) == 27 and virtual["model_id"].iloc[13] == "model_00013"
    assert {"w1", "w3", "PI [deg]", "GAP_assumed_age [points]", "min_sj_after", "invalid_after"} <= set(virtual.columns)
    assert (virtual.loc[13, ["w1", "w2", "w3"]] == 0).all()
    twin = pd.read_parquet(L.virtual_cohort_parquet)
    assert twin["model_id"].tolist() == virtual["model_id"].tolist() and twin["invalid_after"].dtype.kind == "i"
    # a model keeps inverted hexes only where its repair failed (and the shard's quality table says so)
    assert ((virtual["invalid_after"] > 0) <= (virtual["invalid_before"] > 0)).all()
    assert (virtual.loc[virtual["repaired"], "min_sj_after"] > 0).all()
    from spinecohort.store.zarr_store import check_store

    assert check_store(L.store) == []
    assert {"ID", "age", "PI [deg]", "LDI [%]", "DH_L4-L5 [mm]", "GAP [points]"} <= set(sheets["Patients"].columns)
    morph = pd.read_csv(L.morph_report)
    assert len(morph) == 18 and (morph["distance_final_mean_mm"] < 0.04).all()  # the seed's bound
    transfer = pd.read_csv(L.transfer_report)
    linear = transfer[transfer["disc_contact"] == "none"].set_index("method")
    assert linear.loc["smooth", "inverted_element_fraction"] < linear.loc["nearest", "inverted_element_fraction"] / 10
    # the disc-contact distraction (1 mm) never folds more models than the plain smooth transfer, and whatever
    # folds at the grid's extremes the shard repair untangles: no stored model keeps an inverted hex (the test
    # mean without BCPD layers folds a few of its 27 before repair; the default grid 0 of 16,807, docs/reference/store-format.md)
    contact = transfer[transfer["disc_contact"] != "none"].set_index("method")
    assert contact.loc["smooth", "models_with_inverted"] <= linear.loc["smooth", "models_with_inverted"]
    assert (virtual["invalid_after"] == 0).all()
    deck = Path(L.template_deck).read_text()
    assert "*ELEMENT, TYPE=C3D8, ELSET=HEXES\n" in deck and "*ELEMENT, TYPE=C3D8R, ELSET=HEXES_DISC\n" in deck
    assert "*ELEMENT, TYPE=C3D20R, ELSET=HEXES_NP\n" in deck and "*EQUATION\n" in deck
    assert "*SPRING, ELSET=LIG_PLL_L3L4, NONLINEAR" in deck and "*SPRING, ELSET=CONN_ARCH_L3, NONLINEAR" in deck
    for rule in (
        "synthetic_cohort",
        "validate_cohort",
        "gpa",
        "pca",
        "ssm_quality",
        "mode_variation_figure",
        "measure_patients",
        "descriptive_list",
        "hex_template",
        "morph_template",
        "hex_ssm",
        "template_inp",
        "init_store",
    ):
        assert (test_run / "logs" / f"{rule}.log").exists()
        assert Path(L.benchmark(rule)).exists()


def test_nothing_to_do_on_rerun(test_run):
    proc = run(test_run, "-n")
    assert proc.returncode == 0 and "Nothing to be done" in proc.stdout + proc.stderr


def _planned_jobs(workdir, *targets):
    """Rule -> job count of what Snakemake would run (its own dry-run job stats)."""
    proc = run(workdir, "-n", *targets)
    assert proc.returncode == 0, proc.stderr[-2000:]
    out = proc.stdout + proc.stderr
    if "Nothing to be done" in out:
        return {}
    table = out.split("Job stats:")[1].split("\n\n")[0].splitlines()[3:]
    return {line.split()[0]: int(line.split()[1]) for line in table if line.split() and line.split()[0] != "total"}


def test_one_model_by_target_file_runs_only_that_job(test_run):
    target = "results/models/model_00013.inp"  # the mean model of the 3-mode x 3-level test grid
    assert _planned_jobs(test_run, target) == {"model_files": 1}
    proc = run(test_run, target)
    assert proc.returncode == 0, proc.stderr[-2000:]
    deck = (test_run / target).read_text()
    assert "weights (SD) [0.0, 0.0, 0.0]" in deck
    mean = (test_run / "results" / "template" / "Mean_Model (Template).inp").read_text()
    node_block = lambda text: text.split("*NODE")[1].split("*ELEMENT")[0].splitlines()[1:]  # noqa: E731
    assert node_block(deck) == node_block(mean)  # all weights 0: the mean model's coordinates


def test_config_change_reruns_only_the_rules_that_use_it(test_run):
    # params are rerun triggers: a new hex type changes only the template deck (and nothing upstream)
    assert _planned_jobs(test_run, "--config", "template={'resolution': 'coarse', 'hex_type': 'C3D8I'}") == {
        "template_inp": 1,
        "personalize": 1,
        "release": 1,
        "all": 1,
        # the personalized decks use the hex type; the sheet and the two figures read the personalization table
        "descriptive_list": 1,
        "personalized_gallery_figure": 1,
        "parameter_histograms_figure": 1,
    }


def test_broken_user_stl_fails_with_the_file_named_and_no_output(test_run, tmp_path):
    folder = tmp_path / "mine"
    shutil.copytree(test_run / "results" / "synthetic_cohort", folder)
    (folder / "P05.stl").write_bytes((folder / "P05.stl").read_bytes()[:1000])
    work = tmp_path / "work"
    (work / "config").mkdir(parents=True)
    cfg = yaml.safe_load((ROOT / ".test" / "config" / "config.yaml").read_text())
    cfg["cohort"].update(source="folder", folder=str(folder))
    (work / "config" / "config.yaml").write_text(yaml.safe_dump(cfg))
    proc = run(work)
    assert proc.returncode != 0
    log = (work / "logs" / "validate_cohort.log").read_text()
    assert "P05.stl: binary STL header announces" in log
    assert not (work / "results" / "cohort" / "cohort.npz").exists()


def test_bad_config_is_rejected_before_any_rule(tmp_path):
    work = tmp_path / "work"
    (work / "config").mkdir(parents=True)
    cfg = yaml.safe_load((ROOT / ".test" / "config" / "config.yaml").read_text())
    cfg["ssm"]["variance_threshold"] = 1.5
    (work / "config" / "config.yaml").write_text(yaml.safe_dump(cfg))
    proc = run(work)
    assert proc.returncode != 0
    assert "ssm.variance_threshold: 1.5 is greater than the maximum of 1" in proc.stderr + proc.stdout
    assert not (work / "results").exists()


def test_lint_is_clean():
    proc = subprocess.run(
        [*SNAKEMAKE, "--lint", "-s", str(ROOT / "Snakefile"), "--directory", str(ROOT)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert "Congratulations, your workflow is in a good condition!" in proc.stdout + proc.stderr


def _store_files(store: Path) -> dict[str, bytes]:
    return {str(p.relative_to(store)): p.read_bytes() for p in sorted(store.rglob("*")) if p.is_file()}


@pytest.fixture
def run_copy(test_run, tmp_path):
    """A private copy of the finished test run (outputs, logs and Snakemake's metadata) to damage."""
    work = tmp_path / "copy"
    shutil.copytree(test_run, work, symlinks=True)
    return work


def test_a_corrupted_shard_is_detected_and_only_it_is_rebuilt(run_copy):
    store = run_copy / "results" / "cohort.zarr"
    before = _store_files(store)
    obj = store / "hex" / "volume_points" / "c" / "1" / "0" / "0"
    data = bytearray(obj.read_bytes())
    data[len(data) // 2] ^= 0x01  # one flipped bit, same size: only the checksum (crc32c) can tell
    obj.write_bytes(bytes(data))
    # the rule fails naming the shard and what to do
    proc = run(run_copy, "--forcerun", "check_store", "results/store_check.csv")
    assert proc.returncode != 0
    assert "shard 00001: hex/volume_points/c/1/0/0 is corrupt" in proc.stderr and "check-store" in proc.stderr
    cli = [sys.executable, "-m", "spinecohort.cli", "check-store", str(store)]
    proc = subprocess.run(cli, capture_output=True, text=True)
    assert proc.returncode == 1 and "shard 00001" in proc.stdout
    assert subprocess.run([*cli, "--rebuild"], capture_output=True, text=True).returncode == 0
    assert not (run_copy / "results" / "shards" / "00001.sample.json").exists()
    # exactly that shard's job (and the check) run again, then the store is byte-identical to the original
    assert _planned_jobs(run_copy, "results/store_check.csv") == {"sample_shard": 1, "check_store": 1}
    proc = run(run_copy, "results/store_check.csv")
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert _store_files(store) == before


def test_a_shard_job_killed_mid_write_leaves_no_record_and_the_rerun_is_byte_identical(run_copy):
    import os

    from spinecohort.store.zarr_store import FAULT_KILL_ENV, check_store, invalidate_shard

    store = run_copy / "results" / "cohort.zarr"
    before = _store_files(store)
    invalidate_shard(store, 2)  # a run in progress: shard 2 not written yet, the store check not run yet
    for f in (run_copy / "results" / "shards").glob("00002.*"):
        f.unlink()
    (run_copy / "results" / "store_check.csv").unlink()
    # the job writes tri/points, then is SIGKILLed before hex/volume_points (a node failure mid-write)
    env = {**os.environ, FAULT_KILL_ENV: "2"}
    proc = subprocess.run(
        [
            *SNAKEMAKE,
            "-s",
            str(ROOT / "Snakefile"),
            "--directory",
            str(run_copy),
            "-j1",
            "results/shards/00002.sample.json",
        ],
        capture_output=True,
        text=True,
        timeout=600,
        env=env,
    )
    assert proc.returncode != 0 and "sample_shard" in proc.stderr
    assert (store / "tri" / "points" / "c" / "2" / "0" / "0").exists()  # killed mid-write, not before it
    assert not (run_copy / "results" / "shards" / "00002.sample.json").exists()  # no sentinel
    assert check_store(store) == [2]
    proc = run(run_copy, "results/store_check.csv")
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert check_store(store) == [] and _store_files(store) == before
