"""Snakemake adapter: train one scenario/variant (see liverforce.pipeline.train.train_model)."""
from liverforce.pipeline.job import setup_job
from liverforce.pipeline.train import train_model

sm = snakemake  # noqa: F821
setup_job(sm.log[0], sm.threads, outputs=sm.output)
train_model(
    manifest_path=sm.input.manifest,
    scenario=sm.wildcards.scenario,
    variant=sm.wildcards.variant,
    model_cfg=sm.params.model,
    train_cfg=sm.params.train,
    tune_cfg=sm.params.tune,
    tracking_uri=sm.params.tracking_uri,
    experiment_name=sm.params.experiment_name,
    experiment=sm.params.experiment,
    seed=sm.params.seed,
    threads=sm.threads,
    metrics_path=sm.output.metrics,
    model_dir=sm.output.model,
    mesh_paths=list(sm.input.meshes),
)
