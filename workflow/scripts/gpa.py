# Adapter: generalized Procrustes alignment of the cohort.
import numpy as np

from spinecohort.atomic import atomic_write
from spinecohort.cohort.loading import load_cohort_npz
from spinecohort.logs import to_file
from spinecohort.ssm.procrustes import procrustes_align

with to_file(snakemake.log[0]):
    cohort = load_cohort_npz(snakemake.input[0])
    res = procrustes_align(
        cohort.points,
        scaling=snakemake.params.scaling,
        tol_mm=snakemake.params.tol_mm,
        max_iter=snakemake.params.max_iter,
    )
    with atomic_write(snakemake.output[0]) as tmp, open(tmp, "wb") as fh:
        np.savez(
            fh,
            ids=np.array(cohort.ids),
            aligned=res.aligned,
            mean=res.mean,
            rotations=res.rotations,
            scales=res.scales,
            translations=res.translations,
            mean_change_mm=np.array(res.mean_change_mm),
        )
