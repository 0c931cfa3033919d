# Adapter: transfer the SSM mode fields onto the morphed hex nodes; report inverted elements over the grid
# for both transfer methods (the configured one is saved).
import numpy as np
import pandas as pd

from spinecohort.cohort.loading import load_cohort_npz
from spinecohort.logs import to_file
from spinecohort.mesh.hex_ssm import inverted_over_grid, transfer_fields
from spinecohort.mesh.template import HexTemplate
from spinecohort.ssm.model import SSM
from spinecohort.store.zarr_store import grid_weights

with to_file(snakemake.log[0]) as log:
    template = HexTemplate.load(snakemake.input.template)
    ssm = SSM.load(snakemake.input.ssm)
    cohort = load_cohort_npz(snakemake.input.cohort)
    with np.load(snakemake.input.nodes) as z:
        mean_hex = z["nodes"]
    grid = snakemake.params.grid
    weights = grid_weights(grid["n_modes"], grid["levels"])
    rows, chosen = [], None
    h_min = snakemake.params.min_disc_height_mm
    for method in ("nearest", "smooth"):
        hssm = transfer_fields(template, mean_hex, ssm, cohort.landmarks, grid["n_modes"], method, h_min)
        stats = inverted_over_grid(hssm, template.hexes, weights)
        rows.append({"method": method, "disc_contact": "none", "models": len(weights), **stats})
        log.info("%s transfer: %s", method, stats)
        if h_min is not None:
            stats = inverted_over_grid(hssm, template.hexes, weights, contact=True)
            rows.append({"method": method, "disc_contact": f"min height {h_min} mm", "models": len(weights), **stats})
            log.info("%s transfer with disc contact (min height %s mm): %s", method, h_min, stats)
        if method == snakemake.params.transfer:
            chosen = hssm
    pd.DataFrame(rows).to_csv(snakemake.output.report, index=False)
    chosen.save(snakemake.output.ssm)
