# Stage 4: the hexahedral FE template, its morphing onto the SSM mean, the hex SSM and the Abaqus template.


rule hex_template:
    input:
        ssm=f"{R}/ssm/ssm.npz",
        cohort=f"{R}/cohort/cohort.npz",
    output:
        npz=f"{R}/template/template.npz",
        vtu=f"{R}/template/template.vtu",
    log:
        f"{LOGS}/hex_template.log",
    benchmark:
        f"{BENCH}/hex_template.tsv"
    conda:
        "../../environment.yml"
    threads: 1
    params:
        resolution=config["template"]["resolution"],
    script:
        "../scripts/hex_template.py"


rule morph_template:
    input:
        template=f"{R}/template/template.npz",
        ssm=f"{R}/ssm/ssm.npz",
        cohort=f"{R}/cohort/cohort.npz",
    output:
        nodes=f"{R}/template/mean_hex.npz",
        vtu=f"{R}/template/mean_hex.vtu",
        report=f"{R}/template/morph_report.csv",
    log:
        f"{LOGS}/morph_template.log",
    benchmark:
        f"{BENCH}/morph_template.tsv"
    conda:
        "../../environment.yml"
    threads: 1
    params:
        morph=config["morph"],
    script:
        "../scripts/morph_template.py"


rule hex_ssm:
    input:
        template=f"{R}/template/template.npz",
        nodes=f"{R}/template/mean_hex.npz",
        ssm=f"{R}/ssm/ssm.npz",
        cohort=f"{R}/cohort/cohort.npz",
    output:
        ssm=f"{R}/template/hex_ssm.npz",
        report=f"{R}/template/transfer_report.csv",
    log:
        f"{LOGS}/hex_ssm.log",
    benchmark:
        f"{BENCH}/hex_ssm.tsv"
    conda:
        "../../environment.yml"
    threads: 1
    params:
        transfer=config["hex_ssm"]["transfer"],
        min_disc_height_mm=config["hex_ssm"].get("min_disc_height_mm"),
        grid=config["grid"],
    script:
        "../scripts/hex_ssm.py"


rule template_inp:
    input:
        template=f"{R}/template/template.npz",
        nodes=f"{R}/template/mean_hex.npz",
    output:
        f"{R}/template/Mean_Model (Template).inp",
    log:
        f"{LOGS}/template_inp.log",
    benchmark:
        f"{BENCH}/template_inp.tsv"
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
        template=f"{R}/template/template.npz",
        hex_ssm=f"{R}/template/hex_ssm.npz",
        ssm=f"{R}/ssm/ssm.npz",
        cohort=f"{R}/cohort/cohort.npz",
    output:
        f"{R}/models/{{model_id}}.{{ext}}",
    log:
        f"{LOGS}/model_files/{{model_id}}.{{ext}}.log",
    benchmark:
        f"{BENCH}/model_files/{{model_id}}.{{ext}}.tsv"
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


rule template_quality:
    input:
        template=f"{R}/template/template.npz",
        nodes=f"{R}/template/mean_hex.npz",
    output:
        elements=f"{R}/template/mean_quality_elements.csv.gz",
        table3=f"{R}/template/mean_quality.csv",
    log:
        f"{LOGS}/template_quality.log",
    benchmark:
        f"{BENCH}/template_quality.tsv"
    conda:
        "../../environment.yml"
    threads: 1
    script:
        "../scripts/template_quality.py"
