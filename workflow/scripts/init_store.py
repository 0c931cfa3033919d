# Adapter: create the empty virtual-cohort store (results/cohort.zarr) with the SSM checksums and the grid.
from pathlib import Path

from spinecohort.logs import to_file
from spinecohort.store.zarr_store import create_store_for_run, file_sha256

with to_file(snakemake.log[0]) as log:
    grid, settings = snakemake.params.grid, snakemake.params.store
    path = Path(snakemake.output[0]).parent
    attrs = {
        "ssm_sha256": file_sha256(snakemake.input.ssm),
        "hex_ssm_sha256": file_sha256(snakemake.input.hex_ssm),
        "grid": grid,
        "units": "mm",
    }
    inputs = snakemake.input
    root = create_store_for_run(
        path, inputs.ssm, inputs.hex_ssm, inputs.template, grid, settings, attrs=attrs, overwrite=True
    )
    n_tri, n_hex = root["tri/points"].shape[1], root.attrs["n_hex_nodes"]
    log.info(
        "%s: %d models x (%d tri + %d hex nodes, %d of them stored once as tri vertices) in %d shards of %d, "
        "encoding %s (error bound %.2g mm)",
        path,
        root.attrs["n_models"],
        n_tri,
        n_hex,
        root["hex/surface_vertex"].shape[0],
        root.attrs["n_shards"],
        settings["shard_models"],
        settings["encoding"],
        root.attrs["error_bound_mm"],
    )
    Path(snakemake.output[0]).write_text("created by init_store\n")
