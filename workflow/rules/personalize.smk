# Stage 6: patient-personalized models: mode weights (and posture) fitted to each patient's spinopelvic
# parameters, the image-based alternative (projection of the aligned shape), the fit models' .inp decks.
# personalized_models() (the 42 decks) lives in common.smk: the figures and the release use it too.


rule personalize:
    input:
        cohort=f"{R}/cohort/cohort.npz",
        aligned=f"{R}/ssm/aligned.npz",
        ssm=f"{R}/ssm/ssm.npz",
        parameters=f"{R}/patients/parameters.csv",
        template=f"{R}/template/template.npz",
        hex_ssm=f"{R}/template/hex_ssm.npz",
    output:
        table=f"{R}/personalized/personalization.csv",
        report=f"{R}/personalized/report.md",
        info=f"{R}/personalized/info.json",
        models=personalized_models(),
    log:
        f"{LOGS}/personalize.log",
    benchmark:
        f"{BENCH}/personalize.tsv"
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
