# Configuration validation (before any rule runs) and the path helpers every stage uses.
from pathlib import Path

from spinecohort.config import ConfigError, cohort_files, validate_config
from spinecohort.store.zarr_store import n_models, n_shards

try:
    validate_config(
        config, Path(workflow.basedir) / "workflow" / "schemas" / "config.schema.yaml"
    )
except ConfigError as exc:
    raise WorkflowError(str(exc)) from None

R = config["results"]  # root of every output
LOGS = config["logs"]
BENCH = f"{R}/benchmarks"
COHORT = cohort_files(config)
STORE = f"{R}/cohort.zarr"  # the virtual cohort (docs/store.md)
# shard ids of the virtual cohort, zero-padded: one sample and one measure job each
SHARDS = [
    f"{s:05d}"
    for s in range(
        n_shards(
            n_models(config["grid"]["n_modes"], config["grid"]["levels"]),
            config["store"]["shard_models"],
        )
    )
]


def personalized_models():
    """The personalized .inp deck of every patient (personalize.smk; the figures and the release use it).
    Patient IDs = the cohort's STL stems (synthetic: P01..Pnn), as the cohort stage names them.
    """
    return [f"{R}/personalized/{Path(p).stem}.inp" for p in COHORT["stls"]]


def figure_files():
    """Every figure of the pipeline (rules in figures.smk, the SSM curves in ssm.smk); the release packs them."""
    return [
        f"{R}/ssm/compactness.png",
        f"{R}/ssm/quality.png",
        f"{R}/figures/mode_variation.png",
        f"{R}/figures/mean_model_parts.png",
        f"{R}/figures/personalized_gallery.png",
        f"{R}/figures/parameter_histograms.png",
        f"{R}/figures/quality_summary.png",
    ]


def final_outputs():
    return [
        f"{R}/cohort/cohort.npz",
        f"{R}/ssm/ssm.npz",
        f"{R}/ssm/compactness.csv",
        f"{R}/ssm/compactness.png",
        f"{R}/ssm/quality.csv",
        f"{R}/ssm/quality.png",
        f"{R}/figures/mode_variation.png",
        f"{R}/patients/parameters.csv",
        f"{R}/Descriptive_List.xlsx",
        f"{R}/virtual_cohort.csv",
        f"{R}/store_check.csv",
        f"{R}/virtual_cohort_tri_vs_hex.csv",
        f"{R}/template/morph_report.csv",
        f"{R}/template/mean_quality.csv",
        f"{R}/template/hex_ssm.npz",
        f"{R}/template/transfer_report.csv",
        f"{R}/template/Mean_Model (Template).inp",
        *figure_files(),
        RELEASE_BAG,  # release.smk: the verified BagIt bag (its tag manifest is written last)
    ]


def release_inputs(wildcards):
    """Inputs of the release (release.smk), i.e. everything the bag holds."""
    return {
        "store": f"{STORE}/.initialized",
        "store_check": f"{R}/store_check.csv",  # the bag packs only a store whose every shard checks out
        "shards": expand(f"{R}/shards/{{shard}}.sample.json", shard=SHARDS),
        "template_inp": f"{R}/template/Mean_Model (Template).inp",
        "workbook": f"{R}/Descriptive_List.xlsx",
        "virtual": f"{R}/virtual_cohort.csv",
        "patient_table": f"{R}/patients/parameters.csv",
        "patients": COHORT["stls"],
        "personalized": personalized_models(),
        # the SSM figures every configuration makes, plus the figure stage's pictures
        "figures": list(
            dict.fromkeys(
                [
                    f"{R}/ssm/compactness.png",
                    f"{R}/ssm/quality.png",
                    f"{R}/figures/mode_variation.png",
                    *figure_files(),
                ]
            )
        ),
        "ssm": f"{R}/ssm/ssm.npz",
        "hex_ssm": f"{R}/template/hex_ssm.npz",
        "template": f"{R}/template/template.npz",
        "cohort": f"{R}/cohort/cohort.npz",
    }
