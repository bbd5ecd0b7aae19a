"""The docs say what is, and every measured figure says how to get it again.

No commit hashes or references to how the code came about (docs, code
comments and docstrings describe the present code; its history is git's);
every table of measured figures (DDI, seconds, memory, MSE, counts of found
bubbles) has in its section, or in its own cells, the command that produces it.
"""

import ast
import io
import re
import tokenize
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = sorted((ROOT / "docs").glob("*.md")) + [ROOT / "README.md"]

#: 7-40 hex digits with at least one letter and one digit (a short or full commit hash; numbers have no letters)
HASH = re.compile(r"\b(?=[0-9a-f]*[a-f])(?=[0-9a-f]*[0-9])[0-9a-f]{7,40}\b")
#: a revision named by a word that says it is one, whatever its digits
NAMED_REVISION = re.compile(r"\b(?:commit|revision|git archive)\s+[0-9a-f]{7,40}\b", re.I)
HISTORY = ("at commit", "before these changes", "before this change", "before these three",
           "this session", "the issue's", "issue #", "was tried", "earlier run gave", "on an earlier run", "in a first run",
           "the lead's", "the time ran out")
#: where the code's comments and docstrings are read
SOURCES = [ROOT / name for name in ("core", "clients", "service", "bench")]

#: a table header with measured quantities
MEASURED = re.compile(r"\bDDI\b|seconds|\bs\b|\bs \(|MiB|\bMB\b|MSE|wall|CPU|found|spurious", re.I)
#: a command that produces figures: in backticks or at the start of a line of a code block
COMMAND = re.compile(r"`(?:bubsub [a-z]|python -m bubsub|nice |run_fig6|make )|^(?:bubsub|python -m bubsub|nice)\b",
                     re.M)


def _tables(text):
    """``(line number, header, section text before it and the table itself)`` of each markdown table."""
    lines = text.splitlines()
    i = 0
    while i < len(lines):
        if lines[i].startswith("|") and i + 1 < len(lines) and re.fullmatch(r"\|[\s:|-]+\|", lines[i + 1].strip()):
            j = i
            while j < len(lines) and lines[j].startswith("|"):
                j += 1
            before = "\n".join(lines[:i])
            heading = before.rfind("\n#")
            yield i + 1, lines[i], (before[heading:] if heading >= 0 else before) + "\n".join(lines[i:j])
            i = j
        else:
            i += 1


@pytest.mark.parametrize("doc", DOCS, ids=lambda p: p.name)
def test_no_commit_hashes_or_history(doc):
    text = doc.read_text()
    for n, line in enumerate(text.splitlines(), 1):
        assert not HASH.search(line), f"{doc.name}:{n}: {HASH.search(line).group()} looks like a commit hash"
        assert not NAMED_REVISION.search(line), f"{doc.name}:{n}: names a revision"
        low = line.lower()
        for words in HISTORY:
            assert words not in low, f"{doc.name}:{n}: {words!r} (say what is and why, in the present tense)"


def comment_lines(source):
    """``(line number, text)`` of every comment and docstring line of Python ``source`` (no other strings)."""
    out = [(tok.start[0], tok.string) for tok in tokenize.generate_tokens(io.StringIO(source).readline)
           if tok.type == tokenize.COMMENT]
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)) and node.body:
            first = node.body[0]
            if isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant) and isinstance(first.value.value,
                                                                                                  str):
                out += [(first.lineno + i, line) for i, line in enumerate(first.value.value.splitlines())]
    return sorted(out)


def history_in(text):
    """The first reason ``text`` (one line) tells history rather than what is: a commit hash, a named revision
    or one of :data:`HISTORY`; None when it tells none."""
    if HASH.search(text):
        return f"{HASH.search(text).group()} looks like a commit hash"
    if NAMED_REVISION.search(text):
        return "names a revision"
    low = text.lower()
    return next((f"{words!r} (say what is and why, in the present tense)" for words in HISTORY if words in low), None)


@pytest.mark.parametrize("folder", SOURCES, ids=lambda p: p.name)
def test_no_history_in_code_comments_or_docstrings(folder):
    found = []
    for path in sorted(folder.rglob("*.py")):
        for n, line in comment_lines(path.read_text()):
            why = history_in(line)
            if why:
                found.append(f"{path.relative_to(ROOT)}:{n}: {why}")
    assert not found, "\n".join(found)


@pytest.mark.parametrize("doc", DOCS, ids=lambda p: p.name)
def test_every_table_of_measured_figures_names_its_command(doc):
    for line, header, section in _tables(doc.read_text()):
        if MEASURED.search(header):
            assert COMMAND.search(section), f"{doc.name}:{line}: {header[:80]} has no command that produces it"


def test_the_checks_catch_what_they_look_for():
    assert HASH.search("measured at 4a57951 on") and HASH.search("c212297")
    assert not HASH.search("4294967296 bytes") and not HASH.search("deadline accepted")
    assert NAMED_REVISION.search("at commit 3230338")
    code = ('"""Module.\n\nMeasured at 4a57951."""\n'
            'x = "before this change"  # a string, not a comment\n'
            'def f():\n'
            '    """The lead\'s choice."""\n'
            '    return 1  # was tried and not kept\n')
    told = [(n, history_in(text)) for n, text in comment_lines(code) if history_in(text)]
    assert [n for n, _ in told] == [3, 6, 7] and "commit hash" in told[0][1]
    for legit in ("# the lead bubble of a chain", "# an issue of the flat field", "# deadline accepted",
                  "# replace the results of an earlier run in --out", "# 4294967296 bytes"):
        assert history_in(legit) is None, legit
    text = "## T\n\nOn foam2d:\n\n| case | DDI |\n|---|---|\n| a | 0.1 |\n"
    assert not COMMAND.search(next(_tables(text))[2])
    assert COMMAND.search(next(_tables(text.replace("On foam2d", "`bubsub evaluate rec sim`")))[2])


def test_the_parameter_tables_are_the_benchmarks():
    """docs/parameters.md's measured examples are the cases ``python -m bubsub.bench parameters`` runs."""
    from bubsub.bench.parameters import CASES

    text = (ROOT / "docs" / "parameters.md").read_text()
    text = text[text.index("## Measured examples"):]
    assert "python -m bubsub.bench parameters --dim 2" in text and "python -m bubsub.bench parameters --dim 3" in text
    tables = [section for _, header, section in _tables(text) if header.startswith("| arguments | DDI |")]
    assert len(tables) == 2
    for ndim, section in zip((2, 3), tables):
        table = section[section.rindex("| arguments | DDI |"):]  # the section may hold the other table too
        rows = [line for line in table.splitlines()[2:] if line.startswith("| ")]
        cases = [re.match(r"\| `?([^`|]*?)`?(?: \(default\))? \|", row).group(1) for row in rows]
        assert [c if c != "(defaults)" else "" for c in cases] == CASES[ndim][1], ndim
