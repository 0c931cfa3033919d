# Stage 4: the hexahedral FE template, its morphing onto the SSM mean, the hex SSM and the Abaqus template.


rule hex_template:
    input:
        ssm=f"{R}/ssm/ssm.npz",
        cohort=f"{R}/cohort/cohort.npz",
    output:
        npz=f"{R}/template/template.npz",
        vtu=f"{R}/template/template.vtu",
    params:
        resolution=config["template"]["resolution"],
    log:
        f"{LOGS}/hex_template.log",
    benchmark:
        f"{BENCH}/hex_template.tsv"
    threads: 1
    conda:
        "../../environment.yml"
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
    params:
        morph=config["morph"],
    log:
        f"{LOGS}/morph_template.log",
    benchmark:
        f"{BENCH}/morph_template.tsv"
    threads: 1
    conda:
        "../../environment.yml"
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
    params:
        transfer=config["hex_ssm"]["transfer"],
        min_disc_height_mm=config["hex_ssm"].get("min_disc_height_mm"),
        grid=config["grid"],
    log:
        f"{LOGS}/hex_ssm.log",
    benchmark:
        f"{BENCH}/hex_ssm.tsv"
    threads: 1
    conda:
        "../../environment.yml"
    script:
        "../scripts/hex_ssm.py"


rule template_inp:
    input:
        template=f"{R}/template/template.npz",
        nodes=f"{R}/template/mean_hex.npz",
    output:
        f"{R}/template/Mean_Model (Template).inp",
    params:
        hex_type=config["template"]["hex_type"],
        fe=config["fe"],
    log:
        f"{LOGS}/template_inp.log",
    benchmark:
        f"{BENCH}/template_inp.tsv"
    threads: 1
    conda:
        "../../environment.yml"
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
    wildcard_constraints:
        model_id=r"model_\d{5}",
        ext="inp|stl|vtu",
    params:
        grid=config["grid"],
        hex_type=config["template"]["hex_type"],
        fe=config["fe"],
    log:
        f"{LOGS}/model_files/{{model_id}}.{{ext}}.log",
    benchmark:
        f"{BENCH}/model_files/{{model_id}}.{{ext}}.tsv"
    threads: 1
    conda:
        "../../environment.yml"
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
    threads: 1
    conda:
        "../../environment.yml"
    script:
        "../scripts/template_quality.py"
