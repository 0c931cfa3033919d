# Adapter: transfer the SSM mode fields onto the morphed hex nodes; report inverted elements for both
# transfer methods (the configured one is saved) on a documented sample of the grid (report_sample: every
# k-th model ID). The exact count of the stored cohort is in the shards' quality tables (invalid_before),
# which check every model anyway: the report does not check the whole grid a second time.
import numpy as np
import pandas as pd

from spinecohort.cohort.loading import load_cohort_npz
from spinecohort.logs import to_file
from spinecohort.mesh.hex_ssm import inverted_over_grid, report_sample, transfer_fields
from spinecohort.mesh.template import HexTemplate
from spinecohort.ssm.model import SSM
from spinecohort.store.zarr_store import n_models, weights_of

with to_file(snakemake.log[0]) as log:
    template = HexTemplate.load(snakemake.input.template)
    ssm = SSM.load(snakemake.input.ssm)
    cohort = load_cohort_npz(snakemake.input.cohort).landmarks
    with np.load(snakemake.input.nodes) as z:
        mean_hex = z["nodes"]
    grid = snakemake.params.grid
    total = n_models(grid["n_modes"], grid["levels"])
    ids = report_sample(total, len(grid["levels"]))
    weights = weights_of(ids, grid["n_modes"], grid["levels"])
    step = int(ids[1] - ids[0]) if len(ids) > 1 else 1
    sample = f"every {step}-th model ID ({len(ids)} of {total})" if step > 1 else f"all {total} models"
    log.info("transfer report on %s", sample)
    rows, chosen = [], None
    h_min = snakemake.params.min_disc_height_mm
    for method in ("nearest", "smooth"):
        hssm = transfer_fields(template, mean_hex, ssm, cohort, grid["n_modes"], method, h_min)
        # the distraction is reported for the smooth transfer only (it is the one the cohort uses with it)
        with_contact = h_min is not None and method == "smooth"
        variants = [("none", False)] + ([(f"min height {h_min} mm", True)] if with_contact else [])
        for label, contact in variants:
            stats = inverted_over_grid(hssm, template.hexes, weights, contact=contact)
            rows.append({"method": method, "disc_contact": label, "models": len(weights), "sample": sample, **stats})
            log.info("%s transfer, disc contact %s: %s", method, label, stats)
        if method == snakemake.params.transfer:
            chosen = hssm
    pd.DataFrame(rows).to_csv(snakemake.output.report, index=False)
    chosen.save(snakemake.output.ssm)
