"""The virtual cohort stage: one job per shard samples, checks, repairs and measures its models and writes
them to the store (``spinecohort.store``), which knows nothing of the science above it."""
