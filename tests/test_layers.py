"""The package's layers (docs/architecture.md, "Layers"), read from every module's syntax tree: which package may
import which, no cycles between sub-packages, absolute ``bubsub.`` imports only, and imports inside functions only
for optional extras or a reason listed here."""

import ast
import subprocess
import sys

import pytest

from test_layout import _modules, strongly_connected

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
    "matplotlib": "heavy: only figures need it", "mpl_toolkits": "matplotlib's",
    "numba": "heavy, and compiles: the kernel modules load where a kernel is first called",
    "trimesh": "heavy: only the 3D self-crossing checks and some benchmarks need it",
    "algotom": "heavy: only prepare's stripe removal and centre search need it",
    "threadpoolctl": "imported where the BLAS threads are limited, which goes on without it",
    "scipy.optimize": "heavy: not loaded by `import bubsub.core` nor `bubsub --help`",
    "scipy.sparse.linalg": "heavy: not loaded by `import bubsub.core` nor `bubsub --help`",
    "scipy.sparse.csgraph": "heavy (loads scipy.sparse.linalg): not loaded by `import bubsub.core`",
    "h5py": "heavy: a scan file's functions load it, so that `import bubsub.core` and `bubsub --help` do not",
    "skimage.filters": "heavy: Otsu's threshold loads it, so that `import bubsub.core` does not",
    "tqdm": "loads asyncio: a progress phase loads it, so that `bubsub --help` does not",
}

#: ``(importing module, third-party package)`` imported inside a function for a reason of their own.
THIRD_PARTY_ALLOWED = {
    ("bubsub.service.app", "scipy"): "scipy's own BLAS is loaded just before the server limits its threads",
}

#: Modules that ``bubsub --help`` imports for their catalogues (the experiments, the phantoms); what they run they
#: import when it runs.
START_UP = ("bubsub.clients.experiments.runner", "bubsub.clients.experiments.fig6", "bubsub.clients.pipeline.evaluation.simulation")

#: ``(importing module, imported bubsub module)`` pairs imported inside a function, each with its reason.
FUNCTION_LEVEL_ALLOWED = {
    ("bubsub.core.projection.backends", "bubsub.core.projection.backends.raster"):
        "a backend loads its compiled kernels (numba, Embree) only when it is selected",
    ("bubsub.core.projection.backends", "bubsub.core.projection.backends.embree_native"):
        "a backend loads its compiled kernels (numba, Embree) only when it is selected",
    ("bubsub.core.projection.backends", "bubsub.core.projection.backends.embreex"):
        "a backend loads its compiled kernels (numba, Embree) only when it is selected",
}


#: Cycles between units that remain, each with what breaks it.
UNIT_CYCLES_ALLOWED = []


def _optional(target):
    """Whether the third-party module ``target`` is (under) an :data:`OPTIONAL` one."""
    parts = target.split(".")
    return any(".".join(parts[:k]) in OPTIONAL for k in range(1, len(parts) + 1))


def _unit(name):
    for whole in WHOLE:
        if name == whole or name.startswith(whole + "."):
            return whole
    return ".".join(name.split(".")[:3])


def _owner(name, modules):
    while name and name not in modules:
        name = name.rpartition(".")[0]
    return name or None


def _walk(node, function=None):
    """``(node, name of the outermost function around it or None)`` for every node below ``node``."""
    for child in ast.iter_child_nodes(node):
        yield child, function
        inner = function or (child.name if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef)) else None)
        yield from _walk(child, inner)


def _imports(path, name, modules):
    """``(imported module or third-party name, line, enclosing function or None, relative)`` of every import."""
    tree = ast.parse(path.read_text(), filename=str(path))
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    for node, function in _walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                internal = alias.name == "bubsub" or alias.name.startswith("bubsub.")
                yield (_owner(alias.name, modules) if internal else alias.name), node.lineno, function, False
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
                yield target, node.lineno, function, bool(node.level)


def _all_imports():
    modules = {name: path for path, name in _modules()}
    return [(name, target, line, function, relative)
            for name, path in sorted(modules.items())
            for target, line, function, relative in _imports(path, name, modules)]


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
    graph = {}
    for name, target, _, _, _ in imports:
        if _internal(target) and not name.endswith(".__init__") and _unit(target) != _unit(name):
            graph.setdefault(_unit(name), {})[_unit(target)] = 1
    return strongly_connected(graph)


def test_the_checks_find_what_they_look_for():
    # an invented import list: core importing clients, clients importing the CLI, a two-unit cycle through a
    # function-level import, a relative import within the service
    fake = [("bubsub.core.io.x", "bubsub.clients.pipeline.y", 3, "f", False),
            ("bubsub.clients.cluster.e", "bubsub.clients.cli.args", 9, "add", False),
            ("bubsub.clients.pipeline.y", "bubsub.clients.cluster.e", 1, None, False),
            ("bubsub.clients.cluster.e", "bubsub.clients.pipeline.y", 2, "run", False),
            ("bubsub.service.app", "bubsub.service.jobs", 2, None, True)]
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


def optional_modules(imports):
    """The bubsub modules that import an :data:`OPTIONAL` module at their top: importing one of them inside a
    function keeps its extra (or its weight) optional to the importing module."""
    return {name for name, target, _, function, _ in imports
            if function is None and not _internal(target) and _optional(target)}


def lazy_bubsub_imports(imports, start_up=()):
    """``(module, imported bubsub module)`` imported inside a function without one of the reasons of the layers:
    an optional module (:func:`optional_modules`); the command line (a ``bubsub.clients.cli`` module, or one of
    :data:`START_UP` importing a module that ``bubsub --help`` does not import, ``start_up`` being those it does:
    a command imports what it runs when it runs, so that ``bubsub --help`` and a refused argument answer at once);
    or an entry of :data:`FUNCTION_LEVEL_ALLOWED`."""
    optional = optional_modules(imports)
    found = set()
    for name, target, _, function, _ in imports:
        if function is None or not _internal(target) or target in optional:
            continue
        if name.startswith("bubsub.clients.cli."):
            continue
        if name in START_UP and target not in start_up:
            continue
        found.add((name, target))
    return found


def _help_modules():
    """The modules ``bubsub --help`` imports (its parser built in a fresh interpreter)."""
    code = ("import sys\nfrom bubsub.clients.cli.main import build_parser\nbuild_parser()\n"
            "print('\\n'.join(sorted(sys.modules)))")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    return set(res.stdout.split())


@pytest.fixture(scope="module")
def help_modules():
    return _help_modules()


def test_bubsub_help_imports_no_pipeline_and_no_heavy_library(help_modules):
    # the reason the command line imports inside functions (lazy_bubsub_imports): this stays true
    heavy = {"bubsub.clients.pipeline.reconstruct", "bubsub.clients.pipeline.reconstruct4d",
             "bubsub.clients.optimise.fit", "bubsub.core.prep.pipeline", "bubsub.core.foam.column", "scipy.optimize",
             "numba", "matplotlib", "trimesh", "dask", "fastapi", "algotom", "h5py", "tqdm", "asyncio"}
    assert not heavy & help_modules, sorted(heavy & help_modules)
    assert {"bubsub.clients.cli.reconstruct", *START_UP} <= help_modules


def test_bubsub_imports_inside_functions_have_a_reason(help_modules):
    found = lazy_bubsub_imports(IMPORTS, help_modules)
    unexpected = sorted(found - set(FUNCTION_LEVEL_ALLOWED))
    assert not unexpected, ("bubsub imports inside functions (move them to the module's top; where that makes a cycle, "
                            "move the shared function down a layer):\n" + "\n".join(map(str, unexpected)))
    stale = sorted(set(FUNCTION_LEVEL_ALLOWED) - found)
    assert not stale, f"these allowed function-level imports are gone: remove them from FUNCTION_LEVEL_ALLOWED: {stale}"
    assert all(reason.strip() for reason in FUNCTION_LEVEL_ALLOWED.values())


def test_the_reasons_for_imports_inside_functions_are_narrow():
    fake = [("bubsub.core.voxel.splat", "numba", 3, None, False),
            ("bubsub.core.voxel.projector3d", "bubsub.core.voxel.splat", 9, "forward", False),
            ("bubsub.core.voxel.projector3d", "bubsub.core.voxel.grid", 12, "forward", False),
            ("bubsub.clients.cli.reconstruct", "bubsub.clients.pipeline.regions.slabs", 20, "cmd_reconstruct", False),
            ("bubsub.clients.cli.reconstruct", "bubsub.clients.pipeline.results.outputs", 40, "_finish", False),
            ("bubsub.clients.pipeline.regions.slabs", "bubsub.clients.pipeline.results.outputs", 50, "cmd_x", False)]
    fake += [("bubsub.clients.pipeline.evaluation.simulation", "bubsub.core.foam.column", 60, "simulate", False),
             ("bubsub.clients.pipeline.evaluation.simulation", "bubsub.core.io.scanfile", 70, "simulate", False)]
    assert optional_modules(fake) == {"bubsub.core.voxel.splat"}
    assert lazy_bubsub_imports(fake, {"bubsub.core.io.scanfile"}) == {
        ("bubsub.core.voxel.projector3d", "bubsub.core.voxel.grid"),
        ("bubsub.clients.pipeline.regions.slabs", "bubsub.clients.pipeline.results.outputs"),
        ("bubsub.clients.pipeline.evaluation.simulation", "bubsub.core.io.scanfile")}


def test_third_party_imports_inside_functions_are_optional_extras():
    stdlib = set(sys.stdlib_module_names)
    found = {(name, target.split(".")[0]) for name, target, _, function, _ in IMPORTS
             if function and not _internal(target) and target.split(".")[0] not in stdlib
             and not _optional(target)}
    unexpected = sorted(found - set(THIRD_PARTY_ALLOWED))
    assert not unexpected, ("third-party imports inside functions that are not optional extras (move them to the "
                            "top):\n" + "\n".join(map(str, unexpected)))
    stale = sorted(set(THIRD_PARTY_ALLOWED) - found)
    assert not stale, f"these allowed imports are gone: remove them from THIRD_PARTY_ALLOWED: {stale}"


#: Parser methods: a module calling one of them defines command-line options.
PARSER_METHODS = {"add_argument", "add_argument_group", "add_mutually_exclusive_group", "add_subparsers", "add_parser"}


def option_definers(modules):
    """The modules (of ``{name: path}``) that import argparse or call a parser's methods."""
    found = set()
    for name, path in modules.items():
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr in PARSER_METHODS:
                found.add(name)
            elif isinstance(node, ast.Import) and any(a.name == "argparse" for a in node.names):
                found.add(name)
    return found


def test_option_definers_are_found(tmp_path):
    (tmp_path / "a.py").write_text("def add(parser):\n    g = parser.add_argument_group('x')\n    g.add_argument('--n')\n")
    (tmp_path / "b.py").write_text("def f():\n    import argparse\n")
    (tmp_path / "c.py").write_text("def f(d):\n    d.add('x')\n")
    assert option_definers({n: tmp_path / f"{n}.py" for n in "abc"}) == {"a", "b"}


def test_no_command_line_options_below_the_cli():
    modules = {name: path for path, name in _modules() if _under(name, NO_ARGPARSE)}
    users = sorted(option_definers(modules))
    assert not users, f"command-line options below the CLI (move them to bubsub.clients.cli): {users}"
