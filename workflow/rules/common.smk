# Configuration validation (before any rule runs) and the path helpers every stage uses.
from pathlib import Path

from spinecohort.config import ConfigError, cohort_files, cohort_layout, validate_config
from spinecohort.layout import Layout
from spinecohort.mesh.ligament_sites import fibres_per_ligament
from spinecohort.store.zarr_store import n_models, n_shards

try:
    validate_config(
        config, Path(workflow.basedir) / "workflow" / "schemas" / "config.schema.yaml"
    )
except ConfigError as exc:
    raise WorkflowError(str(exc)) from None

L = Layout(config["results"])  # every results path (spinecohort.layout)
R = L.root
LOGS = config["logs"]
COHORT = cohort_files(config)
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
    return [L.personalized_deck(Path(p).stem) for p in COHORT["stls"]]


#: the cohort is the embedded generator's real-bone one (its bones carry the reference's level and part labels)
REAL_BONES = (
    config["cohort"]["source"] == "synthetic"
    and config["cohort"].get("generator") == "real"
)


def final_outputs():
    """The targets of `rule all`, each once."""
    return [
        L.cohort,
        L.ssm,
        L.compactness_csv,
        L.ssm_quality_csv,
        L.patient_parameters,
        L.descriptive_list,
        L.virtual_cohort_csv,
        L.store_check,
        L.tri_vs_hex,
        L.morph_report,
        L.mean_quality,
        L.hex_ssm,
        L.transfer_report,
        L.template_deck,
        *L.figures,
        RELEASE_BAG,  # release.smk: the verified BagIt bag (its tag manifest is written last)
        *([L.registration_report] if "inputs" in COHORT else []),  # register.smk
        *(
            [L.cohort_contacts] if REAL_BONES else []
        ),  # cohort.smk: no two bones of a patient cross
    ]


def release_inputs(wildcards):
    """Inputs of the release (release.smk), i.e. everything the bag holds."""
    return {
        "store": L.store_initialized,
        "store_check": L.store_check,  # the bag packs only a store whose every shard checks out
        "shards": expand(L.shard_file("{shard}", "sample.json"), shard=SHARDS),
        "template_inp": L.template_deck,
        "workbook": L.descriptive_list,
        "virtual": L.virtual_cohort_csv,
        "patient_table": L.patient_parameters,
        "patients": COHORT["stls"],
        "personalized": personalized_models(),
        # the SSM figures every configuration makes, plus the figure stage's pictures
        "figures": L.figures,
        "ssm": L.ssm,
        "hex_ssm": L.hex_ssm,
        "template": L.template,
        "cohort": L.cohort,
    }
