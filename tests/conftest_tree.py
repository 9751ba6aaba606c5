"""A copy of the test set's conftests in a temporary folder, for tests that run a small pytest session of their own
(in a subprocess) with the same workers and fault ledger: tests/test_xdist_workers.py, tests/faults/test_ledger.py."""
from __future__ import annotations

import os
from pathlib import Path

TESTS = Path(__file__).resolve().parent


def conftest_tree(root: Path, ini: str) -> dict[str, str]:
    """Write ``root/tests/conftest.py``, ``root/tests/faults/{__init__,conftest}.py`` (the test set's own) and
    ``root/pytest.ini`` (``ini``); return the environment to run pytest in ``root`` with: this session's without
    its ``PYTEST_*`` variables (not this session's worker), the repository on ``PYTHONPATH``."""
    (root / "tests" / "faults").mkdir(parents=True)
    (root / "tests" / "conftest.py").write_text((TESTS / "conftest.py").read_text())
    for name in ("__init__.py", "conftest.py"):
        (root / "tests" / "faults" / name).write_text((TESTS / "faults" / name).read_text())
    (root / "pytest.ini").write_text(ini)
    env = {k: v for k, v in os.environ.items() if not k.startswith("PYTEST_")}
    env["PYTHONPATH"] = os.pathsep.join([str(TESTS.parent), *filter(None, [env.get("PYTHONPATH")])])
    return env
