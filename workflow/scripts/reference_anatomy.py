# Adapter: the labeled reference (points, faces, bone per vertex, landmarks) every user patient is registered to.
from spinecohort.atomic import atomic_write
from spinecohort.cohort.register import real_reference, synthetic_reference
from spinecohort.logs import to_file

with to_file(snakemake.log[0]) as log:
    p = snakemake.params.register
    real = p["reference"] == "real"
    ref = real_reference() if real else synthetic_reference(p["reference_resolution"])
    log.info(
        "reference %s%s: %d vertices, %d triangles, %d landmark sites",
        p["reference"],
        "" if real else f" ({p['reference_resolution']})",
        len(ref.points),
        len(ref.faces),
        len(ref.landmarks.sites),
    )
    with atomic_write(snakemake.output.reference) as tmp, open(tmp, "wb") as fh:
        ref.save(fh)
    ref.landmarks.save(snakemake.output.landmarks)
