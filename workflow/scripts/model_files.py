# Adapter: materialize one virtual model by target file: results/models/model_NNNNN.{inp,stl,vtu}.
from spinecohort.cohort import load_cohort_npz
from spinecohort.fe_export import materials_from_config
from spinecohort.hex_ssm import HexSSM
from spinecohort.hex_template import HexTemplate
from spinecohort.logs import to_file
from spinecohort.models import virtual_model, write_model
from spinecohort.pca import SSM

with to_file(snakemake.log[0]) as log:
    grid = snakemake.params.grid
    template = HexTemplate.load(snakemake.input.template)
    vm = virtual_model(snakemake.wildcards.model_id, SSM.load(snakemake.input.ssm), HexSSM.load(snakemake.input.hex_ssm),
                       template, grid["n_modes"], grid["levels"])
    log.info("%s: weights %s SD; Jacobian check %s", snakemake.wildcards.model_id, vm.weights.tolist(), vm.repair)
    write_model(vm, snakemake.wildcards.ext, snakemake.output[0], template,
                load_cohort_npz(snakemake.input.cohort).faces, snakemake.params.hex_type,
                materials=materials_from_config(snakemake.params.fe))
