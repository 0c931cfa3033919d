# Stage 3: spinopelvic measurement of the patients, and the Descriptive_List workbook (patients + the
# virtual cohort of stage 5, gathered from its shards).


rule measure_patients:
    input:
        f"{R}/cohort/cohort.npz",
    output:
        table=f"{R}/patients/parameters.csv",
        comparison=f"{R}/patients/sheet_vs_measured.csv",
    log:
        f"{LOGS}/measure_patients.log",
    benchmark:
        f"{BENCH}/measure_patients.tsv"
    conda:
        "../../environment.yml"
    threads: 1
    params:
        measure=config["measure"],
    script:
        "../scripts/measure_patients.py"


rule descriptive_list:
    input:
        patients=f"{R}/patients/parameters.csv",
        params=expand(f"{R}/shards/{{shard}}.params.csv", shard=SHARDS),
        quality=expand(f"{R}/shards/{{shard}}.quality.csv", shard=SHARDS),
        tri_vs_hex=expand(f"{R}/shards/{{shard}}.tri_vs_hex.csv", shard=SHARDS),
        personalization=f"{R}/personalized/personalization.csv",  # sheet 2: the personalized models
    output:
        workbook=f"{R}/Descriptive_List.xlsx",
        virtual=f"{R}/virtual_cohort.csv",
        virtual_parquet=f"{R}/virtual_cohort.parquet",  # typed twin of the CSV (write_table_twins)
        tri_vs_hex=f"{R}/virtual_cohort_tri_vs_hex.csv",
    log:
        f"{LOGS}/descriptive_list.log",
    benchmark:
        f"{BENCH}/descriptive_list.tsv"
    conda:
        "../../environment.yml"
    threads: 1
    script:
        "../scripts/descriptive_list.py"
