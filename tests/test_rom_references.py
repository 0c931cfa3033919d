"""The packaged FE-validation references (spinecohort.rom.references)."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from spinecohort.rom import references as R


def test_every_file_parses_with_consistent_units():
    files = R.validation_files()
    assert {
        "niosi2006.csv", "wilke2017.csv", "liebsch2020.csv", "dreischarf2014.csv", "wilke1999.csv", "jaumard2011.csv"
    } <= set(files)  # fmt: skip
    table = R.load_validation_references()
    assert list(table.columns[:7]) == list(R.TIDY_COLUMNS)
    assert set(table["file"]) == set(files)
    # one unit per quantity, the quantity's own
    assert table.groupby("quantity")["unit"].nunique().max() == 1
    assert (table["unit"] == table["quantity"].map(R.QUANTITY_UNITS)).all()
    # pure moments in N.mm (the project's unit): 7.5 N.m, Liebsch & Wilke's 5 N.m or Yamamoto's 10 N.m; empty
    # where none applies
    assert set(table["moment_nmm"].dropna()) <= {7500, 5000, 10000}
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


# Rows per packaged source: one per published number (a mean and its SD are two rows).
ROWS_PER_SOURCE = {
    "Niosi et al. 2006, Eur Spine J 15:913": 16,  # Table 1: 4 motions x mean/SD x 2 preloads
    "Liebsch & Wilke 2020, Front Bioeng Biotechnol 8:46": 12,  # 2 segments x 3 planes x 2 conditions
    "Dreischarf et al. 2014, J Biomech 47:1757": 3,  # the abstract's three median differences
    "Wilke et al. 1999, Spine 24:755": 12,  # the abstract's twelve pressures
    "Jaumard et al. 2011, J Biomech Eng 133:071010": 21,  # 9 in-vitro rows x mean/SD + 3 FE values
}


def test_rows_per_source():
    table = R.load_validation_references()
    counts = table.groupby("source").size()
    for source, rows in ROWS_PER_SOURCE.items():
        assert counts[source] == rows, source


def test_every_mean_has_its_sd_and_spreads_are_positive():
    """A published mean +- SD is stored as both numbers; an SD is a spread, so never negative."""
    wide = R.reference_wide(R.load_validation_references())
    with_mean = wide[wide["mean"].notna() & wide["source"].isin(["Niosi et al. 2006, Eur Spine J 15:913",
                                                                 "Jaumard et al. 2011, J Biomech Eng 133:071010"])]  # fmt: skip
    assert with_mean["sd"].notna().all()
    assert (wide["sd"].dropna() > 0).all()


def test_intradiscal_pressure_in_vivo_as_read():
    """Wilke et al. 1999 abstract, L4-L5 of one volunteer: relaxed standing 0.5 MPa, standing flexed forward
    1.1 MPa, lying prone 0.1 MPa; lifting 20 kg with a round back 2.3 MPa, the highest value reported."""
    idp = R.select_references(R.load_validation_references(), quantity="intradiscal_pressure")
    assert set(idp["unit"]) == {"MPa"} and set(idp["level"]) == {"L4-L5"} and (idp["n"] == 1).all()
    by = idp.set_index("motion")["value"]
    assert by["standing_relaxed"] == 0.5 and by["standing_flexed_forward"] == 1.1 and by["lying_prone"] == 0.1
    assert by.idxmax() == "lifting_20kg_round_back" and by.max() == 2.3
    # Nachemson's ordering, which the paper confirms: lying < standing < flexed forward; overnight rehydration
    assert by["lying_prone"] < by["standing_relaxed"] < by["standing_flexed_forward"]
    assert by["lying_night_end"] > by["lying_night_start"]
    assert idp["moment_nmm"].isna().all()  # in vivo: no applied moment


def test_facet_forces_as_read():
    """Jaumard et al. 2011 Table 2, T12-L2 in vitro: extension 51.5 +- 39.0 N; in axial rotation the
    contralateral facet carries more than twice the ipsilateral one (70.3 vs 31.3 N): the facet on the side
    the rotation closes is the one in contact."""
    ff = R.select_references(R.load_validation_references(), quantity="facet_force", level="T12-L2")
    assert set(ff["unit"]) == {"N"}
    wide = R.reference_wide(ff).set_index(["motion", "condition"])
    assert wide.loc[("extension", "in vitro, intact"), ["mean", "sd"]].tolist() == [51.5, 39.0]
    ar = wide.loc["axial_rotation"]
    contra = ar.loc["in vitro, intact, contralateral facet", "mean"]
    ipsi = ar.loc["in vitro, intact, ipsilateral facet", "mean"]
    assert contra > 2 * ipsi
    assert (ff["value"] >= 0).all()  # contact forces push, never pull
    assert ff["provenance"].str.startswith("secondary").all()


def test_medians_inside_ranges_everywhere():
    """Every reference with a median and a range has min <= median <= max (and low <= high)."""
    wide = R.reference_wide(R.load_validation_references())
    for lo, hi in (("min", "median"), ("median", "max"), ("low", "high")):
        if lo in wide and hi in wide:
            both = wide[[lo, hi]].dropna()
            assert (both[lo] <= both[hi]).all()


def test_select_references_names_unknown_columns():
    table = R.load_validation_references()
    assert len(R.select_references(table, source="Niosi et al. 2006, Eur Spine J 15:913", preload_n=600)) == 8
    with pytest.raises(ValueError, match="unknown reference columns"):
        R.select_references(table, specimen="x")


def test_not_obtained_list_is_explicit_and_not_stale():
    """The wanted numbers that could not be obtained are listed with where they were searched and why; none
    of them is also in the data (a group leaves the list when its numbers arrive)."""
    gaps = R.not_obtained()
    table = R.load_validation_references()
    assert R.gaps_also_obtained(table, gaps).empty
    dreischarf = gaps[gaps["source"] == "Dreischarf et al. 2014, J Biomech 47:1757"]
    assert set(dreischarf["quantity"]) == {"rom", "intradiscal_pressure", "facet_force"}
    assert (gaps["source"] == "Remus et al. 2021, PLoS ONE 16:e0250456").sum() == 6
    assert gaps["source"].str.startswith("Heuer et al. 2007").any()
    # the staleness check fires once a group's statistics arrive
    arrived = pd.DataFrame(
        [
            {
                "level": "L4-L5",
                "quantity": "rom",
                "statistic": "per reduction step",
                "source": "Heuer et al. 2007, J Biomech 40:271",
            }
        ]
    )
    assert len(R.gaps_also_obtained(arrived, gaps)) == 1


def test_bad_gap_list_is_named():
    gaps = R.not_obtained().copy()
    gaps.loc[0, "reason"] = " "
    with pytest.raises(ValueError, match="empty reason"):
        R.check_gaps(gaps)
    with pytest.raises(ValueError, match="unknown quantity"):
        R.check_gaps(gaps.assign(quantity="stiffness"))


def test_coverage_counts_both_sides():
    cov = R.reference_coverage(R.load_validation_references(), R.not_obtained()).set_index("source")
    assert cov.loc["Wilke et al. 1999, Spine 24:755"].tolist() == [12, 0]
    assert cov.loc["Remus et al. 2021, PLoS ONE 16:e0250456"].tolist() == [0, 6]
    assert cov.loc["Dreischarf et al. 2014, J Biomech 47:1757"].tolist() == [3, 4]


# ---- accessors the validation tables use ------------------------------------------------------------------

ACCESSORS = (R.lumbar_total_rom, R.intradiscal_pressure, R.facet_forces, R.remus_segmental_rom)


@pytest.mark.parametrize("accessor", ACCESSORS, ids=lambda f: f.__name__)
def test_accessors_return_the_documented_columns(accessor):
    """Every accessor gives the same leading columns (facet forces add ``facet`` after ``condition``), with a float
    value column, whether or not the numbers were obtained."""
    out = accessor()
    expected = list(R.ACCESSOR_COLUMNS)
    if accessor is R.facet_forces:
        expected.insert(expected.index("condition") + 1, "facet")
    assert list(out.columns) == expected
    assert out["value"].dtype == float and out["moment_nmm"].dtype == float


def test_accessors_are_empty_exactly_while_their_gap_is_listed():
    """L1-L5 ROM (Dreischarf 2014) and Remus 2021's segmental ROM are not obtained: the accessors are empty, and
    the gaps list names them. Whoever types the numbers in must also take the gap out, or this fails."""
    gaps = R.not_obtained()
    dreischarf_rom = (gaps["source"] == R.DREISCHARF_SOURCE) & (gaps["quantity"] == "rom")
    remus_rom = (gaps["source"] == R.REMUS_SOURCE) & (gaps["quantity"] == "rom") & gaps["levels"].str.contains("L4-L5")
    assert R.lumbar_total_rom().empty == dreischarf_rom.any()
    assert R.remus_segmental_rom().empty == remus_rom.any()
    # the abstract's median differences are Dreischarf's only numbers here, and they are not a ROM
    assert R.lumbar_total_rom().empty and len(R.select_references(R.load_validation_references(), level="L1-L5")) == 3


def test_intradiscal_pressure_accessor():
    """At L4-L5: Wilke 1999's twelve in-vivo values (0.1 MPa lying prone ... 2.3 MPa lifting 20 kg with a round
    back), none under an applied moment; no level holds in-vitro pressures yet, so L1-L2 is empty."""
    idp = R.intradiscal_pressure("L4-L5")
    assert len(idp) == 12 and set(idp["unit"]) == {"MPa"} and idp["moment_nmm"].isna().all()
    assert idp["value"].min() == 0.1 and idp["value"].max() == 2.3
    assert R.intradiscal_pressure().equals(idp)  # the only level held
    assert R.intradiscal_pressure("L1-L2").empty
    with pytest.raises(ValueError, match="'L4L5' is not of the form"):
        R.intradiscal_pressure("L4L5")


def test_facet_forces_accessor_names_the_facet():
    """Jaumard 2011 Table 2: axial rotation and lateral bending at T12-L2 each give an ipsilateral and a
    contralateral mean +- SD (4 + 4 rows); the other 13 rows do not name a side."""
    ff = R.facet_forces()
    assert len(ff) == 21 and set(ff["facet"]) <= set(R.FACET_SIDES)
    assert ff["facet"].value_counts().to_dict() == {"unspecified": 13, "ipsilateral": 4, "contralateral": 4}
    contra = ff[(ff["motion"] == "axial_rotation") & (ff["facet"] == "contralateral") & (ff["statistic"] == "mean")]
    assert contra["value"].tolist() == [70.3]
    assert len(R.facet_forces("T12-L2")) == 18 and list(R.facet_forces()["level"].unique()) == [
        "T12-L2",
        "L2-L3",
        "L4-L5",
    ]
    sides = R.facet_side(pd.Series(["Contralateral facet", "sum of both facets", "ipsilateral", "in vitro", None]))
    assert sides.tolist() == ["contralateral", "both", "ipsilateral", "unspecified", "unspecified"]


def _rows(source, level, motion, quantity, unit, stats):
    return [
        {
            "level": level,
            "motion": motion,
            "quantity": quantity,
            "statistic": s,
            "value": v,
            "unit": unit,
            "source": source,
        }
        for s, v in stats.items()
    ]


def test_accessors_pick_and_order_typed_in_numbers():
    """With numbers typed in (made-up values, for the selection only): the L1-L5 accessor keeps ROM at the span and
    drops the median differences; the Remus accessor keeps segments L1-L2 ... L5-S1 cranial to caudal and drops the
    L1-L5 total and other sources; both sources' L1-L5 values are span ROM; in-vitro (min, median, max) and model (model_min, model_median, model_max) ranges
    pass the ordering check."""
    table = pd.DataFrame(
        _rows(R.DREISCHARF_SOURCE, "L1-L5", "flexion", "rom", "deg", {"min": 1.0, "median": 2.0, "max": 3.0})
        + _rows(
            R.DREISCHARF_SOURCE, "L1-L5", "flexion", "rom", "deg", {"model_min": 1.5, "model_median": 2, "model_max": 4}
        )
        + _rows(R.DREISCHARF_SOURCE, "L1-L5", "flexion_extension", "rom_median_difference", "deg", {"mean": 2.0})
        + _rows(R.REMUS_SOURCE, "L5-S1", "flexion", "rom", "deg", {"single": 1.0})
        + _rows(R.REMUS_SOURCE, "L1-L2", "flexion", "rom", "deg", {"single": 2.0})
        + _rows(R.REMUS_SOURCE, "L1-L5", "flexion", "rom", "deg", {"single": 3.0})
        + _rows("other", "L2-L3", "flexion", "rom", "deg", {"single": 4.0})
    )
    R.check_references(table)
    total = R.lumbar_total_rom(table)
    assert len(total) == 7 and set(total["quantity"]) == {"rom"}  # Dreischarf's six and Remus's L1-L5 value
    wide = R.reference_wide(total.assign(condition="", moment_nmm=7500, preload_n=0)).set_index("source")
    assert wide.loc[R.DREISCHARF_SOURCE, ["min", "median", "max"]].tolist() == [1.0, 2.0, 3.0]
    assert wide.loc[R.DREISCHARF_SOURCE, ["model_min", "model_median", "model_max"]].tolist() == [1.5, 2.0, 4.0]
    remus = R.remus_segmental_rom(table)
    assert remus["level"].tolist() == ["L1-L2", "L5-S1"] and remus["value"].tolist() == [2.0, 1.0]
    reversed_models = table.assign(value=np.where(table["statistic"] == "model_max", 1.0, table["value"]))
    with pytest.raises(ValueError, match="model_min > model_max|model_median > model_max"):
        R.check_references(reversed_models)


def test_level_order_runs_cranial_to_caudal():
    levels = pd.Series(["L5-S1", "x", "L2-L3", "L1-L5", "T12-L1", "L1-L2", "T1-T2"])
    ordered = levels.iloc[np.argsort(R.level_order(levels), kind="stable")].tolist()
    assert ordered == ["T1-T2", "T12-L1", "L1-L2", "L1-L5", "L2-L3", "L5-S1", "x"]


def test_every_number_is_physically_plausible():
    """Bounds no measurement of an intact adult spine exceeds: one segment rotates < 25 deg to one side under
    7.5 N.m (Wilke 2017's largest full range is 14 deg), a whole span < 60 deg; nucleus pressures stay below
    3 MPa (Wilke 1999's highest, lifting 20 kg with a round back, is 2.3 MPa); facet contact forces are pushes
    below 300 N (Jaumard's largest is 117 N)."""
    table = R.load_validation_references()
    span = table["level"].isin(["L1-L5", "T1-T12"])
    upper = {"rom": 25.0, "rom_full": 30.0, "intradiscal_pressure": 3.0, "facet_force": 300.0}
    per_segment = table[~span]
    assert set(per_segment["quantity"]) <= set(upper)
    assert ((per_segment["value"] >= 0) & (per_segment["value"] < per_segment["quantity"].map(upper))).all()
    spans = table[span]
    assert spans.loc[spans["quantity"].isin(["rom", "rom_full"]), "value"].lt(60).all()
    # Dreischarf's model-vs-in-vitro median differences (2, 1, 5 deg) are a fraction of a span's range
    assert spans.loc[spans["quantity"] == "rom_median_difference", "value"].between(0, 10).all()


def test_yamamoto_per_level_rom_is_the_abstract_s():
    """Yamamoto et al. 1989's abstract: flexion, extension, axial rotation (one side), lateral bending (one side)
    per level at 10 N.m; every number and the moment as it states them."""
    got = R.in_vitro_segmental_rom().pivot(index="level", columns="motion", values="value")
    expected = {
        "L1-L2": (5.8, 4.3, 2.3, 4.9),
        "L2-L3": (6.5, 4.3, 2.6, 7.0),
        "L3-L4": (7.5, 3.7, 2.6, 5.7),
        "L4-L5": (8.9, 5.8, 2.2, 5.7),
        "L5-S1": (10.0, 7.8, 1.4, 5.5),
    }
    for level, values in expected.items():
        row = got.loc[level, ["flexion", "extension", "axial_rotation", "lateral_bending"]]
        assert row.tolist() == list(values), level
    assert set(R.in_vitro_segmental_rom()["moment_nmm"]) == {10000.0}
