# Adapter: one resolution of the mesh-convergence study: the template built and morphed onto the SSM mean as rules
# hex_template and morph_template do, its functional units solved under the validation's pure moments.
import pandas as pd

from spinecohort.cohort.loading import load_cohort_npz
from spinecohort.fe.calculix import find_ccx
from spinecohort.fe.materials import materials_from_config
from spinecohort.logs import to_file
from spinecohort.mesh.ligament_sites import fibres_per_ligament
from spinecohort.mesh.morph import MorphParameters
from spinecohort.rom.convergence import morphed_template, solve_resolution
from spinecohort.ssm.model import SSM

with to_file(snakemake.log[0]) as log:
    find_ccx()
    resolution = snakemake.wildcards.resolution
    ssm = SSM.load(snakemake.input.ssm)
    cohort = load_cohort_npz(snakemake.input.cohort)
    template, nodes, mesh = morphed_template(
        resolution,
        ssm.mean,
        cohort.faces,
        cohort.landmarks,
        MorphParameters(**snakemake.params.morph),
        snakemake.params.cep_diameter_fraction,
        fibres_per_ligament(snakemake.params.fe["ligaments"]),
    )
    # at most as many parallel ccx runs as the scheduler gave this job (--set-threads, --cores)
    rom = {**snakemake.params.rom, "threads": min(int(snakemake.params.rom["threads"]), snakemake.threads)}
    table = solve_resolution(
        template,
        nodes,
        rom,
        snakemake.params.units,
        snakemake.params.load_cases,
        snakemake.output.runs,
        materials_from_config(snakemake.params.fe),
        f"mean_{resolution}",
    )
    table = pd.concat([pd.DataFrame([mesh] * len(table)), table], axis=1)
    table.to_csv(snakemake.output.table, index=False)
    log.info(
        "ROM (deg):\n%s", table[["unit", "load_case", "rom_deg", "load_fraction", "solve_s", "peak_rss_mb"]].to_string()
    )
