"""The mesh-convergence study's table logic on a hand-made table, and the coarser preset it adds below the
default resolution."""

from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml

from spinecohort.mesh.morph import MorphParameters
from spinecohort.mesh.template import TEMPLATE_RESOLUTIONS
from spinecohort.rom.convergence import (
    ConvergenceStudy,
    convergence_markdown,
    convergence_table,
    resolution_summary,
    verdict,
)

RES = ["coarser", "coarse", "medium"]


def _rom(rows):
    """rows: (resolution, load_case, rom_deg); one unit, solve time 10 s, 200 MB per case."""
    t = pd.DataFrame(rows, columns=["resolution", "load_case", "rom_deg"])
    sizes = {"coarser": 1000, "coarse": 2000, "medium": 5000}
    return t.assign(
        unit="T6-T7",
        segment="T6-T7",
        solve_s=10.0,
        peak_rss_mb=t["resolution"].map({"coarser": 100.0, "coarse": 200.0, "medium": 400.0}),
        model_hexes=t["resolution"].map(sizes) * 10,
        model_inverted=0,
        unit_nodes=t["resolution"].map(sizes) * 2,
        unit_elements=t["resolution"].map(sizes),
    )


def test_changes_and_verdicts_on_a_hand_made_table():
    # flexion 4.0 -> 5.0 -> 5.2 deg: coarse vs medium (5.0 - 5.2) / 5.2 = -3.85 % passes 5 %; coarser vs coarse
    # (4 - 5) / 5 = -20 % is reported but not judged.  Extension 3.0 -> 3.3: -9.09 % fails.
    rows = [
        ("medium", "flexion", 5.2),  # out of order on purpose: the table sorts by the study's resolutions
        ("coarser", "flexion", 4.0),
        ("coarse", "flexion", 5.0),
        ("coarser", "extension", 2.0),
        ("coarse", "extension", 3.0),
        ("medium", "extension", 3.3),
    ]
    t = convergence_table(_rom(rows), RES, "coarse", 0.05).set_index(["load_case", "resolution"])
    assert t.loc[("flexion", "coarse"), "change_to_finer"] == pytest.approx(-0.2 / 5.2)
    assert t.loc[("flexion", "coarser"), "change_to_finer"] == pytest.approx(-0.2)
    assert np.isnan(t.loc[("flexion", "medium"), "change_to_finer"])
    assert t.loc[("extension", "coarse"), "change_to_finer"] == pytest.approx(-0.3 / 3.3)
    assert t.loc[("flexion", "coarse"), "converged"] == True  # noqa: E712
    assert t.loc[("extension", "coarse"), "converged"] == False  # noqa: E712
    assert t.loc[("flexion", "coarser"), "converged"] is None  # only the default is judged
    assert verdict(t.reset_index()) is False
    # within 5 %, extension 3.2 vs 3.3 (-3.03 %): converged
    ok = [r if r[:2] != ("coarse", "extension") else ("coarse", "extension", 3.2) for r in rows]
    assert verdict(convergence_table(_rom(ok), RES, "coarse", 0.05)) is True
    md = convergence_markdown(convergence_table(_rom(rows), RES, "coarse", 0.05), "coarse", "medium", 0.05)
    assert "| T6-T7 | extension | 2.000 | 3.000 | 3.300 | -33.3 | -9.1 |" in md
    assert "1 of 2 cases pass, verdict: **not converged**" in md


def test_a_default_case_without_its_finer_solve_fails_and_the_summary_sums_the_solves():
    rows = [("coarser", "flexion", 4.0), ("coarse", "flexion", 5.0), ("coarse", "extension", 3.0)]
    t = convergence_table(_rom(rows), RES, "coarse", 0.05)
    assert list(t.loc[t["resolution"] == "coarse", "converged"]) == [False, False]
    s = resolution_summary(t).set_index("resolution")
    assert s.loc["coarse", "solves"] == 2 and s.loc["coarse", "solve_s"] == 20.0
    assert s.loc["coarse", "peak_rss_mb"] == 200.0


def test_the_study_names_a_bad_configuration():
    block = {"resolutions": RES, "units": ["T6T7"], "load_cases": ["flexion"], "max_change": 0.05}
    assert ConvergenceStudy.from_config(block).judged_pair("coarse") == ("coarse", "medium")
    with pytest.raises(ValueError, match="not the finest"):
        ConvergenceStudy.from_config(block).judged_pair("medium")
    with pytest.raises(ValueError, match="'ultra'"):
        ConvergenceStudy.from_config({**block, "resolutions": ["coarse", "ultra"]})
    with pytest.raises(ValueError, match="T6T8X"):
        ConvergenceStudy.from_config({**block, "units": ["T6T8X"]})
    with pytest.raises(ValueError, match="outside"):
        convergence_table(_rom([("fine", "flexion", 1.0)]), RES, "coarse", 0.05)


@pytest.mark.parametrize("surface_map", ["rays", "closest"])  # the real-bone default, the test config's
def test_the_coarser_preset_is_coarser_than_the_default_and_morphs_without_inverted_hexes(
    ssm, small_cohort, surface_map
):
    from spinecohort.rom.convergence import morphed_template

    coarser, coarse = TEMPLATE_RESOLUTIONS["coarser"], TEMPLATE_RESOLUTIONS["coarse"]
    assert coarser.core_cells < coarse.core_cells and coarser.body_layers < coarse.body_layers
    assert coarser.disc_layers < coarse.disc_layers
    # the pipeline's morph onto the primitive cohort's mean, CEP at 70 % as the configs
    template, nodes, mesh = morphed_template(
        "coarser", ssm.mean, small_cohort.faces, small_cohort.landmarks, MorphParameters(surface_map=surface_map), 0.7
    )
    # 12 around x 3 rings + 3x3 core = 45 quads per layer; 17 bodies x 3 + 17 discs x 4 element layers = 119
    assert mesh["model_hexes"] == len(template.hexes) == 45 * 119
    assert mesh["model_inverted"] == 0 and mesh["model_min_scaled_jacobian"] > 0


def test_one_field_variants_change_exactly_one_discretisation_field():
    from dataclasses import asdict

    from spinecohort.rom.convergence import one_field_variants

    base = asdict(TEMPLATE_RESOLUTIONS["coarse"])
    variants = one_field_variants("coarse", "medium")
    # medium refines all four: core 4 -> 6 cells, rings 3 -> 5, body layers 4 -> 8, disc layers 3 -> 5
    assert {f: getattr(r, f) for f, r in variants.items()} == {
        "core_cells": 6,
        "rings": 5,
        "body_layers": 8,
        "disc_layers": 5,
    }
    for field, res in variants.items():
        assert [k for k, v in asdict(res).items() if v != base[k]] == [field]


def test_the_schema_offers_every_template_resolution_to_the_study():
    schema = yaml.safe_load((Path(__file__).parents[1] / "workflow/schemas/config.schema.yaml").read_text())
    study = schema["properties"]["rom"]["properties"]["convergence"]["properties"]
    assert study["resolutions"]["items"]["enum"] == list(TEMPLATE_RESOLUTIONS)


def test_disc_geometry_scales_as_area_and_length(template):
    from spinecohort.rom.convergence import disc_geometry

    g1 = disc_geometry(template, template.nodes, ["L3L4", "T6T7"])
    g2 = disc_geometry(template, 2.0 * template.nodes, ["L3L4", "T6T7"])
    assert list(g1["unit"]) == ["L3-L4", "T6-T7"]
    # doubling every coordinate: areas x4, heights x2; a lumbar disc is wider and taller than a thoracic one
    assert np.allclose(g2["upper_endplate_mm2"], 4 * g1["upper_endplate_mm2"])
    assert np.allclose(g2["mean_height_mm"], 2 * g1["mean_height_mm"])
    assert (g1["upper_endplate_mm2"].iloc[0] > g1["upper_endplate_mm2"].iloc[1]) and (g1["mean_height_mm"] > 0).all()
    # a projection never adds area; the placed template's endplate layers are planes across the disc's axis, within
    # the tilt of the two endplate planes (a few degrees: cos 5 deg = 0.996)
    assert np.allclose(g2["upper_projected_mm2"], 4 * g1["upper_projected_mm2"])
    ratio = g1["upper_projected_mm2"] / g1["upper_endplate_mm2"]
    assert ((ratio <= 1.0 + 1e-12) & (ratio > 0.99)).all(), ratio
