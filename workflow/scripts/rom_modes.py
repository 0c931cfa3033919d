# Adapter: the ROM tables of the mean and of each shape mode at its extremes -> modes.csv + figure.
import pandas as pd

from spinecohort.figures.rom import rom_modes_figure
from spinecohort.logs import to_file
from spinecohort.rom.modes import gather, summary

with to_file(snakemake.log[0]) as log:
    models = pd.DataFrame(snakemake.params.models)
    tables = [pd.read_csv(p) for p in snakemake.input.tables]
    cpu = [float(pd.read_csv(p, sep="\t")["cpu_time"].iloc[0]) for p in snakemake.input.benchmarks]
    modes = gather(models, tables, cpu)
    modes.to_csv(snakemake.output.table, index=False)
    rom_modes_figure(modes, snakemake.output.figure)
    s = summary(modes)
    log.info("per model:\n%s\ntotal CPU %.0f s, solve %.0f s", s.to_string(), s["cpu_s"].sum(), s["solve_s"].sum())
