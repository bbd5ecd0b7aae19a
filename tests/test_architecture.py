"""docs/architecture.md matches the code: every package folder is named, every quoted signature exists."""

import importlib
import inspect
import pathlib
import re

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
DOC = (ROOT / "docs" / "architecture.md").read_text()
SOURCES = ("core", "clients", "service", "bench")


def _package_folders():
    for top in SOURCES:
        for init in sorted((ROOT / top).rglob("__init__.py")):
            yield init.parent.relative_to(ROOT).as_posix() + "/"


def _quoted_signatures():
    block = DOC.split("## Signatures", 1)[1]
    code = re.search(r"```\n(.*?)```", block, flags=re.S).group(1)
    return [line.strip() for line in code.splitlines() if line.strip()]


def _resolve(dotted):
    """The object a dotted name names: the longest importable module prefix, then attributes."""
    parts = dotted.split(".")
    for k in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:k]))
        except ImportError:
            continue
        for name in parts[k:]:
            obj = getattr(obj, name)
        return obj
    raise ImportError(dotted)


def _render(obj):
    """``inspect.signature`` as the doc writes it: no annotations, no private parameters, callables by name."""
    params = []
    for p in inspect.signature(obj).parameters.values():
        if p.name.startswith("_"):
            continue
        default = p.default
        if default is not inspect.Parameter.empty and callable(default) and hasattr(default, "__name__"):
            default = _Name(default.__name__)
        params.append(p.replace(annotation=inspect.Parameter.empty, default=default))
    return str(inspect.Signature(params))


class _Name:
    def __init__(self, name):
        self.name = name

    def __repr__(self):
        return self.name


@pytest.mark.parametrize("folder", list(_package_folders()))
def test_every_package_folder_is_named(folder):
    assert f"`{folder}`" in DOC, f"docs/architecture.md does not name the package folder {folder}"


def test_the_doc_quotes_signatures():
    assert len(_quoted_signatures()) >= 20


@pytest.mark.parametrize("line", _quoted_signatures())
def test_quoted_signature_is_the_codes(line):
    name, args = re.fullmatch(r"([\w.]+)(\(.*\))", line).groups()
    assert _render(_resolve(name)) == args, f"{name}: the code says {_render(_resolve(name))}"


def test_the_renderer_sees_a_changed_signature():
    def f(a, b=2, *, c=None, _private=0):
        pass

    assert _render(f) == "(a, b=2, *, c=None)"
    assert _render(f) != "(a, b=3, *, c=None)"
