# Adapter: materialize one virtual model by target file: results/models/model_NNNNN.{inp,stl,vtu}.
from spinecohort.cohort.loading import load_cohort_npz
from spinecohort.fe.materials import materials_from_config
from spinecohort.fe.models import virtual_model, write_model
from spinecohort.logs import to_file
from spinecohort.mesh.hex_ssm import HexSSM
from spinecohort.mesh.template import HexTemplate
from spinecohort.ssm.model import SSM

with to_file(snakemake.log[0]) as log:
    grid = snakemake.params.grid
    template = HexTemplate.load(snakemake.input.template)
    vm = virtual_model(
        snakemake.wildcards.model_id,
        SSM.load(snakemake.input.ssm),
        HexSSM.load(snakemake.input.hex_ssm),
        template,
        grid["n_modes"],
        grid["levels"],
    )
    log.info("%s: weights %s SD; Jacobian check %s", snakemake.wildcards.model_id, vm.weights.tolist(), vm.repair)
    write_model(
        vm,
        snakemake.wildcards.ext,
        snakemake.output[0],
        template,
        load_cohort_npz(snakemake.input.cohort).faces,
        snakemake.params.hex_type,
        materials=materials_from_config(snakemake.params.fe),
    )
