# Adapter: every patient's registration report in one table (surface distances per bone, both ways, mm).
import pandas as pd

from spinecohort.logs import to_file

with to_file(snakemake.log[0]) as log:
    table = pd.concat([pd.read_csv(p) for p in snakemake.input], ignore_index=True)
    table.to_csv(snakemake.output[0], index=False, float_format="%.4f")
    worst = table.loc[table["mean_mm"].idxmax()]
    log.info(
        "%d patients, %d bones: mean surface distance %.3f mm (worst %s of %s, %.3f mm)",
        table["patient"].nunique(),
        len(table),
        table["mean_mm"].mean(),
        worst["bone"],
        worst["patient"],
        worst["mean_mm"],
    )
