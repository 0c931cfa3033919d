# Adapter: the Descriptive_List workbook (sheet 1 the virtual cohort, sheet 2 the patients; units in the
# headers) and the virtual cohort's CSV and Parquet twins for queries.
import pandas as pd

from spinecohort.logs import to_file
from spinecohort.measure.tables import (
    tri_vs_hex_summary,
    virtual_cohort_table,
    with_personalization,
    write_descriptive_list,
    write_table_twins,
)

with to_file(snakemake.log[0]) as log:
    patients = pd.read_csv(snakemake.input.patients, dtype={"ID": str})
    patients = with_personalization(patients, pd.read_csv(snakemake.input.personalization, dtype={"ID": str}))
    virtual = virtual_cohort_table(
        [pd.read_csv(f) for f in snakemake.input.params], [pd.read_csv(f) for f in snakemake.input.quality]
    )
    write_descriptive_list(snakemake.output.workbook, patients=patients, virtual=virtual)
    written = write_table_twins(virtual, snakemake.output.virtual)
    diff = tri_vs_hex_summary([pd.read_csv(f) for f in snakemake.input.tri_vs_hex])
    diff.to_csv(snakemake.output.tri_vs_hex, index=False, float_format="%.6g")
    log.info(
        "virtual cohort: %d models (%s); %d with inverted hexes before repair, %d after",
        len(virtual),
        ", ".join(map(str, written)),
        int((virtual["invalid_before"] > 0).sum()),
        int((virtual["invalid_after"] > 0).sum()),
    )
