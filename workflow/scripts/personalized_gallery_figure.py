# Adapter: the first personalized hex models side by side (the seed's Figure 9).
import pandas as pd

from spinecohort.figures.models import personalized_gallery_figure
from spinecohort.logs import to_file
from spinecohort.mesh.hex_ssm import HexSSM
from spinecohort.mesh.template import HexTemplate

with to_file(snakemake.log[0]) as log:
    table = pd.read_csv(snakemake.input.table)
    try:
        ids = personalized_gallery_figure(
            HexSSM.load(snakemake.input.hex_ssm),
            HexTemplate.load(snakemake.input.template),
            table,
            snakemake.output[0],
            tuple(snakemake.params.size),
            dpi=snakemake.params.dpi,
            n_models=snakemake.params.n_models,
        )
    except ValueError as exc:
        raise ValueError(f"{snakemake.input.table}: {exc}") from exc
    log.info("gallery of %s", ", ".join(ids))
