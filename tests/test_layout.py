"""The package layout: README imports work, no import cycles (function-level imports included), no imports of
another module's private names, modules stay small."""

import ast
import pathlib
import re
import subprocess
import sys

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
#: Above this many lines a module must say at its top why it is one module.
MAX_LINES = 520
SOURCES = {"core": "bubsub.core", "clients": "bubsub.clients", "service": "bubsub.service", "bench": "bubsub.bench"}


def _modules():
    for folder, package in SOURCES.items():
        for path in sorted((ROOT / folder).rglob("*.py")):
            rel = path.relative_to(ROOT / folder).with_suffix("")
            parts = [p for p in rel.parts if p != "__init__"]
            yield path, ".".join([package, *parts])


def test_readme_imports_work():
    text = (ROOT / "README.md").read_text()
    lines = sorted(set(re.findall(r"^\s*(from bubsub[\w.]* import [^\n#]+)", text, flags=re.M)))
    assert lines, "the README shows no imports"
    code = "\n".join(line.strip().rstrip(",") for line in lines if not line.rstrip().endswith("("))
    subprocess.run([sys.executable, "-c", code], check=True, cwd=ROOT)


def test_example_notebook_imports_work():
    # a fast check of what tests/test_notebook.py finds only after minutes of running the notebook
    import json

    lines = []
    for nb in sorted((ROOT / "examples").glob("*.ipynb")):
        for cell in json.loads(nb.read_text())["cells"]:
            if cell["cell_type"] == "code":
                lines += [ln.strip() for ln in "".join(cell["source"]).splitlines()
                          if re.match(r"\s*from bubsub[\w.]* import [^(]+$", ln)]
    assert lines, "the example notebooks show no bubsub imports"
    subprocess.run([sys.executable, "-c", "\n".join(sorted(set(lines)))], check=True, cwd=ROOT)


def _import_each_first(tmp):
    # A cycle shows up as an ImportError only for some import orders, so each
    # module is imported first into an interpreter without any bubsub module.
    names = [name for _, name in _modules() if not name.endswith("__main__")]
    script = (
        "import importlib, sys\n"
        f"names = {names!r}\n"
        "bad = []\n"
        "for n in names:\n"
        "    for m in [m for m in sys.modules if m == 'bubsub' or m.startswith('bubsub.')]:\n"
        "        del sys.modules[m]\n"
        "    try:\n"
        "        importlib.import_module(n)\n"
        "    except ImportError as e:\n"
        "        # an optional third-party extra that is not installed is not a cycle\n"
        "        if (e.name or '').split('.')[0] != 'bubsub' and 'partially initialized' not in str(e):\n"
        "            continue\n"
        "        bad.append(f'{n}: {e}')\n"
        "print('\\n'.join(bad))\n"
        "sys.exit(1 if bad else 0)\n"
    )
    return [sys.executable, "-c", script], None, ROOT


@pytest.mark.background(command=_import_each_first)
def test_every_module_imports_first_without_a_cycle(background):
    res = background.wait(600)
    assert res.returncode == 0, res.stdout + res.stderr


#: Import cycles allowed, each as the modules of one cycle: none. Optional dependencies need no entry:
#: they are third-party imports, which the graph below does not contain.
CYCLES_ALLOWED = []

#: ``(importing module, imported module, private name)`` allowed: none. A name another module needs is
#: public in its own (in ``__all__``, with a docstring).
PRIVATE_IMPORTS_ALLOWED = set()


def _names():
    return {name: path for path, name in _modules()}


def _owner(name, modules):
    """The module a dotted import name lands in: itself, or the longest module prefix of it."""
    while name and name not in modules:
        name = name.rpartition(".")[0]
    return name or None


def _imports(path, name, modules):
    """``(imported module, imported name or None, line)`` of every bubsub import at any depth of the module."""
    tree = ast.parse(path.read_text(), filename=str(path))
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name == "bubsub" or alias.name.startswith("bubsub."):
                    yield _owner(alias.name, modules), None, node.lineno
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package
                for _ in range(node.level - 1):
                    base = base.rpartition(".")[0]
                source = f"{base}.{node.module}" if node.module else base
            else:
                source = node.module or ""
            if source != "bubsub" and not source.startswith("bubsub."):
                continue
            for alias in node.names:
                full = f"{source}.{alias.name}"
                if full in modules:  # a submodule: the edge goes to it
                    yield full, None, node.lineno
                else:
                    yield _owner(source, modules), alias.name, node.lineno


def import_graph():
    """``{module: {imported module: first line}}`` over every bubsub import, function-level ones included."""
    modules = _names()
    graph = {}
    for name, path in modules.items():
        edges = graph.setdefault(name, {})
        for target, _, line in _imports(path, name, modules):
            if target and target != name:
                edges.setdefault(target, line)
    return graph


def strongly_connected(graph):
    """The components of more than one module (each a set): every import cycle lies within one."""
    index, low, stack, on_stack, found = {}, {}, [], set(), []

    def visit(v):  # Tarjan's algorithm; the package graph is shallow enough for recursion
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = set()
            while True:
                w = stack.pop()
                on_stack.discard(w)
                comp.add(w)
                if w == v:
                    break
            if len(comp) > 1:
                found.append(comp)

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def test_the_cycle_finder_finds_a_cycle_through_a_function_level_import():
    graph = {"a": {"b": 1}, "b": {"c": 3}, "c": {"a": 9}, "d": {"a": 2}}  # c imports a inside a function
    assert strongly_connected(graph) == [{"a", "b", "c"}]
    assert strongly_connected({"a": {"b": 1}, "b": {}}) == []


def test_no_import_cycles_beyond_the_allowed_ones():
    # static: every `import bubsub...` / `from bubsub... import` at any depth, so that cycles hidden in
    # function-level imports (which never fail at import time) count too
    graph = import_graph()
    cycles = strongly_connected(graph)
    unexpected = []
    for comp in cycles:
        if comp not in CYCLES_ALLOWED:
            edges = [f"{a} -> {b} (line {graph[a][b]})" for a in sorted(comp) for b in graph[a] if b in comp]
            unexpected.append("cycle: " + "; ".join(edges))
    assert not unexpected, "\n".join(unexpected)
    stale = [sorted(c) for c in CYCLES_ALLOWED if c not in cycles]
    assert not stale, f"these allowed cycles are gone: remove them from CYCLES_ALLOWED: {stale}"


def test_no_module_imports_another_modules_private_names():
    modules = _names()
    found = set()
    for name, path in modules.items():
        for target, imported, line in _imports(path, name, modules):
            if imported and imported.startswith("_") and not imported.startswith("__") and target != name:
                found.add((name, target, imported))
    unexpected = sorted(found - PRIVATE_IMPORTS_ALLOWED)
    assert not unexpected, f"imports of private names (make them public, or keep them in their module): {unexpected}"
    stale = sorted(PRIVATE_IMPORTS_ALLOWED - found)
    assert not stale, f"these allowed private imports are gone: remove them from PRIVATE_IMPORTS_ALLOWED: {stale}"


@pytest.mark.parametrize("path,name", list(_modules()), ids=lambda x: str(x) if isinstance(x, str) else "")
def test_large_modules_state_why(path, name):
    n = len(path.read_text().splitlines())
    if n <= MAX_LINES:
        return
    doc = ast.get_docstring(ast.parse(path.read_text())) or ""
    assert "on purpose" in doc, f"{name} has {n} lines; split it or say at its top why it is one module ('on purpose')"
