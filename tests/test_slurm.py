"""The pipeline through a real SLURM: the test DAG submitted with `snakemake --profile profiles/slurm`.

Targets the first three stages (cohort, SSM, patient measurement: 8 jobs); the hexahedral stage's
morphing alone takes minutes on 2 cores and would add nothing about SLURM that these do not show.

A one-node SLURM (munge + slurmctld + slurmd, scripts/slurm_local.sh) is started in a scratch dir
for this module and stopped by PID afterwards, whatever happens. The test configuration runs once
through SLURM and once locally with profiles/local, side by side (the SLURM run mostly waits on
status checks); the outputs must be identical, and every job must be in SLURM's own records.
Skipped only when not root (apt and the daemons need it) or when apt cannot install slurm-wlm/munge.
"""

import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "scripts" / "slurm_local.sh"
PROFILE_SLURM = ROOT / "profiles" / "slurm"
PROFILE_LOCAL = ROOT / "profiles" / "local"
SNAKEMAKE = [sys.executable, "-m", "snakemake", "-s", str(ROOT / "Snakefile")]
# the first three stages of the test DAG, reached through the rules at their ends
CORE_RULES = {
    "synthetic_cohort",
    "validate_cohort",
    "gpa",
    "pca",
    "ssm_quality",
    "mode_variation_figure",
    "measure_patients",
}
TARGETS = ["ssm_quality", "mode_variation_figure", "measure_patients"]
DAEMONS = ("slurmd", "slurmctld", "munged")
TIMEOUT_S = 600  # a hung snakemake (e.g. the sacct status trap) fails the test instead of blocking CI

# "Job 3 has been submitted with SLURM jobid 6 (log: /w/.snakemake/slurm_logs/rule_pca/6.log)."
SUBMITTED = re.compile(r"SLURM jobid (\d+) \(log: \S*?/rule_([A-Za-z0-9_]+)/")


def _env(**extra):
    # jobs inherit the submitting environment: the venv's bin must be first on PATH
    path = f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}"
    return {**os.environ, "PATH": path, **extra}


def _pid_alive(pid):
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True


@pytest.fixture(scope="module")
def slurm(tmp_path_factory):
    if os.geteuid() != 0:
        pytest.skip("needs root: installs slurm-wlm/munge with apt and starts munged, slurmctld, slurmd")
    if shutil.which("slurmctld") is None and shutil.which("apt-get") is None:
        pytest.skip("slurm-wlm is not installed and apt-get is unavailable")
    t0 = time.monotonic()
    install = subprocess.run([str(SCRIPT), "install"], capture_output=True, text=True, timeout=TIMEOUT_S)
    if install.returncode != 0:
        pytest.skip(f"apt could not install slurm-wlm/munge: {install.stderr[-500:]}")
    install_s = time.monotonic() - t0
    scratch = tmp_path_factory.mktemp("slurm")
    env = _env(SLURM_LOCAL_DIR=str(scratch))
    pids = {}
    try:
        t1 = time.monotonic()
        start = subprocess.run([str(SCRIPT), "start"], env=env, capture_output=True, text=True, timeout=120)
        start_s = time.monotonic() - t1
        pids = {d: int((scratch / f"{d}.pid").read_text()) for d in DAEMONS if (scratch / f"{d}.pid").exists()}
        assert start.returncode == 0, start.stderr[-3000:]
        yield SimpleNamespace(scratch=scratch, env=env, install_s=install_s, start_s=start_s)
    finally:
        # the script ends exactly the PIDs it recorded; anything that survives is killed here by PID
        pids.update({d: int((scratch / f"{d}.pid").read_text()) for d in DAEMONS if (scratch / f"{d}.pid").exists()})
        subprocess.run([str(SCRIPT), "stop"], env=env, capture_output=True, timeout=120)
        for pid in pids.values():
            if _pid_alive(pid):
                os.kill(pid, signal.SIGKILL)


def _profile_default_resources():
    profile = yaml.safe_load((PROFILE_SLURM / "config.yaml").read_text())
    return [f"{k}={v}" for k, v in profile["default-resources"].items()]


def _workdir(tmp_path_factory, name):
    work = tmp_path_factory.mktemp(name)
    shutil.copytree(ROOT / ".test" / "config", work / "config")
    return work


@pytest.fixture(scope="module")
def runs(slurm, tmp_path_factory):
    local, remote = _workdir(tmp_path_factory, "local"), _workdir(tmp_path_factory, "slurm_run")
    t0 = time.monotonic()
    with open(local / "snakemake.out", "w") as local_out:
        # own session: on failure the whole local run (snakemake and its script children) is killed;
        # niced, so the SLURM jobs (on the critical path) get the 2 cores first
        local_proc = subprocess.Popen(
            ["nice", "-n", "15", *SNAKEMAKE, "--profile", str(PROFILE_LOCAL), "--directory", str(local), *TARGETS],
            env=slurm.env,
            stdout=local_out,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
        try:
            # the test cluster's overrides: its partition, squeue status (no accounting), quick first check
            proc = subprocess.run(
                [
                    *SNAKEMAKE,
                    "--profile",
                    str(PROFILE_SLURM),
                    "--directory",
                    str(remote),
                    "--default-resources",
                    *_profile_default_resources(),
                    "slurm_partition=debug",
                    "--slurm-status-command",
                    "squeue",
                    "--slurm-init-seconds-before-status-checks",
                    "1",
                    *TARGETS,
                ],
                env=slurm.env,
                capture_output=True,
                text=True,
                timeout=TIMEOUT_S,
            )
            slurm_s = time.monotonic() - t0
            local_rc = local_proc.wait(timeout=TIMEOUT_S)
        finally:
            if local_proc.poll() is None:
                os.killpg(local_proc.pid, signal.SIGKILL)
    log = proc.stdout + proc.stderr
    (remote / "snakemake.out").write_text(log)
    assert proc.returncode == 0, log[-4000:]
    assert local_rc == 0, (local / "snakemake.out").read_text()[-4000:]
    print(
        f"\nSLURM: apt check/install {slurm.install_s:.1f} s, start {slurm.start_s:.1f} s, "
        f"pipeline through sbatch {slurm_s:.1f} s"
    )
    return SimpleNamespace(local=local, remote=remote, log=log, slurm=slurm)


def _scontrol(jobid, env):
    out = subprocess.run(
        ["scontrol", "show", "job", str(jobid)], env=env, capture_output=True, text=True, timeout=30, check=True
    ).stdout
    return dict(re.findall(r"(\w+)=(\S*)", out))


def test_every_job_went_through_sbatch_and_slurm_ran_it(runs):
    submitted = {int(j): rule for j, rule in SUBMITTED.findall(runs.log)}
    finished = re.findall(r"Finished jobid: \d+ \(Rule: (\w+)\)", runs.log)
    # every job ran as its own SLURM job: the 8 rules of the first three stages, once each
    assert sorted(submitted.values()) == sorted(finished) == sorted(CORE_RULES)
    ctld_log = (runs.slurm.scratch / "log" / "slurmctld.log").read_text()
    for jobid, rule in submitted.items():
        job = _scontrol(jobid, runs.slurm.env)  # MinJobAge=3600 keeps finished jobs in slurmctld
        assert job["JobState"] == "COMPLETED" and job["ExitCode"] == "0:0", (rule, job)
        assert job["Comment"] == f"rule_{rule}" and job["Partition"] == "debug", (rule, job)
        assert Path(job["WorkDir"]) == runs.remote
        assert f"_slurm_rpc_submit_batch_job: JobId={jobid} " in ctld_log
    # the profile's per-rule resources reached sbatch: fixed ones are exact (attempt 1)
    by_rule = {rule: _scontrol(j, runs.slurm.env) for j, rule in submitted.items()}
    assert "mem=2000M" in by_rule["synthetic_cohort"]["TRES"] and by_rule["synthetic_cohort"]["TimeLimit"] == "00:15:00"
    # measure_patients: 1000 + 4 x its input (~4.3 MiB) MB, 10 min
    assert "mem=101" in by_rule["measure_patients"]["TRES"] and by_rule["measure_patients"]["TimeLimit"] == "00:10:00"
    # input-scaled: gpa asks 1000 + 8 x its input (cohort.npz, ~4.3 MiB on the test config) MB;
    # Snakemake's input.size_mb counts MiB
    size_mb = (runs.remote / "results" / "cohort" / "cohort.npz").stat().st_size / 2**20
    assert f"mem={int(1000 + 8 * size_mb)}M" in by_rule["gpa"]["TRES"]


def test_slurm_outputs_equal_the_local_run(runs):
    lr, sr = runs.local / "results", runs.remote / "results"
    stls = sorted(p.name for p in (lr / "synthetic_cohort").glob("*.stl"))
    assert len(stls) == 8  # n_patients of the test config
    for rel in (
        "synthetic_cohort/patients.csv",
        "synthetic_cohort/landmarks.json",
        "ssm/compactness.csv",
        "ssm/quality.csv",
        "patients/parameters.csv",
        "patients/sheet_vs_measured.csv",
    ):
        assert (sr / rel).read_bytes() == (lr / rel).read_bytes(), rel
    # binary STL: numpy-stl writes the write time into the 80-byte header; count and facets must match
    for name in stls:
        local_stl, slurm_stl = (
            (lr / "synthetic_cohort" / name).read_bytes(),
            (sr / "synthetic_cohort" / name).read_bytes(),
        )
        assert len(slurm_stl) == len(local_stl) > 84 and slurm_stl[80:] == local_stl[80:], name
    # .npz members carry zip timestamps: compare the arrays, which must be bit-identical
    for rel in ("cohort/cohort.npz", "ssm/aligned.npz", "ssm/ssm.npz"):
        with np.load(lr / rel) as a, np.load(sr / rel) as b:
            assert sorted(a.files) == sorted(b.files), rel
            for key in a.files:
                np.testing.assert_array_equal(a[key], b[key], err_msg=f"{rel}:{key}")


def test_profile_sets_resources_for_every_rule_it_runs(runs):
    # a new rule without an entry would run with the 2000 MB / 30 min defaults: make that a decision
    profile = yaml.safe_load((PROFILE_SLURM / "config.yaml").read_text())
    submitted = set(rule for _, rule in SUBMITTED.findall(runs.log))
    assert submitted <= set(profile["set-resources"]), submitted - set(profile["set-resources"])
    listed = subprocess.run(
        [*SNAKEMAKE, "--directory", str(runs.local), "--list-rules"],
        env=runs.slurm.env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    rules = set(listed.stdout.split())
    assert set(profile["set-resources"]) <= rules, set(profile["set-resources"]) - rules  # no stale names
