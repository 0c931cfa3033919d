# Adapter: the model's ROM against the in-vitro references (table + the seed's Figures 10-11 as one figure).
import pandas as pd

from spinecohort.logs import to_file
from spinecohort.rom.analysis import all_effect, validate, validation_figure

with to_file(snakemake.log[0]) as log:
    rom = snakemake.params.rom
    table = pd.read_csv(snakemake.input[0])
    val = validate(table, rom["references"], rom["moment_nmm"], rom["acceptance_sd"])
    val.to_csv(snakemake.output.table, index=False)
    all_effect(table).to_csv(snakemake.output.all_effect, index=False)
    validation_figure(val, snakemake.output.figure, title=snakemake.params.model)
    log.info(
        "validation:\n%s",
        val[
            ["segment", "motion", "side", "mode", "model_deg", "accept_low", "accept_high", "in_range", "distance_deg"]
        ].to_string(),
    )
