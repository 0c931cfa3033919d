# Stage 5: FE decks: the mean model's Abaqus/CalculiX deck and any virtual model's .inp/.stl/.vtu by target file
# (results/models/model_NNNNN.<ext>, a partial rerun of one job).


rule template_inp:
    input:
        template=L.template,
        nodes=L.mean_hex,
    output:
        L.template_deck,
    log:
        f"{LOGS}/template_inp.log",
    benchmark:
        L.benchmark("template_inp")
    conda:
        "../../environment.yml"
    threads: 1
    params:
        hex_type=config["template"]["hex_type"],
        fe=config["fe"],
    script:
        "../scripts/template_inp.py"


rule model_files:
    input:
        template=L.template,
        hex_ssm=L.hex_ssm,
        ssm=L.ssm,
        cohort=L.cohort,
    output:
        L.model_file("{model_id}", "{ext}"),
    log:
        f"{LOGS}/model_files/{{model_id}}.{{ext}}.log",
    benchmark:
        L.benchmark("model_files", "{model_id}.{ext}")
    wildcard_constraints:
        model_id=r"model_\d{5}",
        ext="inp|stl|vtu",
    conda:
        "../../environment.yml"
    threads: 1
    params:
        grid=config["grid"],
        hex_type=config["template"]["hex_type"],
        fe=config["fe"],
    script:
        "../scripts/model_files.py"
