"""The docs say what is, and every measured figure says how to get it again.

No commit hashes or references to how the code came about (docs describe the
present code); every table of measured figures (DDI, seconds, memory, MSE,
counts of found bubbles) has in its section, or in its own cells, the command
that produces it.
"""

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = sorted((ROOT / "docs").glob("*.md")) + [ROOT / "README.md"]

#: 7-40 hex digits with at least one letter and one digit (a short or full commit hash; numbers have no letters)
HASH = re.compile(r"\b(?=[0-9a-f]*[a-f])(?=[0-9a-f]*[0-9])[0-9a-f]{7,40}\b")
#: a revision named by a word that says it is one, whatever its digits
NAMED_REVISION = re.compile(r"\b(?:commit|revision|git archive)\s+[0-9a-f]{7,40}\b", re.I)
HISTORY = ("at commit", "before these changes", "before this change", "before these three", "this session",
           "the issue's", "was tried", "earlier run gave")

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


@pytest.mark.parametrize("doc", DOCS, ids=lambda p: p.name)
def test_every_table_of_measured_figures_names_its_command(doc):
    for line, header, section in _tables(doc.read_text()):
        if MEASURED.search(header):
            assert COMMAND.search(section), f"{doc.name}:{line}: {header[:80]} has no command that produces it"


def test_the_checks_catch_what_they_look_for():
    assert HASH.search("measured at 4a57951 on") and HASH.search("c212297")
    assert not HASH.search("4294967296 bytes") and not HASH.search("deadline accepted")
    assert NAMED_REVISION.search("at commit 3230338")
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
