# Adapter: the Descriptive_List workbook (units in the headers).
import pandas as pd

from spinecohort.logs import to_file
from spinecohort.tables import write_descriptive_list

with to_file(snakemake.log[0]):
    patients = pd.read_csv(snakemake.input.patients, dtype={"ID": str})
    write_descriptive_list(snakemake.output[0], patients=patients)
