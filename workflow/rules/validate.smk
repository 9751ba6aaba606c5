# Stage 7: the chosen scenario-IV model on the unseen liver with unseen constants.


rule validate:
    input:
        # every scenario-IV variant (validate.variant=auto picks by cross-validation score) or the one named
        model=expand(f"{E}/models/IV/{{v}}/model", v=list(PLAN.variants())),
        metrics=expand(f"{E}/models/IV/{{v}}/metrics.json", v=list(PLAN.variants())),
        manifest=f"{E}/shards/V/manifest.json",
        train_manifest=f"{E}/shards/IV/manifest.json",
    output:
        metrics=f"{E}/validate/metrics.json",
    params:
        tracking_uri=TRACKING_URI,
        variant=config_slice("validate", "variant"),
        experiment_name=f"{config_slice('tracking', 'experiment_prefix')}-{config_slice('experiment')}-validation",
    log:
        f"{E}/logs/validate/validate.log",
    conda:
        "../envs/liverforce.yaml"
    threads: 1
    resources:
        mem_mb=2000,
        runtime=10,
    script:
        "../scripts/validate.py"
