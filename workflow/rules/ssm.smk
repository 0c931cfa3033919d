# Stage 2: the statistical shape model: GPA, PCA with compactness, quality measures (mode figure: figures.smk).


rule gpa:
    input:
        L.cohort,
    output:
        L.aligned,
    log:
        f"{LOGS}/gpa.log",
    benchmark:
        L.benchmark("gpa")
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
        L.aligned,
    output:
        ssm=L.ssm,
        table=L.compactness_csv,
        figure=report(
            L.figure("ssm/compactness.png"),
            category="1. Statistical shape model",
            caption="../report/compactness.rst",
        ),
    log:
        f"{LOGS}/pca.log",
    benchmark:
        L.benchmark("pca")
    conda:
        "../../environment.yml"
    threads: 1
    params:
        variance_threshold=config["ssm"]["variance_threshold"],
    script:
        "../scripts/pca.py"


rule ssm_quality:
    input:
        aligned=L.aligned,
        ssm=L.ssm,
    output:
        table=L.ssm_quality_csv,
        figure=report(
            L.figure("ssm/quality.png"),
            category="1. Statistical shape model",
            caption="../report/quality.rst",
        ),
    log:
        f"{LOGS}/ssm_quality.log",
    benchmark:
        L.benchmark("ssm_quality")
    conda:
        "../../environment.yml"
    threads: 1
    params:
        quality=config["ssm"]["quality"],
    script:
        "../scripts/ssm_quality.py"
