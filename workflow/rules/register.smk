# Stage 1 for a user folder of meshes without correspondence (cohort.layout per_patient or per_bone): the
# labeled reference registered onto every patient, one job per patient (spinecohort.cohort.register).


if config["cohort"]["source"] == "folder" and "inputs" in COHORT:

    rule reference_anatomy:
        output:
            reference=L.reference,
            landmarks=L.reference_landmarks,
        log:
            f"{LOGS}/reference_anatomy.log",
        benchmark:
            L.benchmark("reference_anatomy")
        conda:
            "../../environment.yml"
        threads: 1
        params:
            register=config["register"],
        script:
            "../scripts/reference_anatomy.py"

    rule register_patient:
        input:
            patient=lambda wc: COHORT["inputs"][wc.patient],
            reference=L.reference,
        output:
            stl=L.registered_stl("{patient}"),
            report=L.registered_report("{patient}"),
        log:
            f"{LOGS}/register_patient/{{patient}}.log",
        benchmark:
            L.benchmark("register_patient", "{patient}")
        wildcard_constraints:
            patient="|".join(COHORT["inputs"]),
        conda:
            "../../environment.yml"
        threads: 1
        params:
            layout=cohort_layout(config),
            units=config["cohort"]["units"],
            register=config["register"],
        script:
            "../scripts/register_patient.py"

    rule registration_report:
        input:
            [L.registered_report(pid) for pid in COHORT["inputs"]],
        output:
            L.registration_report,
        log:
            f"{LOGS}/registration_report.log",
        benchmark:
            L.benchmark("registration_report")
        conda:
            "../../environment.yml"
        threads: 1
        script:
            "../scripts/registration_report.py"
