# Stage 6: per scenario and model variant, train (Ax-tuned) and track in MLflow.


rule train:
    input:
        manifest=P.manifest(),
        # the meshes only when the variant re-selects the ROI (model.roi_fraction: their surface graphs) or
        # observes the cases with a camera (roi_features: cloud: their surfaces)
        meshes=lambda wc: ([P.mesh(g) for g in PLAN.scenario_geometries(wc.scenario)]
                           if PLAN.variants()[wc.variant].get("roi_fraction") is not None
                           or PLAN.variants()[wc.variant].get("roi_features") == "cloud" else []),
    output:
        metrics=P.model_metrics(),
        model=directory(P.model_dir()),
    params:
        model=lambda wc: PLAN.variants()[wc.variant],
        train=PLAN.train_settings(),
        tune=config_slice("tune"),
        tracking_uri=TRACKING_URI,
        experiment_name=lambda wc: PLAN.experiment_name(wc.scenario),
        experiment=config_slice("experiment"),
        seed=PLAN.train_seed(),
    log:
        P.log("train", "{scenario}-{variant}"),
    conda:
        "../envs/liverforce.yaml"
    threads: 1
    resources:
        mem_mb=4000,
        runtime=120,
    script:
        "../scripts/train.py"


rule models:
    input:
        [P.model_metrics(s, v) for s in PLAN.train_scenarios() for v in PLAN.variants()],
