# Stage 6: FE validation. Range of motion of one model under pure moments in CalculiX (lumbar model
# pelvis..T10 and thoracic functional units), compared with in-vitro data (docs/rom.md).


rule rom_model:
    input:
        deck=f"{R}/models/{{model_id}}.inp",
        template=f"{R}/template/template.npz",
    output:
        table=f"{R}/rom/{{model_id}}.csv",
        runs=directory(f"{R}/rom/{{model_id}}"),
    log:
        f"{LOGS}/rom_model/{{model_id}}.log",
    benchmark:
        f"{BENCH}/rom_model/{{model_id}}.tsv"
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
        f"{R}/rom/{config['rom']['model']}.csv",
    output:
        table=f"{R}/rom/validation.csv",
        all_effect=f"{R}/rom/all_effect.csv",
        figure=f"{R}/rom/validation.png",
    log:
        f"{LOGS}/rom_validation.log",
    benchmark:
        f"{BENCH}/rom_validation.tsv"
    conda:
        "../../environment.yml"
    threads: 1
    params:
        rom=config["rom"],
        model=config["rom"]["model"],
    script:
        "../scripts/rom_validation.py"
