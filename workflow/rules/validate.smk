# Stage 7: the chosen scenario-IV model on the unseen liver with unseen constants.


rule validate:
    input:
        # every scenario-IV variant (validate.variant=auto picks by cross-validation score) or the one named
        model=needs_iv("the unseen-liver validation (rule validate, which the report and the default target need)",
                       [P.model_dir("IV", v) for v in PLAN.variants()]),
        metrics=[P.model_metrics("IV", v) for v in PLAN.variants()],
        manifest=P.manifest(plan.VALIDATION),
        train_manifest=P.manifest("IV"),
        # camera-cloud variants observe the unseen livers' surfaces: their meshes
        meshes=([P.mesh(g) for g in PLAN.scenario_geometries(plan.VALIDATION)]
                if any(v.get("roi_features") == "cloud" for v in PLAN.variants().values()) else []),
    output:
        metrics=P.validation_metrics(),
    params:
        tracking_uri=TRACKING_URI,
        variant=config_slice("validate", "variant"),
        input=config_slice("validate", "input"),
        sensitivity=config_slice("validate", "camera_sensitivity"),
        registration_errors=config_slice("validate", "registration_errors"),
        shape_changes=config_slice("validate", "shape_changes"),
        experiment_name=PLAN.experiment_name("validation"),
    log:
        P.log("validate", "validate"),
    conda:
        "../envs/liverforce.yaml"
    threads: 1
    resources:
        mem_mb=2000,
        runtime=10,
    script:
        "../scripts/validate.py"
