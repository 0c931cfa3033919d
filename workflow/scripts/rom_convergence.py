# Adapter: the mesh-convergence table of the ROM (the resolutions' tables joined, changes to the next finer
# resolution, the verdict on the default one), its Markdown summary and figure.
import pandas as pd

from spinecohort.figures.convergence import convergence_figure
from spinecohort.logs import to_file
from spinecohort.rom.convergence import ConvergenceStudy, convergence_markdown, convergence_table, verdict

with to_file(snakemake.log[0]) as log:
    study = ConvergenceStudy.from_config(snakemake.params.study)
    default, finer = study.judged_pair(snakemake.params.default)
    rom = pd.concat([pd.read_csv(p) for p in snakemake.input.tables], ignore_index=True)
    table = convergence_table(rom, list(study.resolutions), default, study.max_change)
    table.to_csv(snakemake.output.table, index=False)
    with open(snakemake.output.markdown, "w") as f:
        f.write(convergence_markdown(table, default, finer, study.max_change))
    convergence_figure(table, default, study.max_change, snakemake.output.figure)
    log.info(
        "mesh convergence (%s vs %s): %s\n%s",
        default,
        finer,
        "converged" if verdict(table) else "NOT converged",
        table[["resolution", "unit", "load_case", "rom_deg", "change_to_finer", "converged"]].to_string(),
    )
