# Adapter: generate the synthetic patient cohort into the STL-folder layout a user with real data provides.
from pathlib import Path

from spinecohort.cohort.loading import write_cohort_folder
from spinecohort.cohort.real import generate_real_cohort
from spinecohort.cohort.synthetic import generate_cohort
from spinecohort.logs import Progress, to_file

with to_file(snakemake.log[0]) as log:
    p = snakemake.params.synthetic
    progress = Progress("patients built", p["n_patients"])
    if snakemake.params.generator == "real":
        cohort = generate_real_cohort(p["n_patients"], seed=p["seed"], criteria=p["criteria"], progress=progress)
    else:
        cohort = generate_cohort(
            p["n_patients"],
            seed=p["seed"],
            resolution=p["resolution"],
            noise_mm=p["noise_mm"],
            criteria=p["criteria"],
            progress=progress,
        )
    log.info(
        "%d patients (%d candidates drawn), %d vertices and %d triangles each",
        len(cohort.ids),
        cohort.n_candidates,
        cohort.vertices.shape[1],
        len(cohort.faces),
    )
    write_cohort_folder(
        Path(snakemake.output.sheet).parent, cohort.ids, cohort.vertices, cohort.faces, cohort.landmarks, cohort.table
    )
