"""The package's import layers, read from the source with ``ast`` (function-level imports count too).

- no import circle between any two modules of ``liverforce``;
- ``mlflow`` is imported only inside ``liverforce/tracking/``;
- ``fem``, ``mesh``, ``geometry`` and ``dataset`` never import ``learn``, ``tracking`` or ``serve``;
- ``pyarrow`` only inside ``liverforce/dataset/``; ``hydra``/``omegaconf`` only in ``liverforce/config.py``.
"""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

PKG = Path(__file__).resolve().parents[1] / "liverforce"
LOWER = ("fem", "mesh", "geometry", "dataset")
UPPER = ("learn", "tracking", "serve")


def module_name(path: Path) -> str:
    parts = path.relative_to(PKG.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def all_modules() -> dict[str, Path]:
    return {module_name(p): p for p in PKG.rglob("*.py")}


def imports_of(path: Path, name: str, modules: dict[str, Path]) -> list[tuple[str, int]]:
    """(imported name, line) of every import in the file; a ``from pkg import sub`` names ``pkg.sub``
    when ``sub`` is a module of the package. Relative imports are resolved against the module."""
    tree = ast.parse(path.read_text(), filename=str(path))
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(a.name, node.lineno) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")
                anchor = anchor[: len(anchor) - (node.level - 1)]
                base = ".".join(anchor + ([base] if base else []))
            for a in node.names:
                sub = f"{base}.{a.name}"
                out.append((sub if sub in modules else base, node.lineno))
    return out


def internal_graph() -> dict[str, set[str]]:
    modules = all_modules()
    graph: dict[str, set[str]] = {m: set() for m in modules}
    for name, path in modules.items():
        for imp, _ in imports_of(path, name, modules):
            if imp in modules and imp != name:
                graph[name].add(imp)
    return graph


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One cycle of the directed graph (as a closed list of nodes), or None."""
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(n):
        state[n] = 1
        stack.append(n)
        for m in sorted(graph[n]):
            if state.get(m) == 1:
                return stack[stack.index(m):] + [m]
            if m not in state:
                found = visit(m)
                if found:
                    return found
        stack.pop()
        state[n] = 2
        return None

    for n in sorted(graph):
        if n not in state:
            found = visit(n)
            if found:
                return found
    return None


def test_find_cycle_detects_a_circle_and_accepts_a_tree():
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b", "c"}, "b": {"c"}, "c": set()}) is None


def test_relative_and_submodule_imports_are_resolved(tmp_path):
    f = tmp_path / "m.py"
    f.write_text("from . import tracking\nfrom .fem import problem\nimport mlflow.pyfunc\n")
    mods = {"liverforce.tracking": None, "liverforce.fem.problem": None}
    got = [n for n, _ in imports_of(f, "liverforce.x", mods)]
    assert got == ["liverforce.tracking", "liverforce.fem.problem", "mlflow.pyfunc"]


def test_no_import_circle_in_the_package():
    cycle = find_cycle(internal_graph())
    assert cycle is None, "import circle: " + " -> ".join(cycle)


@pytest.mark.parametrize("third_party, home", [
    ("mlflow", "liverforce.tracking"),
    ("pyarrow", "liverforce.dataset"),
    ("hydra", "liverforce.config"),
    ("omegaconf", "liverforce.config"),
])
def test_third_party_imports_stay_in_their_module(third_party, home):
    modules = all_modules()
    bad = []
    for name, path in modules.items():
        if name == home or name.startswith(home + "."):
            continue
        for imp, line in imports_of(path, name, modules):
            if imp == third_party or imp.startswith(third_party + "."):
                bad.append(f"{path.relative_to(PKG.parent)}:{line} imports {imp}")
    assert not bad, f"{third_party} may be imported only in {home}:\n" + "\n".join(bad)


def test_lower_layers_never_import_learning_tracking_or_serving():
    modules = all_modules()
    bad = []
    for name, path in modules.items():
        if name.split(".")[1:2] and name.split(".")[1] in LOWER:
            for imp, line in imports_of(path, name, modules):
                parts = imp.split(".")
                if parts[0] == "liverforce" and len(parts) > 1 and parts[1] in UPPER:
                    bad.append(f"{path.relative_to(PKG.parent)}:{line} imports {imp}")
    assert not bad, "fem/mesh/geometry/dataset must not depend on learn/tracking/serve:\n" + "\n".join(bad)
