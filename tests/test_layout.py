"""The package layout: README imports work, no import cycles, modules stay small."""

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


def test_every_module_imports_first_without_a_cycle():
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
    res = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, cwd=ROOT)
    assert res.returncode == 0, res.stdout + res.stderr


@pytest.mark.parametrize("path,name", list(_modules()), ids=lambda x: str(x) if isinstance(x, str) else "")
def test_large_modules_state_why(path, name):
    n = len(path.read_text().splitlines())
    if n <= MAX_LINES:
        return
    doc = ast.get_docstring(ast.parse(path.read_text())) or ""
    assert "on purpose" in doc, f"{name} has {n} lines; split it or say at its top why it is one module ('on purpose')"
