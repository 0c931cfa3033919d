"""Stage 2 — the statistical shape model: Procrustes alignment, PCA, compactness/generalization/specificity."""
