import subprocess
import sys

from spinecohort.cli import main


def test_generate_check_and_info(tmp_path, capsys):
    out = tmp_path / "cohort"
    assert main(["generate-cohort", str(out), "--n", "3", "--resolution", "coarse", "--quiet"]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["P01.stl", "P02.stl", "P03.stl", "landmarks.json", "patients.csv"]
    assert main(["check-cohort", str(out)]) == 0
    assert "3 patients, 16716 vertices" in capsys.readouterr().out


def test_input_errors_are_one_line_messages(tmp_path):
    (tmp_path / "a.stl").write_bytes(b"")
    proc = subprocess.run(
        [sys.executable, "-m", "spinecohort.cli", "check-cohort", str(tmp_path)], capture_output=True, text=True
    )
    assert proc.returncode == 2
    assert "error:" in proc.stderr and "Traceback" not in proc.stderr


def test_a_results_file_not_made_yet_is_named_in_one_line(tmp_path, capsys):
    # export from a results folder the pipeline has not filled: the missing file, not a traceback
    args = ["export", "model_00013", "--config", ".test/config/config.yaml", "--results", str(tmp_path / "none")]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert err.startswith("spinecohort: error: ") and str(tmp_path / "none") in err and "snakemake -j2" in err
    # --guided without --load: it has nothing to guide
    assert main(["export", "model_00013", "--guided", "--results", str(tmp_path / "none")]) == 2
    assert "--load" in capsys.readouterr().err


def test_python_dash_m_spinecohort_is_the_console_script():
    """`python -m spinecohort` and `python -m spinecohort.cli` expose the same subcommands."""
    outs = [
        subprocess.run([sys.executable, "-m", mod, "--help"], capture_output=True, text=True, check=True).stdout
        for mod in ("spinecohort", "spinecohort.cli")
    ]
    assert "check-store" in outs[0] and outs[0].split("\n", 1)[1] == outs[1].split("\n", 1)[1]
