# Adapter: build the hex template on the SSM mean (placed by the mean's endplate frames).
import dataclasses

from spinecohort.cohort.loading import load_cohort_npz
from spinecohort.fe.export import NOT_ANATOMY, fe_model
from spinecohort.fe.writers import write_vtu
from spinecohort.logs import to_file
from spinecohort.mesh.template import TEMPLATE_RESOLUTIONS, build_template
from spinecohort.ssm.model import SSM

with to_file(snakemake.log[0]) as log:
    ssm = SSM.load(snakemake.input.ssm)
    cohort = load_cohort_npz(snakemake.input.cohort)
    resolution = dataclasses.replace(
        TEMPLATE_RESOLUTIONS[snakemake.params.resolution],
        cep_diameter_fraction=float(snakemake.params.cep_diameter_fraction),
    )
    # ligament bundles at the insertion sites where the cohort's landmarks carry them (real bones)
    template = build_template(
        ssm.mean, cohort.faces, cohort.landmarks, resolution, fibres=dict(snakemake.params.fibres)
    )
    log.info(
        "template: %d nodes (%d hex nodes), %d hexes, %d surface triangles, %d ligament springs (fibres per ligament "
        "%s), %d element sets",
        template.n_nodes,
        template.n_hex_nodes,
        len(template.hexes),
        len(template.tris),
        len(template.ligaments),
        template.meta.get("ligament_fibres", {}),
        len(template.elsets),
    )
    template.save(snakemake.output.npz)
    write_vtu(fe_model(template), snakemake.output.vtu, leave_out=NOT_ANATOMY)  # deck ids, no connector lines
