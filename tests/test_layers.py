"""The package's import structure: the layers of ``[tool.importlinter]`` in pyproject.toml hold, and no module
imports itself back through others (no import cycles). Imports inside functions count: grimp reads every import
statement, wherever it stands."""

import importlib.util
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

pytestmark = pytest.mark.skipif(
    importlib.util.find_spec("importlinter") is None or importlib.util.find_spec("grimp") is None,
    reason="import-linter is not installed (it is in the test extra: pip install -e '.[test]')")


def test_import_contracts_are_kept():
    """``lint-imports``: every contract of pyproject.toml (layers, independent siblings, forbidden imports) is kept.

    In a subprocess: import-linter configures logging in the process it runs in (existing loggers,
    ``torchcal``'s among them, end up disabled for every later test)."""
    code = ("import sys; from importlinter.cli import EXIT_STATUS_SUCCESS, lint_imports; "
            f"sys.exit(0 if lint_imports(config_filename={str(ROOT / 'pyproject.toml')!r}, no_cache=True, "
            "no_logo=True) == EXIT_STATUS_SUCCESS else 1)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=600, cwd=ROOT)
    assert out.returncode == 0, out.stdout + out.stderr


def _cycles(graph, modules: set[str]) -> list[list[str]]:
    """Strongly connected components with more than one module (or a module importing itself), Tarjan, iterative."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    on_stack: set[str] = set()
    stack: list[str] = []
    found = []
    succ = {m: sorted(graph.find_modules_directly_imported_by(m) & modules) for m in modules}
    counter = 0
    for root in sorted(modules):
        if root in index:
            continue
        work = [(root, 0)]
        while work:
            v, i = work.pop()
            if i == 0:
                index[v] = low[v] = counter
                counter += 1
                stack.append(v)
                on_stack.add(v)
            if i < len(succ[v]):
                work.append((v, i + 1))
                w = succ[v][i]
                if w not in index:
                    work.append((w, 0))
                elif w in on_stack:
                    low[v] = min(low[v], index[w])
                continue
            if work:  # v is done: pass its low link up to its caller
                caller = work[-1][0]
                low[caller] = min(low[caller], low[v])
            if low[v] == index[v]:
                comp = []
                while True:
                    w = stack.pop()
                    on_stack.discard(w)
                    comp.append(w)
                    if w == v:
                        break
                if len(comp) > 1 or v in succ[v]:
                    found.append(sorted(comp))
    return found


def test_no_import_cycles():
    """No module reaches itself through imports (a cycle would make import order matter, and layers meaningless)."""
    import grimp

    graph = grimp.build_graph("torchcal", cache_dir=None)
    modules = {m for m in graph.modules if m == "torchcal" or m.startswith("torchcal.")}
    cycles = _cycles(graph, modules)
    assert not cycles, "import cycles:\n" + "\n".join(
        f"{len(c)} modules: " + ", ".join(c) for c in cycles)


def test_cycle_finder_finds_a_planted_cycle():
    """The check above is not vacuous: a three-module cycle and a self-import are found, a chain is not."""
    import grimp

    graph = grimp.ImportGraph()
    for m in ("p", "p.a", "p.b", "p.c", "p.d", "p.e"):
        graph.add_module(m)
    for a, b in (("p.a", "p.b"), ("p.b", "p.c"), ("p.c", "p.a"), ("p.d", "p.a"), ("p.e", "p.e")):
        graph.add_import(importer=a, imported=b)
    assert _cycles(graph, set(graph.modules)) == [["p.a", "p.b", "p.c"], ["p.e"]]


LONG_MODULE_LINES = 500


def test_every_long_module_says_why_it_is_one_module():
    """A module over ~500 lines states at its top why it is not split (a docstring paragraph 'Why one module:')."""
    import ast

    missing = []
    for path in sorted((ROOT / "torchcal").rglob("*.py")):
        text = path.read_text(encoding="utf-8")
        if text.count("\n") > LONG_MODULE_LINES:
            doc = ast.get_docstring(ast.parse(text)) or ""
            if "Why one module:" not in doc:
                missing.append(f"{path.relative_to(ROOT)} ({text.count(chr(10))} lines)")
    assert not missing, "long modules without a reason at the top: " + ", ".join(missing)
