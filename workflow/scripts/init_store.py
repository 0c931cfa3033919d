# Adapter: create the empty virtual-cohort store (results/cohort.zarr) with the SSM checksums and the grid.
from pathlib import Path

import numpy as np

from spinecohort.logs import to_file
from spinecohort.store.zarr_store import create_store, file_sha256

with to_file(snakemake.log[0]) as log:
    grid, settings = snakemake.params.grid, snakemake.params.store
    with np.load(snakemake.input.ssm) as z:
        n_tri = z["mean"].shape[0]
    with np.load(snakemake.input.hex_ssm) as z:
        n_hex = z["mean"].shape[0]
    with np.load(snakemake.input.template) as z:  # the hex nodes that are tri vertices: stored once
        surface_vertex = z["surface_vertex"]
    path = Path(snakemake.output[0]).parent
    attrs = {
        "ssm_sha256": file_sha256(snakemake.input.ssm),
        "hex_ssm_sha256": file_sha256(snakemake.input.hex_ssm),
        "grid": grid,
        "units": "mm",
    }
    root = create_store(
        path,
        n_tri,
        n_hex,
        grid["n_modes"],
        grid["levels"],
        settings["shard_models"],
        attrs=attrs,
        encoding=settings["encoding"],
        chunk_models=settings["chunk_models"],
        overwrite=True,
        surface_vertex=surface_vertex,
    )
    log.info(
        "%s: %d models x (%d tri + %d hex nodes, %d of them stored once as tri vertices) in %d shards of %d, "
        "encoding %s (error bound %.2g mm)",
        path,
        root.attrs["n_models"],
        n_tri,
        n_hex,
        len(surface_vertex),
        root.attrs["n_shards"],
        settings["shard_models"],
        settings["encoding"],
        root.attrs["error_bound_mm"],
    )
    Path(snakemake.output[0]).write_text("created by init_store\n")
