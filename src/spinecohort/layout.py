"""Every output path of the pipeline, spelled once.

The rules (through ``workflow/rules/common.smk``), the command line, the benchmarks and the tests take their
results paths from a :class:`Layout`; nothing else writes ``"ssm/ssm.npz"`` out again. Paths are strings,
as Snakemake wants them; wildcard patterns are the same functions called with ``"{shard}"``-style
placeholders (``layout.shard_file("{shard}", "sample.json")``).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

#: the deck name the seed's Data Records use for the mean model
TEMPLATE_DECK_NAME = "Mean_Model (Template).inp"

#: mesh file suffixes a user's cohort folder may hold (what segmentation tools export; pyvista reads them all)
MESH_SUFFIXES = (".stl", ".ply", ".obj", ".vtk", ".vtp")

#: the SSM and virtual-cohort figures (figures.smk; the SSM curves come from ssm.smk)
FIGURE_NAMES = (
    "ssm/compactness.png",
    "ssm/quality.png",
    "figures/mode_variation.png",
    "figures/mean_model_parts.png",
    "figures/personalized_gallery.png",
    "figures/parameter_histograms.png",
    "figures/quality_summary.png",
)


@dataclass(frozen=True)
class Layout:
    """The results tree under ``root`` (config key ``results``), stage by stage as the DAG runs."""

    root: str

    def __init__(self, root: str | Path):
        object.__setattr__(self, "root", str(root).rstrip("/") or ".")

    def path(self, *parts: str) -> str:
        return "/".join((self.root, *parts))

    # stage 1: cohort
    @property
    def synthetic_dir(self) -> str:
        return self.path("synthetic_cohort")

    @property
    def cohort(self) -> str:
        return self.path("cohort", "cohort.npz")

    @property
    def cohort_contacts(self) -> str:
        """Neighbouring bones of the real-bone cohort: crossings and closest gaps per pair (rule cohort_contacts)."""
        return self.path("cohort", "contacts.csv")

    # stage 1, a user folder: the labeled reference registered onto each patient (register.smk)
    @property
    def reference(self) -> str:
        return self.path("registered", "reference.npz")

    @property
    def reference_landmarks(self) -> str:
        return self.path("registered", "landmarks.json")

    def registered_stl(self, patient: str) -> str:
        return self.path("registered", f"{patient}.stl")

    def registered_report(self, patient: str) -> str:
        return self.path("registered", f"{patient}.csv")

    @property
    def registration_report(self) -> str:
        return self.path("registered", "report.csv")

    # stage 2: SSM
    @property
    def aligned(self) -> str:
        return self.path("ssm", "aligned.npz")

    @property
    def ssm(self) -> str:
        return self.path("ssm", "ssm.npz")

    @property
    def compactness_csv(self) -> str:
        return self.path("ssm", "compactness.csv")

    @property
    def ssm_quality_csv(self) -> str:
        return self.path("ssm", "quality.csv")

    # spinopelvic measurement of the patients
    @property
    def patient_parameters(self) -> str:
        return self.path("patients", "parameters.csv")

    @property
    def sheet_vs_measured(self) -> str:
        return self.path("patients", "sheet_vs_measured.csv")

    # stage 3: hex template, morph, hex SSM, the template deck
    @property
    def template(self) -> str:
        return self.path("template", "template.npz")

    @property
    def template_vtu(self) -> str:
        return self.path("template", "template.vtu")

    @property
    def mean_hex(self) -> str:
        return self.path("template", "mean_hex.npz")

    @property
    def mean_hex_vtu(self) -> str:
        return self.path("template", "mean_hex.vtu")

    @property
    def morph_report(self) -> str:
        return self.path("template", "morph_report.csv")

    @property
    def mean_quality(self) -> str:
        return self.path("template", "mean_quality.csv")

    @property
    def mean_quality_elements(self) -> str:
        return self.path("template", "mean_quality_elements.csv.gz")

    @property
    def hex_ssm(self) -> str:
        return self.path("template", "hex_ssm.npz")

    @property
    def transfer_report(self) -> str:
        return self.path("template", "transfer_report.csv")

    @property
    def template_deck(self) -> str:
        return self.path("template", TEMPLATE_DECK_NAME)

    # stage 4: the virtual-cohort store and its shards
    @property
    def store(self) -> str:
        return self.path("cohort.zarr")

    @property
    def store_initialized(self) -> str:
        return self.path("cohort.zarr", ".initialized")

    def shard_file(self, shard: str, kind: str) -> str:
        """``shards/<shard>.<kind>``; kind is sample.json, quality.csv, params.csv or tri_vs_hex.csv."""
        return self.path("shards", f"{shard}.{kind}")

    @property
    def store_check(self) -> str:
        return self.path("store_check.csv")

    # stage 5: tables, personalized models, figures, release
    @property
    def descriptive_list(self) -> str:
        return self.path("Descriptive_List.xlsx")

    @property
    def virtual_cohort_csv(self) -> str:
        return self.path("virtual_cohort.csv")

    @property
    def virtual_cohort_parquet(self) -> str:
        return self.path("virtual_cohort.parquet")

    @property
    def tri_vs_hex(self) -> str:
        return self.path("virtual_cohort_tri_vs_hex.csv")

    @property
    def personalized_dir(self) -> str:
        return self.path("personalized")

    def personalized_deck(self, patient_id: str) -> str:
        return self.path("personalized", f"{patient_id}.inp")

    @property
    def personalization_csv(self) -> str:
        return self.path("personalized", "personalization.csv")

    @property
    def personalization_info(self) -> str:
        return self.path("personalized", "info.json")

    @property
    def personalization_report(self) -> str:
        return self.path("personalized", "report.md")

    def figure(self, name: str) -> str:
        """A figure by its name in :data:`FIGURE_NAMES` (``"figures/mode_variation.png"``)."""
        return self.path(name)

    @property
    def figures(self) -> list[str]:
        return [self.figure(n) for n in FIGURE_NAMES]

    def release(self, bag_dir: str) -> str:
        return self.path(bag_dir)

    # on demand: one model's files, FE validation
    def model_file(self, model_id: str, ext: str) -> str:
        return self.path("models", f"{model_id}.{ext}")

    def rom_table(self, model_id: str) -> str:
        return self.path("rom", f"{model_id}.csv")

    def rom_dir(self, model_id: str) -> str:
        return self.path("rom", model_id)

    def rom_idp_table(self, model_id: str) -> str:
        """One model's nucleus pressure per disc and load case (`spinecohort.rom.loads`)."""
        return self.path("rom", f"{model_id}_idp.csv")

    def rom_facet_table(self, model_id: str) -> str:
        """One model's facet contact force per joint side and load case (`spinecohort.rom.loads`)."""
        return self.path("rom", f"{model_id}_facets.csv")

    @property
    def rom_outcomes(self) -> str:
        """Nucleus pressures, facet forces, L1-L5 and same-geometry ROM, orderings against references."""
        return self.path("rom", "validation_extended.csv")

    @property
    def rom_loads_png(self) -> str:
        return self.path("rom", "validation_loads.png")

    @property
    def rom_validation(self) -> str:
        return self.path("rom", "validation.csv")

    @property
    def rom_validation_png(self) -> str:
        return self.path("rom", "validation.png")

    @property
    def rom_all_effect(self) -> str:
        """The configured model's extension ROM with and without the ALL, per segment (rule rom_all_effect)."""
        return self.path("rom", "all_effect.csv")

    @property
    def rom_all_effect_dir(self) -> str:
        return self.path("rom", "all_effect")

    @property
    def rom_validation_md(self) -> str:
        return self.path("rom", "validation.md")

    @property
    def rom_orderings(self) -> str:
        return self.path("rom", "orderings.csv")

    @property
    def rom_sensitivity(self) -> str:
        return self.path("rom", "sensitivity.csv")

    @property
    def rom_sensitivity_png(self) -> str:
        return self.path("rom", "sensitivity.png")

    @property
    def rom_sensitivity_dir(self) -> str:
        return self.path("rom", "sensitivity")

    @property
    def rom_modes(self) -> str:
        return self.path("rom", "modes.csv")

    def rom_mode_table(self, model_id: str) -> str:
        """One model's ROM table of the mode study (its functional units only, rule rom_mode_model)."""
        return self.path("rom", "modes", f"{model_id}.csv")

    def rom_mode_dir(self, model_id: str) -> str:
        return self.path("rom", "modes", model_id)

    @property
    def rom_modes_png(self) -> str:
        return self.path("rom", "modes.png")

    def rom_convergence(self, ext: str = "csv") -> str:
        """The mesh-convergence study of the ROM (rule rom_convergence): ``csv`` table, ``md`` summary, ``png`` figure."""
        return self.path("rom", f"convergence.{ext}")

    def rom_convergence_resolution(self, resolution: str, ext: str = "csv") -> str:
        """One template resolution of the study (rule rom_convergence_resolution): ``csv`` ROM table, ``runs``
        the ccx decks and logs."""
        name = resolution if ext == "runs" else f"{resolution}.{ext}"
        return self.path("rom", "convergence", name)

    # bookkeeping
    def benchmark(self, rule: str, key: str | None = None) -> str:
        """Snakemake's benchmark table of a rule (``benchmarks/<rule>.tsv`` or ``benchmarks/<rule>/<key>.tsv``)."""
        return self.path("benchmarks", f"{rule}.tsv" if key is None else f"{rule}/{key}.tsv")
