# Helpers and the composed configuration. No rules here.
import shlex

from liverforce.config import compose, tracking_uri
from liverforce.pipeline import plan
from liverforce.pipeline.job import thread_env

# one thread per BLAS / numba / torch pool in every job: 2 jobs on 2 cores
thread_env(1, override=False)


def _overrides_from_snakemake_config(config):
    """Hydra overrides from `--config experiment=... overrides="a=1 b=2"`."""
    out = []
    if "experiment" in config:
        out.append(f"experiment={config['experiment']}")
    ov = config.get("overrides", [])
    if isinstance(ov, str):
        ov = shlex.split(ov)
    out.extend(str(o) for o in ov)
    return out


CFG = compose(_overrides_from_snakemake_config(config))


def _refuse_unstable_material(cfg):
    """Drucker-check the configured material constants once, before any job runs.

    The sweep rule checks them again with every sampled set; checking here
    means unstable constants stop the workflow before geometry and meshing.
    """
    from liverforce.config import ConfigError, liver_material
    from liverforce.pipeline.sweep import material_checks

    mat = cfg["material"]
    stable, _ = material_checks(mat["stability_stretch"], mat["nu"])
    ok, why = stable(mat["model"], dict(mat["params_mpa"]))
    if not ok:
        raise ConfigError(f"config key 'material.params_mpa': {why}")
    for i, imp in enumerate(cfg["geometry"]["imported"]):  # a lab liver's own constants (config.liver_material)
        if imp.get("material") is not None:
            key = f"geometry.imported[{i}].material"
            params, note = liver_material(imp["material"], mat, key)
            ok, why = stable(mat["model"], params)
            if not ok:
                raise ConfigError(f"config key '{key}': {note}: {why}")


_refuse_unstable_material(CFG)
PLAN = plan.Plan(CFG)
P = PLAN.paths  # every output path (liverforce.layout): results/<experiment>/...
TRACKING_URI = tracking_uri(CFG)


wildcard_constraints:
    **PLAN.wildcard_patterns(),


def config_slice(*keys):
    """A plain-dict slice of the composed config (what `params:` carries)."""
    node = CFG
    for k in keys:
        node = node[k]
    return node


def needs_iv(what, paths):
    """Input function giving ``paths`` (scenario IV's models) to the validation and physics jobs, or the refusal
    of a run without scenario IV (``Plan.require_iv``), raised only when such a job is asked for (so a one-liver
    run's models target runs). No rule-like text in here: the linter's regex would take it for one."""

    def get(wildcards):
        PLAN.require_iv(what)
        return paths

    return get


onstart:
    # create the embedded MLflow store once, before parallel jobs (SQLite race)
    from liverforce.tracking import ensure_store

    ensure_store(TRACKING_URI)
