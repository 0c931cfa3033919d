# Stage 9: FE validation. Range of motion of one model under pure moments in CalculiX (lumbar model
# pelvis..T10 and thoracic functional units), compared with in-vitro data (docs/rom.md).


rule rom_model:
    input:
        deck=L.model_file("{model_id}", "inp"),
        template=L.template,
    output:
        table=L.rom_table("{model_id}"),
        runs=directory(L.rom_dir("{model_id}")),
    log:
        f"{LOGS}/rom_model/{{model_id}}.log",
    benchmark:
        L.benchmark("rom_model", "{model_id}")
    wildcard_constraints:
        model_id=r"model_\d{5}",
    conda:
        "../../environment.yml"
    threads: config["rom"]["threads"]
    params:
        rom=config["rom"],
        fe=config["fe"],
    script:
        "../scripts/rom_model.py"


rule rom_validation:
    input:
        L.rom_table(config["rom"]["model"]),
    output:
        table=L.rom_validation,
        all_effect=L.rom_all_effect,
        figure=L.rom_validation_png,
    log:
        f"{LOGS}/rom_validation.log",
    benchmark:
        L.benchmark("rom_validation")
    conda:
        "../../environment.yml"
    threads: 1
    params:
        rom=config["rom"],
        model=config["rom"]["model"],
    script:
        "../scripts/rom_validation.py"
