# Adapter: generalization and specificity of the SSM, table and plot.
import numpy as np

from spinecohort.figures.ssm import quality_plot
from spinecohort.logs import to_file
from spinecohort.ssm.model import SSM
from spinecohort.ssm.quality import generalization, specificity

with to_file(snakemake.log[0]) as log:
    q = snakemake.params.quality
    with np.load(snakemake.input.aligned) as z:
        aligned = z["aligned"]
    ssm = SSM.load(snakemake.input.ssm)
    gen = generalization(aligned, q["max_modes"])
    spec = specificity(ssm, aligned, q["specificity_samples"], q["max_modes"], q["seed"])
    table = gen.merge(spec, on="modes")
    log.info("generalization / specificity (mm):\n%s", table.round(3).to_string(index=False))
    table.to_csv(snakemake.output.table, index=False)
    quality_plot(gen, spec, snakemake.output.figure)
