# Adapter: build, verify and publish the release bag (spinecohort.release; docs/howto/release.md).
import io
from pathlib import Path

import numpy as np

from spinecohort.cohort.loading import load_cohort_npz
from spinecohort.logs import to_file
from spinecohort.release import build_release, payload_layout, release_counts

with to_file(snakemake.log[0]) as log:
    inp, par = snakemake.input, snakemake.params
    # the bag folder holds the rule's output (its tag manifest); results is the bag's parent (release.smk)
    bag = Path(snakemake.output[0]).parent
    store = Path(inp.store).parent  # the store's .initialized marker
    files = payload_layout(
        bag.parent,
        template_inp=inp.template_inp,
        workbook=inp.workbook,
        virtual_csv=inp.virtual,
        patient_table=inp.patient_table,
        patients=list(inp.patients),
        personalized=list(inp.personalized),
        figures=list(inp.figures),
        model_inputs={"ssm.npz": inp.ssm, "hex_ssm.npz": inp.hex_ssm, "template.npz": inp.template},
    )
    faces = io.BytesIO()  # triangles of the patient/SSM surfaces: what `export --format stl` needs
    np.save(faces, load_cohort_npz(inp.cohort).faces)
    counts = release_counts(
        store,
        inp.template,
        n_patients=len(inp.patients),
        n_personalized=len(inp.personalized),
        n_figures=len(inp.figures),
        hex_type=par.hex_type,
    )
    summary = build_release(
        bag,
        store=store,
        files=files,
        meta=par.release,
        counts=counts,
        generated={"model_inputs/faces.npy": faces.getvalue()},
        model_settings={"fe": par.fe},
        processes=snakemake.threads,
    )
    log.info(
        "release %s: %d files, %.1f MB (store zip %.1f MB); payload %.1f s, bag %.1f s, verify %.1f s",
        bag,
        summary["files"],
        summary["bytes"] / 1e6,
        summary["store_bytes"] / 1e6,
        summary["seconds_payload"],
        summary["seconds_bag"],
        summary["seconds_verify"],
    )
