# Stage 1: the patient cohort (embedded synthetic generator or a user STL folder), read and validated.


if config["cohort"]["source"] == "synthetic":

    rule synthetic_cohort:
        output:
            stls=COHORT["stls"],
            sheet=COHORT["sheet"],
            landmarks=COHORT["landmarks"],
        log:
            f"{LOGS}/synthetic_cohort.log",
        benchmark:
            L.benchmark("synthetic_cohort")
        conda:
            "../../environment.yml"
        threads: 1
        params:
            synthetic=config["synthetic"],
            generator=config["cohort"]["generator"],
        script:
            "../scripts/synthetic_cohort.py"


rule validate_cohort:
    input:
        stls=COHORT["stls"],
        sheet=COHORT["sheet"],
        landmarks=COHORT["landmarks"],
    output:
        L.cohort,
    log:
        f"{LOGS}/validate_cohort.log",
    benchmark:
        L.benchmark("validate_cohort")
    conda:
        "../../environment.yml"
    threads: 1
    params:
        units=config["cohort"]["units"],
        degenerate_area_mm2=config["cohort"]["degenerate_area_mm2"],
        max_degenerate_fraction=config["cohort"]["max_degenerate_fraction"],
    script:
        "../scripts/validate_cohort.py"


rule cohort_contacts:
    input:
        L.cohort,
    output:
        L.cohort_contacts,
    log:
        f"{LOGS}/cohort_contacts.log",
    benchmark:
        L.benchmark("cohort_contacts")
    conda:
        "../../environment.yml"
    threads: 1
    script:
        "../scripts/cohort_contacts.py"
