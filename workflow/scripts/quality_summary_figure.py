# Adapter: mesh-quality summary of the virtual cohort (shard quality tables) and Table 3 of the mean model.
import pandas as pd

from spinecohort.figures.cohort import quality_summary_figure
from spinecohort.logs import to_file

with to_file(snakemake.log[0]) as log:
    quality = pd.concat([pd.read_csv(p) for p in snakemake.input.shards], ignore_index=True)
    table3 = pd.read_csv(snakemake.input.table3)
    quality_summary_figure(quality, table3, snakemake.output[0], tuple(snakemake.params.size), dpi=snakemake.params.dpi)
    log.info(
        "%d models from %d shards; %d with inverted hexes before repair, %d after",
        len(quality),
        len(snakemake.input.shards),
        (quality["invalid_before"] > 0).sum(),
        (quality["invalid_after"] > 0).sum(),
    )
