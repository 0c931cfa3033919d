# Adapter: render the first modes at -3, 0, +3 SD.
import numpy as np

from spinecohort.figures.ssm import mode_variation_figure
from spinecohort.logs import to_file
from spinecohort.ssm.model import SSM

with to_file(snakemake.log[0]):
    with np.load(snakemake.input.cohort) as z:
        faces = z["faces"]
    mode_variation_figure(
        SSM.load(snakemake.input.ssm),
        faces,
        snakemake.output[0],
        snakemake.params.n_modes,
        tuple(snakemake.params.window),
        dpi=snakemake.params.dpi,
    )
