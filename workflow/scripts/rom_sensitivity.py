# Adapter: each calibrated parameter at the ends of its published range -> change of every compared ROM.
import pandas as pd

from spinecohort.fe.calculix import find_ccx
from spinecohort.fe.export import read_deck_points
from spinecohort.figures.rom import rom_sensitivity_figure
from spinecohort.layout import Layout
from spinecohort.logs import to_file
from spinecohort.mesh.template import HexTemplate
from spinecohort.rom.sensitivity import sensitivity

with to_file(snakemake.log[0]) as log:
    find_ccx()
    template = HexTemplate.load(snakemake.input.template)
    points = read_deck_points(snakemake.input.deck, template)
    rom = {**snakemake.params.rom, "threads": min(int(snakemake.params.rom["threads"]), snakemake.threads)}
    cfg = {"fe": snakemake.params.fe, "rom": rom}
    # the variants' runs are a cache, not an output (Snakemake would empty an output directory before every rerun):
    # a variant is solved again only when its mesh or solver settings change (rom.sensitivity.variant_key)
    runs = Layout(snakemake.config["results"]).rom_sensitivity_dir
    table = sensitivity(template, points, cfg, runs, snakemake.params.model)
    table.to_csv(snakemake.output.table, index=False)
    rom_sensitivity_figure(table, snakemake.output.figure)
    with pd.option_context("display.width", 200):
        log.info(
            "change of ROM (deg):\n%s",
            table.pivot_table(index=["parameter", "level"], columns=["segment", "motion"], values="change_deg").round(
                2
            ),
        )
