"""Snakemake adapter: the physics study (see liverforce.pipeline.physics.physics_study)."""
from liverforce.pipeline.job import setup_job
from liverforce.pipeline.physics import physics_study

sm = snakemake  # noqa: F821
setup_job(sm.log[0], sm.threads, outputs=sm.output)
physics_study(sm.input.cases, sm.input.mesh, list(sm.input.model), list(sm.input.metrics), sm.params.simulate,
              sm.params.boundary, sm.params.dataset, sm.params.material, sm.params.spec, sm.output.study,
              sm.output.shards)
