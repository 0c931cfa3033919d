# Stage 3: spinopelvic measurement of the patients, and the Descriptive_List workbook (patients + the
# virtual cohort of stage 6, gathered from its shards).


rule measure_patients:
    input:
        L.cohort,
    output:
        table=L.patient_parameters,
        comparison=L.sheet_vs_measured,
    log:
        f"{LOGS}/measure_patients.log",
    benchmark:
        L.benchmark("measure_patients")
    conda:
        "../../environment.yml"
    threads: 1
    params:
        measure=config["measure"],
    script:
        "../scripts/measure_patients.py"


rule descriptive_list:
    input:
        patients=L.patient_parameters,
        params=expand(L.shard_file("{shard}", "params.csv"), shard=SHARDS),
        quality=expand(L.shard_file("{shard}", "quality.csv"), shard=SHARDS),
        tri_vs_hex=expand(L.shard_file("{shard}", "tri_vs_hex.csv"), shard=SHARDS),
        personalization=L.personalization_csv,  # sheet 2: the personalized models
    output:
        workbook=L.descriptive_list,
        virtual=L.virtual_cohort_csv,
        virtual_parquet=L.virtual_cohort_parquet,  # typed twin of the CSV (write_table_twins)
        tri_vs_hex=L.tri_vs_hex,
    log:
        f"{LOGS}/descriptive_list.log",
    benchmark:
        L.benchmark("descriptive_list")
    conda:
        "../../environment.yml"
    threads: 1
    script:
        "../scripts/descriptive_list.py"
