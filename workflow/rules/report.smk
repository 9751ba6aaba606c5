# Stage 8: one human-readable summary of the run (needs the comparison studies too).


rule report:
    input:
        models=[P.model_metrics(s, v) for s in PLAN.train_scenarios() for v in PLAN.variants()],
        manifests=[P.manifest(s) for s in PLAN.all_scenarios()],
        validation=P.validation_metrics(),
        physics=[P.physics()] if config_slice("validate", "physics", "enabled") else [],
        features=[P.features(g) for g in PLAN.all_geometries],
        pictures=[P.regions_picture(g) for g in PLAN.all_geometries],
        surfaces=[P.surface(g) for g in PLAN.all_geometries],
        studies=[P.study(s) for s in STUDY_NAMES],
    output:
        html=P.report(),
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
            "regressors": {v["name"]: v.get("regressor", config_slice("model")["regressor"])
                           for v in config_slice("train")["variants"]},
            "tracking": config_slice("tracking"),
            "tracking_uri": TRACKING_URI,
            "mlflow_experiments": {"models": PLAN.experiment_name("<scenario>"),
                                   "validation": PLAN.experiment_name("validation"),
                                   "studies": PLAN.experiment_name("studies")},
            # imported livers' own constants (geometry.imported[].material); absent without them, so a run
            # without such livers keeps its report params (and is not re-rendered after a pull)
            **({"liver_materials": PLAN.liver_materials()} if PLAN.liver_materials() else {}),
            "population": {
                "training": PLAN.train_geometries,
                "single": PLAN.single_geometry,  # the liver of scenarios I-III
                "unseen": PLAN.validation_geometries,
                "volume_range_l": config_slice("geometry", "procedural", "shape").get("volume_range_l"),
            },
        },
    log:
        P.log("report", "report"),
    conda:
        "../envs/liverforce.yaml"
    threads: 1
    resources:
        mem_mb=2000,
        runtime=10,
    script:
        "../scripts/report.py"
