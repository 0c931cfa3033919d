# Adapter: morph the template onto the SSM mean (multilayer BCPD), report distances per part.
import numpy as np

from spinecohort.cohort.loading import load_cohort_npz
from spinecohort.fe.export import NOT_ANATOMY, fe_model
from spinecohort.fe.writers import write_vtu
from spinecohort.logs import Progress, to_file
from spinecohort.mesh.morph import MorphParameters, morph_template
from spinecohort.mesh.quality.verdict import scaled_jacobian
from spinecohort.mesh.template import HexTemplate
from spinecohort.ssm.model import SSM

with to_file(snakemake.log[0]) as log:
    template = HexTemplate.load(snakemake.input.template)
    ssm = SSM.load(snakemake.input.ssm)
    cohort = load_cohort_npz(snakemake.input.cohort)
    nodes, report = morph_template(
        template,
        ssm.mean,
        cohort.faces,
        cohort.landmarks,
        MorphParameters(**snakemake.params.morph),
        progress=Progress("parts morphed", 18),
    )
    sj = scaled_jacobian(nodes, template.hexes)
    n_bad = int((sj <= 0).sum())
    log.info("morphed mean: min scaled Jacobian %.3f, %d inverted of %d hexes", sj.min(), n_bad, len(sj))
    if n_bad:
        raise RuntimeError(f"the morphed mean has {n_bad} inverted hexes (min scaled Jacobian {sj.min():.3f})")
    report.to_csv(snakemake.output.report, index=False)
    np.savez(snakemake.output.nodes, nodes=nodes, min_scaled_jacobian=sj.min())
    write_vtu(fe_model(template, nodes), snakemake.output.vtu, leave_out=NOT_ANATOMY)  # deck ids, no connector lines
