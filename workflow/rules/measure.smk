# Stage 3: spinopelvic measurement of the patients, and the Descriptive_List workbook.


rule measure_patients:
    input:
        f"{R}/cohort/cohort.npz",
    output:
        table=f"{R}/patients/parameters.csv",
        comparison=f"{R}/patients/sheet_vs_measured.csv",
    params:
        measure=config["measure"],
    log:
        f"{LOGS}/measure_patients.log",
    benchmark:
        f"{BENCH}/measure_patients.tsv"
    threads: 1
    conda:
        "../../environment.yml"
    script:
        "../scripts/measure_patients.py"


rule descriptive_list:
    input:
        patients=f"{R}/patients/parameters.csv",
    output:
        f"{R}/Descriptive_List.xlsx",
    log:
        f"{LOGS}/descriptive_list.log",
    benchmark:
        f"{BENCH}/descriptive_list.tsv"
    threads: 1
    conda:
        "../../environment.yml"
    script:
        "../scripts/descriptive_list.py"
