# Stage 4: the hexahedral FE mesh: the template, its morphing onto the SSM mean (BCPD), its Table 3 quality and
# the hex SSM (deformation-field transfer). Decks are stage 5 (fe.smk).


rule hex_template:
    input:
        ssm=L.ssm,
        cohort=L.cohort,
    output:
        npz=L.template,
        vtu=L.template_vtu,
    log:
        f"{LOGS}/hex_template.log",
    benchmark:
        L.benchmark("hex_template")
    conda:
        "../../environment.yml"
    threads: 1
    params:
        resolution=config["template"]["resolution"],
        cep_diameter_fraction=config["template"].get("cep_diameter_fraction", 1.0),
        fibres=fibres_per_ligament(config["fe"]["ligaments"]),
    script:
        "../scripts/hex_template.py"


rule morph_template:
    input:
        template=L.template,
        ssm=L.ssm,
        cohort=L.cohort,
    output:
        nodes=L.mean_hex,
        vtu=L.mean_hex_vtu,
        report=L.morph_report,
    log:
        f"{LOGS}/morph_template.log",
    benchmark:
        L.benchmark("morph_template")
    conda:
        "../../environment.yml"
    threads: 1
    params:
        morph=config["morph"],
    script:
        "../scripts/morph_template.py"


rule hex_ssm:
    input:
        template=L.template,
        nodes=L.mean_hex,
        ssm=L.ssm,
        cohort=L.cohort,
    output:
        ssm=L.hex_ssm,
        report=L.transfer_report,
    log:
        f"{LOGS}/hex_ssm.log",
    benchmark:
        L.benchmark("hex_ssm")
    conda:
        "../../environment.yml"
    threads: 1
    params:
        transfer=config["hex_ssm"]["transfer"],
        min_disc_height_mm=config["hex_ssm"].get("min_disc_height_mm"),
        grid=config["grid"],
    script:
        "../scripts/hex_ssm.py"


rule template_quality:
    input:
        template=L.template,
        nodes=L.mean_hex,
    output:
        elements=L.mean_quality_elements,
        table3=L.mean_quality,
    log:
        f"{LOGS}/template_quality.log",
    benchmark:
        L.benchmark("template_quality")
    conda:
        "../../environment.yml"
    threads: 1
    script:
        "../scripts/template_quality.py"
