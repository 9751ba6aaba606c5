# Stage 8: one human-readable summary of the run (needs the comparison studies too).


rule report:
    input:
        models=expand(f"{E}/models/{{scenario}}/{{variant}}/metrics.json", scenario=PLAN.train_scenarios(), variant=list(PLAN.variants())),
        manifests=expand(f"{E}/shards/{{scenario}}/manifest.json", scenario=PLAN.all_scenarios()),
        validation=f"{E}/validate/metrics.json",
        features=expand(f"{E}/mesh/{{gid}}.features.json", gid=PLAN.all_geometries),
        pictures=expand(f"{E}/mesh/{{gid}}.regions.png", gid=PLAN.all_geometries),
        surfaces=expand(f"{E}/geometry/{{gid}}.ply", gid=PLAN.all_geometries),
        studies=expand(f"{E}/studies/{{study}}.json", study=STUDY_NAMES),
    output:
        html=f"{E}/report/index.html",
    params:
        experiment=config_slice("experiment"),
        setup={
            "main_variant": PLAN.chosen_variant(),
            "material": config_slice("material"),
            "boundary": config_slice("boundary"),
            "sweep": config_slice("sweep"),
            "mesh": config_slice("mesh"),
            "dataset": config_slice("dataset"),
            "validate": config_slice("validate"),
            "train": {k: v for k, v in config_slice("train").items() if k != "variants"},
            "tune": {k: v for k, v in config_slice("tune").items() if k != "space"},
            "tracking": config_slice("tracking"),
            "tracking_uri": TRACKING_URI,
            "population": {
                "training": PLAN.train_geometries,
                "unseen": PLAN.validation_geometries,
                "volume_range_l": config_slice("geometry", "procedural", "shape").get("volume_range_l"),
            },
        },
    log:
        f"{E}/logs/report/report.log",
    conda:
        "../envs/liverforce.yaml"
    threads: 1
    resources:
        mem_mb=2000,
        runtime=10,
    script:
        "../scripts/report.py"
