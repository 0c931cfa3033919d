"""Stage 4 — the virtual cohort store: the sharded Zarr v3 store and the per-shard pipeline."""
