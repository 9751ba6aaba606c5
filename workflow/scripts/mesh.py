"""Snakemake adapter: mesh stage (see liverforce.pipeline.mesh.make_mesh)."""
from liverforce.pipeline.job import setup_job
from liverforce.pipeline.mesh import make_mesh

sm = snakemake  # noqa: F821
setup_job(sm.log[0], sm.threads, outputs=sm.output)
make_mesh(sm.input.surface, sm.params.mesh, sm.params.seed, sm.output.mesh, sm.output.features, sm.output.picture,
          exertion=sm.params.exertion)
