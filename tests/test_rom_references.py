"""The packaged FE-validation references (spinecohort.rom.references)."""

from __future__ import annotations

import pandas as pd
import pytest

from spinecohort.rom import references as R


def test_every_file_parses_with_consistent_units():
    files = R.validation_files()
    assert {"niosi2006.csv", "wilke2017.csv", "liebsch2020.csv", "dreischarf2014.csv"} <= set(files)
    table = R.load_validation_references()
    assert list(table.columns[:7]) == list(R.TIDY_COLUMNS)
    assert set(table["file"]) == set(files)
    # one unit per quantity, the quantity's own
    assert table.groupby("quantity")["unit"].nunique().max() == 1
    assert (table["unit"] == table["quantity"].map(R.QUANTITY_UNITS)).all()
    # pure moments in N.mm (the project's unit): 7.5 N.m, or Liebsch & Wilke's 5 N.m
    assert set(table["moment_nmm"]) <= {7500, 5000}
    assert table["source"].str.len().min() > 10 and table["provenance"].notna().all()


def test_published_numbers_as_read():
    """Spot values against the sources: Niosi 2006 Table 1 (L3-L4 flexion 3.7 +- 1.5 deg without preload,
    1.2 +- 0.5 deg axial rotation under 600 N); Wilke 2017 abstract (T1-T2 flexion/extension 14 deg, T10-T12
    axial rotation 7-8 deg)."""
    wide = R.reference_wide(R.load_validation_references()).set_index(["level", "motion", "preload_n", "source"])
    niosi = "Niosi et al. 2006, Eur Spine J 15:913"
    assert wide.loc[("L3-L4", "flexion", 0, niosi), ["mean", "sd"]].tolist() == [3.7, 1.5]
    assert wide.loc[("L3-L4", "axial_rotation", 600, niosi), ["mean", "sd"]].tolist() == [1.2, 0.5]
    wilke = "Wilke et al. 2017, PLoS ONE 12:e0177823"
    assert wide.loc[("T1-T2", "flexion_extension", 0, wilke), "mean"] == 14
    assert wide.loc[("T11-T12", "axial_rotation", 0, wilke), ["low", "high"]].tolist() == [7, 8]


@pytest.mark.parametrize(
    "change, message",
    [
        ({"unit": "rad"}, "expected 'deg'"),
        ({"quantity": "torque"}, "unknown quantity"),
        ({"statistic": "mode"}, "unknown statistic"),
        ({"value": "n/a"}, "non-finite"),
    ],
)
def test_bad_rows_are_named(change, message):
    row = {"level": "L3-L4", "motion": "flexion", "quantity": "rom", "statistic": "mean", "value": 3.7}
    table = pd.DataFrame([row | {"unit": "deg", "source": "x"} | change])
    with pytest.raises(ValueError, match=message):
        R.check_references(table)


def test_low_above_high_is_an_error():
    base = {"level": "T2-T3", "motion": "axial_rotation", "quantity": "rom_full", "unit": "deg", "source": "x"}
    table = pd.DataFrame([base | {"statistic": "low", "value": 12.0}, base | {"statistic": "high", "value": 10.0}])
    with pytest.raises(ValueError, match="low > high"):
        R.check_references(table)
