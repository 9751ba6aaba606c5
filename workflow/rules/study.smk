# Stage 7b: comparison studies (ROI fraction, encoder, state vector, occlusion, noise)
# on the shards already simulated; no new FE. Each study point reuses the
# scenario's main model (first train.variants entry: settings + tuned
# hyper-parameters), trains without Ax and is one MLflow run under
# "<prefix>-<experiment>-studies" (tags study, value, scenario).
from liverforce.learn.study import STUDIES, enabled_studies, study_geometries, study_scenarios, study_slice

STUDY_CFG = config_slice("study")
STUDY_NAMES = enabled_studies(STUDY_CFG)
MAIN_VARIANT = PLAN.chosen_variant()


wildcard_constraints:
    study="|".join(STUDIES),


rule study:
    input:
        manifests=lambda wc: [f"{E}/shards/{s}/manifest.json" for s in study_scenarios(wc.study, STUDY_CFG)],
        main_metrics=lambda wc: [f"{E}/models/{s}/{MAIN_VARIANT}/metrics.json" for s in study_scenarios(wc.study, STUDY_CFG)],
        meshes=lambda wc: [f"{E}/mesh/{g}.vtu" for g in study_geometries(wc.study, STUDY_CFG, PLAN)],
    output:
        json=f"{E}/studies/{{study}}.json",
        png=f"{E}/studies/{{study}}.png",
    params:
        study=lambda wc: study_slice(wc.study, STUDY_CFG),
        scenarios=lambda wc: study_scenarios(wc.study, STUDY_CFG),
        model=PLAN.variants()[MAIN_VARIANT],
        train=PLAN.train_settings(),
        tracking_uri=TRACKING_URI,
        experiment_prefix=config_slice("tracking", "experiment_prefix"),
        experiment=config_slice("experiment"),
        seed=config_slice("seed"),
    log:
        f"{E}/logs/study/{{study}}.log",
    conda:
        "../envs/liverforce.yaml"
    threads: 1
    resources:
        mem_mb=3000,
        runtime=60,
    script:
        "../scripts/study.py"


rule studies:
    input:
        expand(f"{E}/studies/{{study}}.json", study=STUDY_NAMES),
