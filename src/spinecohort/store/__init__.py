"""The virtual cohort's sharded Zarr v3 store: its format, the streaming shard writer, the readers and the
integrity check (``zarr_store`` is the public API in one import).  Imports nothing else of spinecohort; the
per-shard job that fills it is ``spinecohort.virtual``."""
