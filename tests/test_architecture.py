"""The structure the code must keep (issue 12), checked from the source with `ast` (nothing is imported):
no import cycles among vio/, frontend/ and backend/; frontend and backend never import each other; rerun only in
vio/viz/; no class longer than 400 lines; no mixins in backend/ (a class there derives from no class but an exception).

Run alone: `.venv/bin/python -m pytest -q tests/test_architecture.py`.
"""

from __future__ import annotations

import ast

from tests.conftest import ROOT

PACKAGES = ("vio", "frontend", "backend")
MAX_CLASS_LINES = 400


def _modules() -> dict[str, ast.Module]:
    out = {}
    for pkg in PACKAGES:
        for path in sorted((ROOT / pkg).rglob("*.py")):
            parts = list(path.relative_to(ROOT).with_suffix("").parts)
            name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
            out[name] = ast.parse(path.read_text(encoding="utf-8"), str(path))
    return out


MODULES = _modules()


def _resolve(name: str) -> str | None:
    """The project module an imported name belongs to (longest existing prefix), or None."""
    while name:
        if name in MODULES:
            return name
        name = name.rpartition(".")[0]
    return None


def _imports(name: str, tree: ast.Module) -> set[str]:
    """Every project module imported anywhere in the module (function-local and TYPE_CHECKING imports count)."""
    out = set()
    pkg = name if name in {m for m in MODULES if (ROOT / m.replace(".", "/")).is_dir()} else name.rpartition(".")[0]
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                up = pkg.split(".")[: len(pkg.split(".")) - node.level + 1]
                base = ".".join([*up, base] if base else up)
            targets = [f"{base}.{a.name}" for a in node.names] + [base]
        else:
            continue
        out |= {m for t in targets if (m := _resolve(t)) and m != name}
    return out


def _graph() -> dict[str, set[str]]:
    return {name: _imports(name, tree) for name, tree in MODULES.items()}


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_the_checker_sees_a_cycle():
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert _resolve("vio.config.Config") == "vio.config" and _resolve("numpy") is None
    assert "vio.config" in _imports("backend.smoother", MODULES["backend.smoother"])


def test_no_import_cycles():
    assert _cycles(_graph()) == []


def test_frontend_and_backend_never_import_each_other():
    bad = [
        f"{a} -> {b}"
        for a, deps in _graph().items()
        for b in deps
        if {a.split(".")[0], b.split(".")[0]} == {"frontend", "backend"}
    ]
    assert bad == []


def test_rerun_is_imported_only_by_the_viewer_package():
    bad = []
    for name, tree in MODULES.items():
        for node in ast.walk(tree):
            mods = [a.name for a in node.names] if isinstance(node, ast.Import) else []
            mods += [node.module or ""] if isinstance(node, ast.ImportFrom) else []
            if any(m == "rerun" or m.startswith("rerun.") for m in mods) and not name.startswith("vio.viz."):
                bad.append(name)
    assert bad == []


def test_no_long_classes_and_no_mixins_in_backend():
    long, mixins = [], []
    for name, tree in MODULES.items():
        for node in ast.walk(tree):
            if not isinstance(node, ast.ClassDef):
                continue
            if node.end_lineno - node.lineno + 1 > MAX_CLASS_LINES:
                long.append(f"{name}.{node.name}")
            bases = [ast.unparse(b) for b in node.bases]
            if name.startswith("backend.") and any(b not in ("RuntimeError", "Exception", "object") for b in bases):
                mixins.append(f"{name}.{node.name}({', '.join(bases)})")
    assert long == [] and mixins == []
