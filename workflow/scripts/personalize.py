# Adapter: personalized models of every patient (fit to its parameters, and projection of its aligned
# shape), the fit models' .inp decks (Jacobian-checked and repaired), the table and the report.
import json
from pathlib import Path

import numpy as np
import pandas as pd

from spinecohort.atomic import atomic_write
from spinecohort.cohort.loading import load_cohort_npz
from spinecohort.fe.export import fe_model, write_deck
from spinecohort.fe.materials import materials_from_config
from spinecohort.logs import to_file
from spinecohort.mesh.hex_ssm import HexSSM
from spinecohort.mesh.template import HexTemplate
from spinecohort.personalize.cohort import Settings, personalize_cohort, personalized_hex
from spinecohort.personalize.report import report_markdown
from spinecohort.ssm.model import SSM

with to_file(snakemake.log[0]) as log:
    settings = Settings.from_config(snakemake.params.settings, snakemake.params.grid_modes)
    m = snakemake.params.measure
    measure_kw = {"vertical": m["vertical_axis"], "c7_proxy": m["c7_proxy"]}
    cohort = load_cohort_npz(snakemake.input.cohort)
    with np.load(snakemake.input.aligned) as z:
        aligned_ids = [str(s) for s in z["ids"]]
        aligned = z["aligned"]
    if aligned_ids != cohort.ids:
        raise ValueError(f"{snakemake.input.aligned}: patient order differs from {snakemake.input.cohort}")
    targets = pd.read_csv(snakemake.input.parameters, dtype={"ID": str})
    ssm = SSM.load(snakemake.input.ssm)
    table, info = personalize_cohort(ssm, cohort.landmarks, cohort.ids, targets, aligned, settings, measure_kw)

    template = HexTemplate.load(snakemake.input.template)
    hex_ssm = HexSSM.load(snakemake.input.hex_ssm)
    out = {Path(p).stem: p for p in snakemake.output.models}
    missing = sorted(set(out) - set(cohort.ids))
    if missing:
        raise ValueError(f"no patient for the requested models {', '.join(missing)}")
    k = settings.n_modes
    materials = materials_from_config(snakemake.params.fe)  # the cohort's decks' materials
    checks = []
    for _, row in table[table.method == "fit"].iterrows():  # one FE model per patient
        w = row[[f"b{j + 1}" for j in range(k)]].to_numpy(float)
        pts, rep = personalized_hex(template, hex_ssm, w, row["posture_deg"], name=f"patient {row['ID']}")
        heading = (
            f"spinecohort personalized model of patient {row['ID']}: weights (SD) {np.round(w, 4).tolist()}, "
            f"posture {row['posture_deg']:.3f} deg"
        )
        if row["ID"] in out:
            write_deck(
                fe_model(template, pts, hex_type=snakemake.params.hex_type, heading=heading, materials=materials),
                out[row["ID"]],
                provenance=heading,
            )
        checks.append(
            {
                "ID": row["ID"],
                "method": "fit",
                **{
                    c: rep[c]
                    for c in ("invalid_before", "invalid_after", "min_sj_before", "min_sj_after", "nodes_moved")
                },
                "distraction_mm": rep.get("distraction_mm", 0.0),
            }
        )  # disc opening of the hex SSM's contact map
        log.info("%s: Jacobian check %s", row["ID"], {c: v for c, v in rep.items() if c != "level_offsets_mm"})
    table = table.merge(pd.DataFrame(checks), on=["ID", "method"], how="left")
    with atomic_write(snakemake.output.table) as tmp:
        table.to_csv(tmp, index=False, float_format="%.6f")
    Path(snakemake.output.report).write_text(report_markdown(table, info))
    Path(snakemake.output.info).write_text(json.dumps(info, indent=1))
    log.info("personalized %d patients:\n%s", info["n_patients"], Path(snakemake.output.report).read_text())
