# Stage 2: the statistical shape model: GPA, PCA with compactness, quality measures (mode figure: figures.smk).


rule gpa:
    input:
        f"{R}/cohort/cohort.npz",
    output:
        f"{R}/ssm/aligned.npz",
    log:
        f"{LOGS}/gpa.log",
    benchmark:
        f"{BENCH}/gpa.tsv"
    conda:
        "../../environment.yml"
    threads: 1
    params:
        scaling=config["ssm"]["scaling"],
        tol_mm=config["ssm"]["gpa_tol_mm"],
        max_iter=config["ssm"]["gpa_max_iter"],
    script:
        "../scripts/gpa.py"


rule pca:
    input:
        f"{R}/ssm/aligned.npz",
    output:
        ssm=f"{R}/ssm/ssm.npz",
        table=f"{R}/ssm/compactness.csv",
        figure=report(
            f"{R}/ssm/compactness.png",
            category="1. Statistical shape model",
            caption="../report/compactness.rst",
        ),
    log:
        f"{LOGS}/pca.log",
    benchmark:
        f"{BENCH}/pca.tsv"
    conda:
        "../../environment.yml"
    threads: 1
    params:
        variance_threshold=config["ssm"]["variance_threshold"],
    script:
        "../scripts/pca.py"


rule ssm_quality:
    input:
        aligned=f"{R}/ssm/aligned.npz",
        ssm=f"{R}/ssm/ssm.npz",
    output:
        table=f"{R}/ssm/quality.csv",
        figure=report(
            f"{R}/ssm/quality.png",
            category="1. Statistical shape model",
            caption="../report/quality.rst",
        ),
    log:
        f"{LOGS}/ssm_quality.log",
    benchmark:
        f"{BENCH}/ssm_quality.tsv"
    conda:
        "../../environment.yml"
    threads: 1
    params:
        quality=config["ssm"]["quality"],
    script:
        "../scripts/ssm_quality.py"
