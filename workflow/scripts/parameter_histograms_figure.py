# Adapter: histograms of the virtual cohort's parameters with the patients and the inclusion thresholds.
import pandas as pd

from spinecohort.figures.cohort import parameter_histograms_figure
from spinecohort.logs import to_file

with to_file(snakemake.log[0]) as log:
    tables = {}
    for key in ("virtual", "patients"):
        path = snakemake.input[key]
        try:
            tables[key] = pd.read_csv(path)
        except Exception as exc:
            raise ValueError(f"{path}: cannot read the parameter table ({exc})") from exc
    shares = parameter_histograms_figure(
        tables["virtual"],
        tables["patients"],
        dict(snakemake.params.criteria),
        list(snakemake.params.parameters),
        snakemake.output[0],
        tuple(snakemake.params.size),
        dpi=snakemake.params.dpi,
    )
    log.info("share above each inclusion threshold:\n%s", shares.to_string(index=False))
