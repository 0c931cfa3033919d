"""`spinecohort rom-table`: the sensitivity and mode-study tables written from the rules' CSV columns; every
number below is read off the small tables built here."""

import pandas as pd

from spinecohort.cli import main
from spinecohort.rom.tables import modes_markdown, sensitivity_markdown


def sensitivity_table() -> pd.DataFrame:
    rows = []
    for seg, mot, rom in (("L3-L4", "flexion", 4.0), ("T10-T11", "axial_rotation", 9.5)):
        rows.append((seg, mot, "baseline", "", 0.0, rom, 0.0, 1.0, 0.0))
        rows.append((seg, mot, "fibre_angle", "lumbar", 25.0, rom + 0.5, 0.5, 1.0, 0.0))
        rows.append((seg, mot, "fibre_angle", "lumbar", 35.0, rom - 0.25, -0.25, 0.8, 1200.0))
    cols = ["segment", "motion", "parameter", "level", "value", "rom_deg", "change_deg"]
    return pd.DataFrame(rows, columns=[*cols, "min_load_fraction", "max_guide_moment_nmm"])


def test_sensitivity_table_rows_are_the_calibrated_rom_then_each_change():
    lines = sensitivity_markdown(sensitivity_table()).splitlines()
    assert lines[0] == "| variant | L3-L4 F | T10-T11 AR | min load | guide (N·mm) |"
    assert lines[2] == "| **calibrated (deg)** | 4.00 | 9.50 | 1.00 | 0 |"
    assert lines[3] == "| fibre_angle lumbar (25) | +0.50 | +0.50 | 1.00 | 0 |"
    assert lines[4] == "| fibre_angle lumbar (35) | -0.25 | -0.25 | 0.80 | 1200 |"
    assert len(lines) == 5


def modes_table() -> pd.DataFrame:
    units = ("T2-T3", "T6-T7", "T10-T11", "L1-L2", "L3-L4", "L4-L5")
    cases = ("flexion", "extension", "lateral_left", "lateral_right", "axial_left", "axial_right")
    rows = []
    for model, mode, w in (("model_08403", 1, 0.0), ("model_00000", 1, -3.0)):
        for k, u in enumerate(units):
            for j, c in enumerate(cases):
                short = model == "model_00000" and u == "L4-L5" and c == "extension"
                rows.append((model, mode, w, u, u, c, 1.0 + k + 0.1 * j, 0.5 if short else 1.0, 0.0))
        rows.append((model, mode, w, "L3-L4", "L4-L5", "flexion", 99.0, 1.0, 0.0))  # a neighbour: not shown
    cols = ["model", "shape_mode", "weight_sd", "unit", "segment", "load_case", "rom_deg"]
    return pd.DataFrame(rows, columns=[*cols, "load_fraction", "guide_moment_nmm"])


def test_modes_table_sums_each_plane_and_marks_a_short_case():
    lines = modes_markdown(modes_table()).splitlines()
    assert lines[2].startswith("| model_08403 | 0 | 0 | 2.1 | 2.5 | 2.9 | 4.1 |")  # T2-T3: 1.0+1.1, 1.2+1.3, ...
    # L4-L5 (k = 5) F/E = 6.0 + 6.1, short of the moment in extension for the -3 SD model
    assert lines[3].startswith("| model_00000 | 1 | −3 |") and lines[3].endswith("| 12.1* | 12.5 | 12.9 |")
    assert len(lines) == 4


def test_the_cli_prints_the_table_and_names_a_missing_file(tmp_path, capsys):
    csv = tmp_path / "sensitivity.csv"
    sensitivity_table().to_csv(csv, index=False)
    assert main(["rom-table", "sensitivity", str(csv)]) == 0
    assert capsys.readouterr().out == sensitivity_markdown(pd.read_csv(csv))
    assert main(["rom-table", "modes", str(tmp_path / "nope.csv")]) == 2
    assert "nope.csv: no such file (make it with: snakemake -j2 results/rom/modes.csv)" in capsys.readouterr().err
