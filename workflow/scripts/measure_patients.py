# Adapter: measure every patient of the cohort; compare with the patient sheet's own values.
from spinecohort.cohort.loading import load_cohort_npz
from spinecohort.logs import to_file
from spinecohort.measure.spinopelvic import measure
from spinecohort.measure.tables import compare_with_sheet

with to_file(snakemake.log[0]) as log:
    cohort = load_cohort_npz(snakemake.input[0])
    p = snakemake.params.measure
    age = cohort.table["age"].to_numpy(float) if "age" in cohort.table else None
    table = measure(
        cohort.points,
        cohort.landmarks,
        vertical=p["vertical_axis"],
        age=age,
        assumed_age=p["assumed_age"],
        c7_proxy=p["c7_proxy"],
    )
    table.insert(0, "ID", cohort.ids)
    for k, col in enumerate(c for c in ("age", "sex") if c in cohort.table):
        table.insert(1 + k, col, cohort.table[col].to_numpy())
    table.to_csv(snakemake.output.table, index=False, float_format="%.6f")
    comparison = compare_with_sheet(table, cohort.table)
    comparison.to_csv(snakemake.output.comparison, index=False, float_format="%.6g")
    log.info(
        "measured %d patients; largest |sheet - measured| per parameter:\n%s",
        len(table),
        comparison.to_string(index=False),
    )
