# Stage 9: FE validation. Range of motion of one model under pure moments in CalculiX (lumbar model
# pelvis..T10 and thoracic functional units), compared with in-vitro data, and its nucleus pressures, facet forces,
# L1-L5 and same-geometry ROM against the packaged references (docs/explanation/validation.md); the sensitivity of
# the compared ROM to the calibrated parameters; the ROM of the mean and of each shape mode at its extremes.
from spinecohort.rom.modes import mode_models, mode_rom_config
from spinecohort.rom.run import solver_config


rule rom_model:
    input:
        deck=L.model_file("{model_id}", "inp"),
        template=L.template,
    output:
        table=L.rom_table("{model_id}"),
        idp=L.rom_idp_table("{model_id}"),
        facets=L.rom_facet_table("{model_id}"),
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
        # only what the solver reads: editing references, criteria or the sensitivity list reruns nothing
        rom=solver_config(config["rom"]),
        fe=config["fe"],
    script:
        "../scripts/rom_model.py"


rule rom_validation:
    input:
        table=L.rom_table(config["rom"]["model"]),
        idp=L.rom_idp_table(config["rom"]["model"]),
        facets=L.rom_facet_table(config["rom"]["model"]),
    output:
        table=L.rom_validation,
        orderings=L.rom_orderings,
        markdown=L.rom_validation_md,
        figure=L.rom_validation_png,
        outcomes=L.rom_outcomes,
        loads_figure=L.rom_loads_png,
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


# The ALL's share of extension: the validation model's extension solved again without the ALL (not in the
# validation's DAG: ~2.5 min of ccx that the comparison does not read)
rule rom_all_effect:
    input:
        deck=L.model_file(config["rom"]["model"], "inp"),
        template=L.template,
        table=L.rom_table(config["rom"]["model"]),
    output:
        table=L.rom_all_effect,
        runs=directory(L.rom_all_effect_dir),
    log:
        f"{LOGS}/rom_all_effect.log",
    benchmark:
        L.benchmark("rom_all_effect")
    conda:
        "../../environment.yml"
    threads: config["rom"]["threads"]
    params:
        rom=solver_config(config["rom"]),
        fe=config["fe"],
        model=config["rom"]["model"],
    script:
        "../scripts/rom_all_effect.py"


rule rom_sensitivity:
    input:
        deck=L.model_file(config["rom"]["model"], "inp"),
        template=L.template,
    output:
        table=L.rom_sensitivity,
        figure=L.rom_sensitivity_png,
    log:
        f"{LOGS}/rom_sensitivity.log",
    benchmark:
        L.benchmark("rom_sensitivity")
    conda:
        "../../environment.yml"
    threads: config["rom"]["threads"]
    params:
        rom=config["rom"],
        fe=config["fe"],
        model=config["rom"]["model"],
    script:
        "../scripts/rom_sensitivity.py"


# The cohort's mechanics: the mean and each shape mode at rom.mode_levels, functional units rom.mode_units
# (not in rule all: ~2 min per model on 2 cores)
MODE_MODELS = mode_models(
    config["grid"]["n_modes"], config["grid"]["levels"], config["rom"]["mode_levels"]
)


rule rom_mode_model:
    input:
        deck=L.model_file("{model_id}", "inp"),
        template=L.template,
    output:
        table=L.rom_mode_table("{model_id}"),
        runs=directory(L.rom_mode_dir("{model_id}")),
    log:
        f"{LOGS}/rom_mode_model/{{model_id}}.log",
    benchmark:
        L.benchmark("rom_mode_model", "{model_id}")
    wildcard_constraints:
        model_id=r"model_\d{5}",
    conda:
        "../../environment.yml"
    threads: config["rom"]["threads"]
    params:
        rom=mode_rom_config(config["rom"]),
        fe=config["fe"],
    script:
        "../scripts/rom_model.py"


rule rom_modes:
    input:
        tables=[L.rom_mode_table(m) for m in MODE_MODELS["model"]],
        benchmarks=[L.benchmark("rom_mode_model", m) for m in MODE_MODELS["model"]],
    output:
        table=L.rom_modes,
        figure=L.rom_modes_png,
    log:
        f"{LOGS}/rom_modes.log",
    benchmark:
        L.benchmark("rom_modes")
    conda:
        "../../environment.yml"
    threads: 1
    params:
        models=MODE_MODELS.to_dict("list"),
    script:
        "../scripts/rom_modes.py"


# Mesh convergence of the ROM (docs/explanation/validation.md "Mesh convergence"): the mean's hex model built
# and morphed at each rom.convergence resolution, its functional units solved; not in rule all (see the
# explanation for its cost)
from spinecohort.rom.convergence import ConvergenceStudy

CONVERGENCE = ConvergenceStudy.from_config(config["rom"]["convergence"])


rule rom_convergence_resolution:
    input:
        ssm=L.ssm,
        cohort=L.cohort,
    output:
        table=L.rom_convergence_resolution("{resolution}"),
        runs=directory(L.rom_convergence_resolution("{resolution}", "runs")),
    log:
        f"{LOGS}/rom_convergence/{{resolution}}.log",
    benchmark:
        L.benchmark("rom_convergence_resolution", "{resolution}")
    wildcard_constraints:
        resolution="|".join(CONVERGENCE.resolutions),
    conda:
        "../../environment.yml"
    threads: config["rom"]["threads"]
    params:
        # only what a resolution's solves read: editing the list of resolutions or the criterion re-solves nothing
        units=config["rom"]["convergence"]["units"],
        load_cases=config["rom"]["convergence"]["load_cases"],
        morph=config["morph"],
        cep_diameter_fraction=config["template"].get("cep_diameter_fraction", 1.0),
        rom=solver_config(config["rom"]),
        fe=config["fe"],
    script:
        "../scripts/rom_convergence_resolution.py"


rule rom_convergence:
    input:
        tables=[L.rom_convergence_resolution(r) for r in CONVERGENCE.resolutions],
    output:
        table=L.rom_convergence(),
        markdown=L.rom_convergence("md"),
        figure=L.rom_convergence("png"),
    log:
        f"{LOGS}/rom_convergence.log",
    benchmark:
        L.benchmark("rom_convergence")
    conda:
        "../../environment.yml"
    threads: 1
    params:
        study=config["rom"]["convergence"],
        default=config["template"]["resolution"],
    script:
        "../scripts/rom_convergence.py"
