# Stage 7: patient-personalized models: mode weights (and posture) fitted to each patient's spinopelvic
# parameters, the image-based alternative (projection of the aligned shape), the fit models' .inp decks.
# personalized_models() (the 42 decks) lives in common.smk: the figures and the release use it too.


rule personalize:
    input:
        cohort=L.cohort,
        aligned=L.aligned,
        ssm=L.ssm,
        parameters=L.patient_parameters,
        template=L.template,
        hex_ssm=L.hex_ssm,
    output:
        table=L.personalization_csv,
        report=L.personalization_report,
        info=L.personalization_info,
        models=personalized_models(),
    log:
        f"{LOGS}/personalize.log",
    benchmark:
        L.benchmark("personalize")
    conda:
        "../../environment.yml"
    threads: 1
    params:
        settings=config["personalize"],
        grid_modes=config["grid"]["n_modes"],
        measure=config["measure"],
        hex_type=config["template"]["hex_type"],
        fe=config["fe"],
    script:
        "../scripts/personalize.py"
