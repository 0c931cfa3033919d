"""Stage 1 — the patient cohort: synthetic generator, STL I/O, landmarks, loading and validation."""
