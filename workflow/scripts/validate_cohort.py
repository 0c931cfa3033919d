# Adapter: read and validate the cohort (STL files + patient sheet + landmarks) into one .npz.
from spinecohort.cohort.loading import load_cohort, save_cohort
from spinecohort.logs import to_file

with to_file(snakemake.log[0]):
    cohort = load_cohort(
        list(snakemake.input.stls),
        snakemake.input.sheet,
        snakemake.input.landmarks,
        units=snakemake.params.units,
        degenerate_area_mm2=snakemake.params.degenerate_area_mm2,
        max_degenerate_fraction=snakemake.params.max_degenerate_fraction,
    )
    save_cohort(snakemake.output[0], cohort)
