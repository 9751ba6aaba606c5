#!/usr/bin/env bash
# Install liverforce into ./.venv (or $LIVERFORCE_VENV). Idempotent.
#
#   bash scripts/install.sh          # the package and its runtime stack
#   bash scripts/install.sh test     # ... plus the test extras (and slurm-wlm for the cluster test, as root)
#
# CHOLMOD (sparse Cholesky, ~10x faster than SuperLU on liver meshes) needs the
# system SuiteSparse headers: installed with apt when we are root and apt-get
# exists; otherwise the solver falls back to SciPy's SuperLU (and says so).
set -euo pipefail
cd "$(dirname "$0")/.."
VENV="${LIVERFORCE_VENV:-.venv}"
PY="${PYTHON:-python3}"
EXTRAS=""
[ "${1:-}" = "test" ] && EXTRAS="test"

if [ ! -x "$VENV/bin/python" ]; then
    "$PY" -m venv "$VENV"
fi

have_suitesparse() { [ -f /usr/include/suitesparse/cholmod.h ]; }
if ! have_suitesparse && [ "$(id -u)" = "0" ] && command -v apt-get >/dev/null 2>&1; then
    echo "[install] installing SuiteSparse (CHOLMOD) with apt-get" >&2
    export DEBIAN_FRONTEND=noninteractive
    { apt-get update -q && apt-get install -y -q libsuitesparse-dev libopenblas0-pthread; } >/dev/null 2>&1 \
        || echo "[install] apt-get failed: continuing without CHOLMOD (SuperLU fallback)" >&2
fi
# the test extras also get a one-node SLURM (slurm-wlm + munge) when we can install it:
# tests/faults/test_cluster.py then runs jobs through the SLURM profile for real (it skips, saying why, without)
if [ "$EXTRAS" = "test" ] && ! command -v sbatch >/dev/null 2>&1 && [ "$(id -u)" = "0" ] \
        && command -v apt-get >/dev/null 2>&1; then
    echo "[install] installing slurm-wlm and munge with apt-get (cluster test)" >&2
    export DEBIAN_FRONTEND=noninteractive
    { apt-get update -q && apt-get install -y -q slurm-wlm munge; } >/dev/null 2>&1 \
        || echo "[install] apt-get failed: the SLURM cluster test will be skipped" >&2
fi
if have_suitesparse; then
    EXTRAS="${EXTRAS:+$EXTRAS,}fast"
fi

SPEC="."
[ -n "$EXTRAS" ] && SPEC=".[$EXTRAS]"
echo "[install] pip install -e '$SPEC' into $VENV" >&2
"$VENV/bin/python" -m pip install --disable-pip-version-check -q -e "$SPEC"
"$VENV/bin/python" -c "import liverforce, torch; print('[install] liverforce', liverforce.__version__, '| torch', torch.__version__)" >&2
