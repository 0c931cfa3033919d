# Configuration validation (before any rule runs) and the path helpers every stage uses.
from pathlib import Path

from spinecohort.config import ConfigError, cohort_files, validate_config
from spinecohort.store import n_models, n_shards

try:
    validate_config(config, Path(workflow.basedir) / "workflow" / "schemas" / "config.schema.yaml")
except ConfigError as exc:
    raise WorkflowError(str(exc)) from None

R = config["results"]  # root of every output
LOGS = config["logs"]
BENCH = f"{R}/benchmarks"
COHORT = cohort_files(config)
STORE = f"{R}/cohort.zarr"  # the virtual cohort (docs/store.md)
# shard ids of the virtual cohort, zero-padded: one sample and one measure job each
SHARDS = [f"{s:05d}" for s in range(n_shards(n_models(config["grid"]["n_modes"], config["grid"]["levels"]),
                                              config["store"]["shard_models"]))]


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
        f"{R}/virtual_cohort_tri_vs_hex.csv",
        f"{R}/template/morph_report.csv",
        f"{R}/template/mean_quality.csv",
        f"{R}/template/hex_ssm.npz",
        f"{R}/template/transfer_report.csv",
        f"{R}/release/Mean_Model (Template).inp",
    ]
