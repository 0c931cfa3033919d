# Adapter: check that no two neighbouring bones of any patient of the real-bone cohort cross; table per pair.
from spinecohort.anatomy.contacts import cohort_contacts
from spinecohort.anatomy.reference import load_reference
from spinecohort.cohort.loading import load_cohort_npz
from spinecohort.cohort.real import first_use_reference
from spinecohort.logs import to_file

with to_file(snakemake.log[0]) as log:
    cohort = load_cohort_npz(snakemake.input[0])
    ref = first_use_reference(load_reference())
    table = cohort_contacts(cohort.points, cohort.faces, ref.level, ref.region)
    table.to_csv(snakemake.output[0], index_label="pair")
    log.info("neighbouring bones of %d patients:\n%s", len(cohort.ids), table)
    crossing = table.index[table["patients_crossing"] > 0].tolist()
    if crossing:
        raise RuntimeError(f"bones cross in the cohort: {crossing} (see {snakemake.output[0]})")
