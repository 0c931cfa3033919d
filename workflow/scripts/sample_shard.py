# Adapter: one pass over one shard of the virtual cohort: sample (tri + hex), check every hex, repair
# inverted models, Table 3 rows, spinopelvic parameters (tri and hex), one streaming store write; then the
# per-shard tables and, last, the shard record (the job's completion mark).
from pathlib import Path

from spinecohort.logs import to_file
from spinecohort.virtual.shard_job import run_shard_job

with to_file(snakemake.log[0]) as log:
    run_shard_job(
        Path(snakemake.input.store).parent,
        int(snakemake.wildcards.shard),
        inputs={k: snakemake.input[k] for k in ("ssm", "hex_ssm", "template", "cohort")},
        outputs={k: snakemake.output[k] for k in ("quality", "params", "tri_vs_hex", "record")},
        settings=snakemake.params.settings,
        measure_settings=snakemake.params.measure,
        log=log,
    )
