# Helpers and the composed configuration. No rules here.
import os
import shlex

from liverforce.config import compose, tracking_uri
from liverforce.pipeline import plan

# one thread per BLAS / numba / torch pool in every job: 2 jobs on 2 cores
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(_var, "1")


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
PLAN = plan.Plan(CFG)
E = PLAN.root  # results/<experiment>
TRACKING_URI = tracking_uri(CFG)


def config_slice(*keys):
    """A plain-dict slice of the composed config (what `params:` carries)."""
    node = CFG
    for k in keys:
        node = node[k]
    return node


onstart:
    # create the embedded MLflow store once, before parallel jobs (SQLite race)
    from liverforce.tracking import ensure_store

    ensure_store(TRACKING_URI)
