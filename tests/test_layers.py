"""The package's layers (docs/architecture.md, "Layers"), read from every module's syntax tree: which package may
import which, no cycles between sub-packages, absolute ``bubsub.`` imports only, and imports inside functions only
for optional extras or a reason listed here."""

import ast
import sys

import pytest

from test_layout import _modules

#: A module's unit: its sub-package below ``bubsub.core`` or ``bubsub.clients`` (nested folders belong to it), a
#: module directly in ``core/`` or ``clients/`` on its own, the whole of ``service`` and of ``bench``.
WHOLE = ("bubsub.service", "bubsub.bench")

#: Which packages each package may import; a name stands for the package and everything under it.
MAY_IMPORT = {
    "bubsub.core": ("bubsub.core",),
    "bubsub.service": ("bubsub.service", "bubsub.core"),
    "bubsub.clients": ("bubsub.clients", "bubsub.core"),
    "bubsub.bench": ("bubsub.bench", "bubsub.clients", "bubsub.service", "bubsub.core"),
    "bubsub.clients.cli": ("bubsub.clients", "bubsub.bench", "bubsub.service", "bubsub.core"),
}
#: Never imported by these packages, although a broader entry above would allow it.
MUST_NOT_IMPORT = {
    "bubsub.clients": ("bubsub.clients.cli",),
    "bubsub.bench": ("bubsub.clients.cli",),
}
#: Packages without command-line parsing: they take plain arguments; the CLI turns options into them.
NO_ARGPARSE = ("bubsub.core", "bubsub.clients.cluster", "bubsub.clients.pipeline",
               "bubsub.clients.optimise", "bubsub.clients.remote", "bubsub.clients.analysis")

#: Third-party modules that may be imported inside a function: optional extras (a missing one fails only the
#: feature that needs it) and heavy modules that most runs never use.
OPTIONAL = {
    "astra": "the 'astra' extra",
    "dask": "the 'cluster' extra", "distributed": "the 'cluster' extra", "dask_jobqueue": "the 'cluster' extra",
    "fastapi": "the 'service' extra", "uvicorn": "the 'service' extra", "httpx": "the 'service'/'client' extra",
    "pydantic": "the 'service' extra", "pydantic_settings": "the 'service' extra",
    "swagger_ui_bundle": "the 'service' extra", "starlette": "the 'service' extra",
    "gpytoolbox": "the 'dynamic' extra", "foamquant": "the 'foamquant' extra", "psutil": "not a dependency",
    "embreex": "a backend that is not the default; its import fails on some platforms",
    "matplotlib": "heavy (0.3 s): only figures need it", "mpl_toolkits": "matplotlib's",
}

#: ``(importing module, imported bubsub module)`` pairs imported inside a function, each with its reason.
FUNCTION_LEVEL_ALLOWED = {
}


#: Cycles between units that remain, each with what breaks it.
UNIT_CYCLES_ALLOWED = [
    ({"bubsub.core.projection", "bubsub.core.voxel"},
     "projection.validity.overlap_measure samples with voxel.raster.coverage: the mesh-to-mask conversion moves "
     "into core/projection with the renaming of the two raster.py"),
    ({"bubsub.core.analysis", "bubsub.core.io", "bubsub.core.prep"},
     "io.scanfile converts raw counts with prep.flats, io.tables measures bubbles with analysis.shape"),
]


def _unit(name):
    for whole in WHOLE:
        if name == whole or name.startswith(whole + "."):
            return whole
    return ".".join(name.split(".")[:3])


def _owner(name, modules):
    while name and name not in modules:
        name = name.rpartition(".")[0]
    return name or None


def _walk(node, in_function=False):
    """``(node, inside a function)`` for every node below ``node``."""
    for child in ast.iter_child_nodes(node):
        yield child, in_function
        yield from _walk(child, in_function or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)))


def _imports(path, name, modules):
    """``(imported module or third-party name, line, inside a function, relative)`` of every import statement."""
    tree = ast.parse(path.read_text(), filename=str(path))
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    for node, in_function in _walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                internal = alias.name == "bubsub" or alias.name.startswith("bubsub.")
                yield (_owner(alias.name, modules) if internal else alias.name), node.lineno, in_function, False
        elif isinstance(node, ast.ImportFrom):
            source = node.module or ""
            if node.level:
                base = package
                for _ in range(node.level - 1):
                    base = base.rpartition(".")[0]
                source = f"{base}.{node.module}" if node.module else base
            if source == "bubsub" or source.startswith("bubsub."):
                targets = {f"{source}.{a.name}" if f"{source}.{a.name}" in modules else _owner(source, modules)
                           for a in node.names}
            else:
                targets = {source}
            for target in sorted(t for t in targets if t):
                yield target, node.lineno, in_function, bool(node.level)


def _all_imports():
    modules = {name: path for path, name in _modules()}
    return [(name, target, line, in_function, relative)
            for name, path in sorted(modules.items())
            for target, line, in_function, relative in _imports(path, name, modules)]


IMPORTS = _all_imports()


def _internal(target):
    return target == "bubsub" or target.startswith("bubsub.")


def _rule(name, table):
    """The entry of ``table`` for the longest package prefix of ``name``."""
    keys = [k for k in table if name == k or name.startswith(k + ".")]
    return table[max(keys, key=len)] if keys else None


def _under(name, prefixes):
    return any(name == p or name.startswith(p + ".") for p in prefixes)


def layer_violations(imports):
    """``importer -> imported (line)`` for every bubsub import its package may not make."""
    found = []
    for name, target, line, _, _ in imports:
        if not _internal(target) or _unit(target) == _unit(name):
            continue
        allowed = _rule(name, MAY_IMPORT) or ()
        banned = _rule(name, MUST_NOT_IMPORT) or ()
        if not _under(target, allowed) or _under(target, banned):
            found.append(f"{name} -> {target} (line {line})")
    return found


def unit_cycles(imports):
    """Cycles between units (sets of units), function-level imports included."""
    from test_layout import strongly_connected

    graph = {}
    for name, target, _, _, _ in imports:
        if _internal(target) and not name.endswith(".__init__") and _unit(target) != _unit(name):
            graph.setdefault(_unit(name), {})[_unit(target)] = 1
    return strongly_connected(graph)


def test_the_checks_find_what_they_look_for():
    # an invented import list: core importing clients, clients importing the CLI, a two-unit cycle, an argparse
    fake = [("bubsub.core.io.x", "bubsub.clients.pipeline.y", 3, True, False),
            ("bubsub.clients.cluster.e", "bubsub.clients.cli.args", 9, True, False),
            ("bubsub.clients.pipeline.y", "bubsub.clients.cluster.e", 1, False, False),
            ("bubsub.clients.cluster.e", "bubsub.clients.pipeline.y", 2, True, False),
            ("bubsub.service.app", "bubsub.service.jobs", 2, False, True)]
    assert layer_violations(fake) == ["bubsub.core.io.x -> bubsub.clients.pipeline.y (line 3)",
                                      "bubsub.clients.cluster.e -> bubsub.clients.cli.args (line 9)"]
    assert unit_cycles(fake) == [{"bubsub.clients.pipeline", "bubsub.clients.cluster"}]
    assert _unit("bubsub.core.projection.backends.raster") == "bubsub.core.projection"
    assert _unit("bubsub.core.metrics") == "bubsub.core.metrics" and _unit("bubsub.service.routes.jobs") == "bubsub.service"


def test_each_package_imports_only_the_layers_below_it():
    bad = layer_violations(IMPORTS)
    assert not bad, "imports across the layers (docs/architecture.md, Layers):\n" + "\n".join(bad)


def test_no_cycles_between_sub_packages():
    cycles = unit_cycles(IMPORTS)
    allowed = [units for units, _ in UNIT_CYCLES_ALLOWED]
    stale = [sorted(c) for c in allowed if c not in cycles]
    assert not stale, f"these allowed cycles are gone: remove them from UNIT_CYCLES_ALLOWED: {stale}"
    cycles = [c for c in cycles if c not in allowed]
    detail = []
    for comp in cycles:
        edges = sorted({f"{n} -> {t} (line {ln})" for n, t, ln, _, _ in IMPORTS
                        if _internal(t) and _unit(n) in comp and _unit(t) in comp and _unit(n) != _unit(t)})
        detail.append("; ".join(edges))
    assert not cycles, "sub-packages that import each other (move the shared function down a layer):\n" + \
        "\n".join(detail)


def test_imports_are_absolute():
    relative = [f"{name} (line {line})" for name, _, line, _, rel in IMPORTS if rel]
    assert not relative, "relative imports (write `from bubsub.x.y import z`):\n" + "\n".join(relative)


@pytest.mark.parametrize("package", NO_ARGPARSE)
def test_no_argument_parsing_below_the_cli(package):
    users = sorted({name for name, target, _, _, _ in IMPORTS if target == "argparse" and _under(name, (package,))})
    assert not users, f"argparse below the CLI (move the options to bubsub.clients.cli): {users}"
