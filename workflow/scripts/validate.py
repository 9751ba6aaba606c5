"""Snakemake adapter: unseen-liver validation (see liverforce.pipeline.validate.validate_model)."""
from liverforce.pipeline.job import setup_job
from liverforce.pipeline.validate import validate_model

sm = snakemake  # noqa: F821
setup_job(sm.log[0], sm.threads, outputs=sm.output)
validate_model(list(sm.input.model), list(sm.input.metrics), sm.input.manifest, sm.input.train_manifest,
               sm.params.tracking_uri, sm.output.metrics, experiment_name=sm.params.experiment_name,
               variant=sm.params.variant, input=sm.params.input, mesh_paths=list(sm.input.meshes),
               sensitivity=sm.params.sensitivity, registration_errors=sm.params.registration_errors,
               shape_changes=sm.params.shape_changes)
