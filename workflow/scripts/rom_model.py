# Adapter: the range of motion of one model (its exported .inp) for every configured extraction and load case,
# and its nucleus pressures and facet forces per case where the rule asks for them (rule rom_model).

from spinecohort.fe.calculix import find_ccx
from spinecohort.fe.export import read_deck_points
from spinecohort.fe.materials import materials_from_config
from spinecohort.logs import to_file
from spinecohort.mesh.template import HexTemplate
from spinecohort.rom.run import solve_model_loads

with to_file(snakemake.log[0]) as log:
    find_ccx()  # a clear error naming the Debian package before any work
    template = HexTemplate.load(snakemake.input.template)
    points = read_deck_points(snakemake.input.deck, template)  # the extraction rebuilds the facet nodes
    # at most as many parallel ccx runs as the scheduler gave this job (--set-threads, --cores)
    rom = {**snakemake.params.rom, "threads": min(int(snakemake.params.rom["threads"]), snakemake.threads)}
    table, idp, facets = solve_model_loads(
        template,
        points,
        rom,
        snakemake.output.runs,
        snakemake.wildcards.model_id,
        materials_from_config(snakemake.params.fe),
        load_prints="idp" in snakemake.output.keys(),  # the mode study's rule keeps the ROM only
    )
    table.to_csv(snakemake.output.table, index=False)
    if "idp" in snakemake.output.keys():
        idp.to_csv(snakemake.output.idp, index=False)
        facets.to_csv(snakemake.output.facets, index=False)
    log.info("ROM (deg):\n%s", table[["mode", "variant", "segment", "load_case", "rom_deg", "solve_s"]].to_string())
    log.info("nucleus pressure (MPa):\n%s\nfacet force (N):\n%s", idp.to_string(), facets.to_string())
