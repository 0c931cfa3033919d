# Adapter: the validation model's extension without the ALL beside its intact extension (rule rom_all_effect).
import pandas as pd

from spinecohort.fe.calculix import find_ccx
from spinecohort.fe.export import read_deck_points
from spinecohort.fe.materials import materials_from_config
from spinecohort.logs import to_file
from spinecohort.mesh.template import HexTemplate
from spinecohort.rom.compare import all_effect
from spinecohort.rom.run import solve_model

with to_file(snakemake.log[0]) as log:
    find_ccx()
    template = HexTemplate.load(snakemake.input.template)
    points = read_deck_points(snakemake.input.deck, template)
    rom = {**snakemake.params.rom, "threads": min(int(snakemake.params.rom["threads"]), snakemake.threads)}
    free = solve_model(
        template,
        points,
        {**rom, "load_cases": ["extension"]},
        snakemake.output.runs,
        snakemake.params.model,
        materials_from_config(snakemake.params.fe),
        variants=("no_ALL",),
    )
    effect = all_effect(pd.concat([pd.read_csv(snakemake.input.table), free], ignore_index=True))
    effect.to_csv(snakemake.output.table, index=False)
    log.info("extension ROM with and without the ALL (deg):\n%s", effect.to_string())
