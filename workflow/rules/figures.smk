# Stage 8: figures. Renders (pyvista off-screen) and charts (matplotlib), each a PNG of the pixel size set in
# config `figures`, registered with report() so that `snakemake --report report.html` shows them by topic.
# The compactness and generalization/specificity plots are written by the pca and ssm_quality rules; the list of
# every figure is L.figures (spinecohort.layout.FIGURE_NAMES) (lint: functions live there).


rule mode_variation_figure:
    input:
        ssm=L.ssm,
        cohort=L.cohort,
    output:
        report(
            L.figure("figures/mode_variation.png"),
            category="1. Statistical shape model",
            caption="../report/mode_variation.rst",
            labels={"figure": "shape modes at -3, 0, +3 SD"},
        ),
    log:
        f"{LOGS}/mode_variation_figure.log",
    benchmark:
        L.benchmark("mode_variation_figure")
    conda:
        "../../environment.yml"
    threads: 1
    params:
        n_modes=config["figures"]["mode_variation_modes"],
        window=config["figures"]["window"],
        dpi=config["figures"]["dpi"],
    script:
        "../scripts/mode_variation_figure.py"


rule mean_model_parts_figure:
    input:
        template=L.template,
        hex_ssm=L.hex_ssm,
    output:
        report(
            L.figure("figures/mean_model_parts.png"),
            category="2. Hexahedral FE template",
            caption="../report/mean_model_parts.rst",
            labels={"figure": "hex mean model by part"},
        ),
    log:
        f"{LOGS}/mean_model_parts_figure.log",
    benchmark:
        L.benchmark("mean_model_parts_figure")
    conda:
        "../../environment.yml"
    threads: 1
    params:
        size=config["figures"]["parts_size"],
        dpi=config["figures"]["dpi"],
        detail_disc=config["figures"]["detail_disc"],
    script:
        "../scripts/mean_model_parts_figure.py"


rule parameter_histograms_figure:
    input:
        virtual=L.virtual_cohort_csv,
        patients=L.patient_parameters,
    output:
        report(
            L.figure("figures/parameter_histograms.png"),
            category="3. Virtual cohort",
            caption="../report/parameter_histograms.rst",
            labels={"figure": "parameter histograms"},
        ),
    log:
        f"{LOGS}/parameter_histograms_figure.log",
    benchmark:
        L.benchmark("parameter_histograms_figure")
    conda:
        "../../environment.yml"
    threads: 1
    params:
        size=config["figures"]["histogram_size"],
        dpi=config["figures"]["dpi"],
        parameters=config["figures"]["histogram_parameters"],
        criteria=config["synthetic"]["criteria"],
    script:
        "../scripts/parameter_histograms_figure.py"


rule quality_summary_figure:
    input:
        shards=expand(L.shard_file("{shard}", "quality.csv"), shard=SHARDS),
        table3=L.mean_quality,
    output:
        report(
            L.figure("figures/quality_summary.png"),
            category="3. Virtual cohort",
            caption="../report/quality_summary.rst",
            labels={"figure": "mesh quality"},
        ),
    log:
        f"{LOGS}/quality_summary_figure.log",
    benchmark:
        L.benchmark("quality_summary_figure")
    conda:
        "../../environment.yml"
    threads: 1
    params:
        size=config["figures"]["quality_size"],
        dpi=config["figures"]["dpi"],
    script:
        "../scripts/quality_summary_figure.py"


rule personalized_gallery_figure:
    input:
        table=L.personalization_csv,
        template=L.template,
        hex_ssm=L.hex_ssm,
    output:
        report(
            L.figure("figures/personalized_gallery.png"),
            category="4. Personalized models",
            caption="../report/personalized_gallery.rst",
            labels={"figure": "personalized models"},
        ),
    log:
        f"{LOGS}/personalized_gallery_figure.log",
    benchmark:
        L.benchmark("personalized_gallery_figure")
    conda:
        "../../environment.yml"
    threads: 1
    params:
        size=config["figures"]["gallery_size"],
        dpi=config["figures"]["dpi"],
        n_models=config["figures"]["gallery_patients"],
    script:
        "../scripts/personalized_gallery_figure.py"
