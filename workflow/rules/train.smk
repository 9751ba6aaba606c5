# Stage 6: per scenario and model variant, train (Ax-tuned) and track in MLflow.


rule train:
    input:
        manifest=f"{E}/shards/{{scenario}}/manifest.json",
        # the meshes only when the variant re-selects the ROI (model.roi_fraction): their surface graphs
        meshes=lambda wc: (expand(f"{E}/mesh/{{gid}}.vtu", gid=PLAN.scenario_geometries(wc.scenario))
                           if PLAN.variants()[wc.variant].get("roi_fraction") is not None else []),
    output:
        metrics=f"{E}/models/{{scenario}}/{{variant}}/metrics.json",
        model=directory(f"{E}/models/{{scenario}}/{{variant}}/model"),
    params:
        model=lambda wc: PLAN.variants()[wc.variant],
        train=PLAN.train_settings(),
        tune=config_slice("tune"),
        tracking_uri=TRACKING_URI,
        experiment_prefix=config_slice("tracking", "experiment_prefix"),
        experiment=config_slice("experiment"),
        seed=config_slice("seed"),
    log:
        f"{E}/logs/train/{{scenario}}-{{variant}}.log",
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
        expand(f"{E}/models/{{scenario}}/{{variant}}/metrics.json", scenario=PLAN.train_scenarios(), variant=list(PLAN.variants())),
