"""The package's layout rules, read from the sources (no DOLFINx needed).

- no module of the package longer than ``MAX_MODULE_LINES``;
- no import cycle between the package's modules (deferred imports inside functions count);
- no private name (``_name``) imported from another module, in the package, the demos, the
  benchmarks or the model builders (``meshes/``); a private *module* (``_compat``) may be
  imported inside the package, never from outside it;
- demos, benchmarks and model builders import public names only, import ``meshes`` by name
  (no loading by file path) and nothing from ``tests/``.

Run ``python3 tests/test_layout.py [REPO]`` to list every violation of a tree.
"""

from __future__ import annotations

import ast
import sys
from pathlib import Path

MAX_MODULE_LINES = 700
PACKAGE = "fenics_matdepth"
OUTSIDE = ("demos", "benchmarks", "meshes")
REPO = Path(__file__).resolve().parent.parent


def _module_name(path: Path, repo: Path) -> str:
    parts = list(path.relative_to(repo).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _package_modules(repo: Path) -> dict[str, Path]:
    return {_module_name(p, repo): p for p in sorted((repo / PACKAGE).rglob("*.py"))}


def _imports(path: Path, name: str) -> list[tuple[str, str | None, int]]:
    """(module, imported name or None, line) for every import in the file, wherever it is."""
    tree = ast.parse(path.read_text(), filename=str(path))
    is_package = path.name == "__init__.py"
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [(alias.name, None, node.lineno) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            module = node.module or ""
            if node.level:  # relative import
                base = name.split(".") if is_package else name.split(".")[:-1]
                base = base[: len(base) - node.level + 1]
                module = ".".join(base + ([module] if module else []))
            found += [(module, alias.name, node.lineno) for alias in node.names]
    return found


def _targets(module: str, imported: str | None, modules: dict[str, Path]) -> list[str]:
    """The package modules an import statement loads (a name that is a submodule counts)."""
    if imported is not None and f"{module}.{imported}" in modules:
        return [f"{module}.{imported}"]
    return [module] if module in modules else []


def import_graph(repo: Path = REPO) -> dict[str, set[str]]:
    modules = _package_modules(repo)
    graph = {}
    for name, path in modules.items():
        edges = set()
        for module, imported, _ in _imports(path, name):
            edges.update(t for t in _targets(module, imported, modules) if t != name)
        graph[name] = edges
    return graph


def import_cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan)."""
    index, low, stack, on_stack, cycles = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                cycles.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return cycles


def long_modules(repo: Path = REPO) -> list[str]:
    return [
        f"{name}: {n} lines"
        for name, path in _package_modules(repo).items()
        if (n := len(path.read_text().splitlines())) > MAX_MODULE_LINES
    ]


def private_imports(repo: Path = REPO) -> list[str]:
    """Private names imported from another module; private modules imported from outside."""
    modules = _package_modules(repo)
    files = list(modules.items())
    for folder in OUTSIDE:
        files += [(_module_name(p, repo), p) for p in sorted((repo / folder).rglob("*.py"))]
    found = []
    for name, path in files:
        inside = name.split(".")[0] == PACKAGE
        where = path.relative_to(repo)
        for module, imported, line in _imports(path, name):
            if module.split(".")[0] != PACKAGE:
                continue
            is_module = imported is not None and f"{module}.{imported}" in modules
            if imported is not None and imported.startswith("_") and not (inside and is_module):
                found.append(f"{where}:{line}: private name {imported} of {module}")
            full = f"{module}.{imported}" if is_module else module
            if not inside and any(part.startswith("_") for part in full.split(".")):
                found.append(f"{where}:{line}: private module {full}")
    return found


def outside_rules(repo: Path = REPO) -> list[str]:
    """Demos, benchmarks and model builders: no loading by path, nothing from tests/."""
    found = []
    for folder in OUTSIDE:
        for path in sorted((repo / folder).rglob("*.py")):
            name = _module_name(path, repo)
            text = path.read_text()
            where = path.relative_to(repo)
            if "spec_from_file_location" in text:
                found.append(f"{where}: loads a module by file path")
            for module, _, line in _imports(path, name):
                if module.split(".")[0] == "tests" or module.startswith("test_"):
                    found.append(f"{where}:{line}: imports {module} from the tests")
    return found


def test_no_module_over_the_line_limit():
    assert long_modules() == []


def test_no_import_cycle():
    assert import_cycles(import_graph()) == []


def test_no_private_name_crosses_a_module():
    assert private_imports() == []


def test_demos_and_benchmarks_use_public_names_only():
    assert outside_rules() == []


def test_the_checks_find_what_they_look_for(tmp_path):
    """The rules find a cycle, a long module, a private import and a load by path."""
    pkg = tmp_path / PACKAGE
    (pkg / "sub").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "sub" / "__init__.py").write_text("")
    (pkg / "a.py").write_text("def f():\n    from fenics_matdepth.sub.b import g\n")
    (pkg / "sub" / "b.py").write_text("from fenics_matdepth.a import f\n_h = 1\n")
    (pkg / "c.py").write_text("from fenics_matdepth.sub.b import _h\n" + "x = 1\n" * 700)
    (pkg / "_priv.py").write_text("")
    (tmp_path / "demos").mkdir()
    (tmp_path / "demos" / "demo_x.py").write_text(
        "from fenics_matdepth import _priv\nimport importlib.util\n"
        "spec = importlib.util.spec_from_file_location('m', 'meshes/m.py')\n"
        "from test_operator import helper\n"
    )
    assert import_cycles(import_graph(tmp_path)) == [["fenics_matdepth.a", "fenics_matdepth.sub.b"]]
    assert long_modules(tmp_path) == ["fenics_matdepth.c: 701 lines"]
    found = private_imports(tmp_path)
    assert any("private name _h" in f for f in found)
    assert any("private module fenics_matdepth._priv" in f for f in found)
    assert len(outside_rules(tmp_path)) == 2


if __name__ == "__main__":
    repo = Path(sys.argv[1]).resolve() if len(sys.argv) > 1 else REPO
    problems = long_modules(repo) + private_imports(repo) + outside_rules(repo)
    problems += ["import cycle: " + " <-> ".join(c) for c in import_cycles(import_graph(repo))]
    print("\n".join(problems) or "layout: no violations")
    sys.exit(1 if problems else 0)
