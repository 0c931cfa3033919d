# Stage 6: the virtual cohort: the Zarr store and one sample/check/repair/measure/write job per shard.
# (L and SHARDS come from common.smk: the Descriptive_List rule gathers the shards too.) The store
# itself is a directory written shard by shard; its .initialized marker is what the rules exchange.


wildcard_constraints:
    shard=r"\d{5}",


rule init_store:
    input:
        ssm=L.ssm,
        hex_ssm=L.hex_ssm,
        template=L.template,
    output:
        L.store_initialized,
    log:
        f"{LOGS}/init_store.log",
    benchmark:
        L.benchmark("init_store")
    conda:
        "../../environment.yml"
    threads: 1
    params:
        grid=config["grid"],
        store=config["store"],
    script:
        "../scripts/init_store.py"


# One pass per shard (sample -> check and repair -> Table 3 rows -> parameters -> one streaming store
# write): the store only ever holds the coordinates the FE models use, nothing is decoded again, and a
# shard is either complete (its record and checksum sidecar exist) or absent.
rule sample_shard:
    input:
        store=L.store_initialized,
        ssm=L.ssm,
        hex_ssm=L.hex_ssm,
        template=L.template,
        cohort=L.cohort,
    output:
        quality=L.shard_file("{shard}", "quality.csv"),
        params=L.shard_file("{shard}", "params.csv"),
        tri_vs_hex=L.shard_file("{shard}", "tri_vs_hex.csv"),
        record=L.shard_file("{shard}", "sample.json"),
    log:
        f"{LOGS}/sample_shard/{{shard}}.log",
    benchmark:
        L.benchmark("sample_shard", "{shard}")
    conda:
        "../../environment.yml"
    threads: 1
    params:
        settings=config["store"],
        measure=config["measure"],
    script:
        "../scripts/sample_shard.py"


# Integrity of the whole store against the sha256 recorded by each shard's writer: fails naming the bad
# shards. `spinecohort check-store <store> --rebuild` then invalidates them and the next run rewrites
# exactly those (docs/reference/store-format.md). Rerun it on demand with `snakemake --forcerun check_store`.
rule check_store:
    input:
        store=L.store_initialized,
        records=expand(L.shard_file("{shard}", "sample.json"), shard=SHARDS),
    output:
        L.store_check,
    log:
        f"{LOGS}/check_store.log",
    benchmark:
        L.benchmark("check_store")
    conda:
        "../../environment.yml"
    threads: 1
    script:
        "../scripts/check_store.py"
