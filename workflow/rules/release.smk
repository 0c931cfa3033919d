# Stage 10: the release, a verified BagIt bag of everything a data user downloads (docs/howto/release.md).
from spinecohort.release import release_dir

# schema-checked as a plain name; release_dir checks again, so no config value can put the bag outside R
RELEASE_DIR = str(release_dir(R, config["release"]["dir"]))
# the bag's last-written tag file is the rule's output: a bag without it is incomplete, and Snakemake
# adds no bookkeeping file inside the bag (as it would for a directory() output)
RELEASE_BAG = f"{RELEASE_DIR}/tagmanifest-sha256.txt"
# its inputs: release_inputs() in common.smk


rule release:
    input:
        unpack(release_inputs),
    output:
        RELEASE_BAG,
    log:
        f"{LOGS}/release.log",
    benchmark:
        L.benchmark("release")
    conda:
        "../../environment.yml"
    threads: 2
    params:
        release=config["release"],
        hex_type=config["template"]["hex_type"],
        fe=config.get("fe"),  # materials of the decks: `export --release` writes the same decks
    script:
        "../scripts/release.py"
