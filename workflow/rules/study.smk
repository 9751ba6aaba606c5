# Stage 7b: comparison studies (ROI fraction, encoder, state vector, occlusion, noise)
# on the shards already simulated; no new FE. Each study point reuses the
# scenario's main model (first train.variants entry: settings + tuned
# hyper-parameters), trains without Ax and is one MLflow run under
# PLAN.experiment_name("studies") (tags study, value, scenario).
from liverforce.learn.study import STUDIES, enabled_studies, study_geometries, study_scenarios, study_slice

STUDY_CFG = config_slice("study")
STUDY_NAMES = enabled_studies(STUDY_CFG)
MAIN_VARIANT = PLAN.chosen_variant()


wildcard_constraints:
    study="|".join(STUDIES),


rule study:
    input:
        manifests=lambda wc: [P.manifest(s) for s in study_scenarios(wc.study, STUDY_CFG)],
        main_metrics=lambda wc: [P.model_metrics(s, MAIN_VARIANT) for s in study_scenarios(wc.study, STUDY_CFG)],
        meshes=lambda wc: [P.mesh(g) for g in study_geometries(wc.study, STUDY_CFG, PLAN)],
    output:
        json=P.study(),
        png=P.study_picture(),
    params:
        study=lambda wc: study_slice(wc.study, STUDY_CFG),
        scenarios=lambda wc: study_scenarios(wc.study, STUDY_CFG),
        model=PLAN.variants()[MAIN_VARIANT],
        train=PLAN.train_settings(),
        tracking_uri=TRACKING_URI,
        experiment_name=PLAN.experiment_name("studies"),
        experiment=config_slice("experiment"),
        seed=PLAN.train_seed(),
    log:
        P.log("study", "{study}"),
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
        [P.study(s) for s in STUDY_NAMES],
