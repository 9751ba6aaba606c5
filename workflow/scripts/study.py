"""Snakemake adapter: one comparison study (see liverforce.pipeline.study.run_study_stage)."""
from liverforce.pipeline.job import setup_job
from liverforce.pipeline.study import run_study_stage

sm = snakemake  # noqa: F821
setup_job(sm.log[0], sm.threads, outputs=sm.output)
scenarios = list(sm.params.scenarios)
run_study_stage(
    study=sm.wildcards.study,
    study_cfg=sm.params.study,
    manifests=dict(zip(scenarios, sm.input.manifests)),
    main_metrics=dict(zip(scenarios, sm.input.main_metrics)),
    mesh_paths=list(sm.input.meshes),
    model_cfg=sm.params.model,
    train_cfg=sm.params.train,
    tracking_uri=sm.params.tracking_uri,
    experiment_name=sm.params.experiment_name,
    experiment=sm.params.experiment,
    seed=sm.params.seed,
    threads=sm.threads,
    out_json=sm.output.json,
    out_png=sm.output.png,
)
