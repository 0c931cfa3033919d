# Stage 5: the virtual cohort: the Zarr store, one sample/check/repair job and one measure job per shard.
# (STORE and SHARDS come from common.smk: the Descriptive_List rule gathers the shards too.) The store
# itself is a directory written shard by shard; its .initialized marker is what the rules exchange.


wildcard_constraints:
    shard=r"\d{5}",


rule init_store:
    input:
        ssm=f"{R}/ssm/ssm.npz",
        hex_ssm=f"{R}/template/hex_ssm.npz",
    output:
        f"{STORE}/.initialized",
    log:
        f"{LOGS}/init_store.log",
    benchmark:
        f"{BENCH}/init_store.tsv"
    conda:
        "../../environment.yml"
    threads: 1
    params:
        grid=config["grid"],
        store=config["store"],
    script:
        "../scripts/init_store.py"


# Check and repair run before the single store write (one rule, not the design's two): the store only
# ever holds the coordinates the FE models use, and a shard is either complete or absent.
rule sample_shard:
    input:
        store=f"{STORE}/.initialized",
        ssm=f"{R}/ssm/ssm.npz",
        hex_ssm=f"{R}/template/hex_ssm.npz",
        template=f"{R}/template/template.npz",
    output:
        quality=f"{R}/shards/{{shard}}.quality.csv",
        record=f"{R}/shards/{{shard}}.sample.json",
    log:
        f"{LOGS}/sample_shard/{{shard}}.log",
    benchmark:
        f"{BENCH}/sample_shard/{{shard}}.tsv"
    conda:
        "../../environment.yml"
    threads: 1
    params:
        grid=config["grid"],
        settings=config["store"],
    script:
        "../scripts/sample_shard.py"


rule measure_shard:
    input:
        store=f"{STORE}/.initialized",
        record=f"{R}/shards/{{shard}}.sample.json",
        cohort=f"{R}/cohort/cohort.npz",
        template=f"{R}/template/template.npz",
    output:
        params=f"{R}/shards/{{shard}}.params.csv",
        tri_vs_hex=f"{R}/shards/{{shard}}.tri_vs_hex.csv",
    log:
        f"{LOGS}/measure_shard/{{shard}}.log",
    benchmark:
        f"{BENCH}/measure_shard/{{shard}}.tsv"
    conda:
        "../../environment.yml"
    threads: 1
    params:
        measure=config["measure"],
    script:
        "../scripts/measure_shard.py"


# Integrity of the whole store against the sha256 recorded by each shard's writer: fails naming the bad
# shards. `spinecohort check-store <store> --rebuild` then invalidates them and the next run rewrites
# exactly those (docs/store.md). Rerun it on demand with `snakemake --forcerun check_store`.
rule check_store:
    input:
        store=f"{STORE}/.initialized",
        records=expand(f"{R}/shards/{{shard}}.sample.json", shard=SHARDS),
    output:
        f"{R}/store_check.csv",
    log:
        f"{LOGS}/check_store.log",
    benchmark:
        f"{BENCH}/check_store.tsv"
    conda:
        "../../environment.yml"
    threads: 1
    script:
        "../scripts/check_store.py"
