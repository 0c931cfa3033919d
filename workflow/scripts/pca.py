# Adapter: PCA of the aligned shapes, compactness table and plot.
import numpy as np

from spinecohort.atomic import atomic_write
from spinecohort.figures.ssm import compactness_plot
from spinecohort.logs import to_file
from spinecohort.ssm.model import build_ssm
from spinecohort.ssm.quality import compactness_table

with to_file(snakemake.log[0]) as log:
    with np.load(snakemake.input[0]) as z:
        aligned = z["aligned"]
    ssm = build_ssm(aligned)
    threshold = snakemake.params.variance_threshold
    n = ssm.modes_for_variance(threshold)
    log.info(
        "%d modes; %d explain %.1f %% of the variance (first 5: %s %%)",
        ssm.n_modes,
        n,
        100 * ssm.cumulative_variance[n - 1],
        np.round(100 * ssm.explained_variance_ratio[:5], 1),
    )
    with atomic_write(snakemake.output.ssm) as tmp, open(tmp, "wb") as fh:
        ssm.save(fh, modes_for_threshold=n, variance_threshold=threshold)
    table = compactness_table(ssm)
    table.to_csv(snakemake.output.table, index=False)
    compactness_plot(table, threshold, snakemake.output.figure)
