# Adapter: the hex mean model (morphed template) coloured by tissue, with ligaments by group.
from spinecohort.figures.models import part_model_figure
from spinecohort.logs import to_file
from spinecohort.mesh.hex_ssm import HexSSM
from spinecohort.mesh.template import HexTemplate

with to_file(snakemake.log[0]) as log:
    template = HexTemplate.load(snakemake.input.template)
    hex_ssm = HexSSM.load(snakemake.input.hex_ssm)
    if hex_ssm.mean.shape[0] != template.n_nodes:
        raise ValueError(
            f"{snakemake.input.hex_ssm}: {hex_ssm.mean.shape[0]} nodes, but the template "
            f"{snakemake.input.template} has {template.n_nodes}"
        )
    part_model_figure(
        template,
        hex_ssm.mean,
        snakemake.output[0],
        tuple(snakemake.params.size),
        dpi=snakemake.params.dpi,
        detail_disc=snakemake.params.detail_disc,
    )
    log.info(
        "%d hexes, %d surface triangles, %d ligaments drawn",
        len(template.hexes),
        len(template.tris),
        len(template.ligaments),
    )
