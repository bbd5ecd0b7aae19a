"""Help texts and the README are complete: every command describes itself, every experiment is listed."""

import argparse
import re
from pathlib import Path

from bubsub.clients.cli import main
from bubsub.clients.cli.main import build_parser

ROOT = Path(__file__).resolve().parents[1]


def _commands():
    parser = build_parser()
    return next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices


def test_every_command_has_a_description_and_a_summary():
    commands = _commands()
    assert {"simulate", "prepare", "reconstruct", "reconstruct4d", "evaluate", "analyse", "experiment", "demo",
            "bench", "serve"} <= set(commands)
    parent = build_parser()
    summaries = {a.dest: a.help for a in next(a for a in parent._actions
                                                if isinstance(a, argparse._SubParsersAction))._choices_actions}
    for name, p in commands.items():
        # more than a line: what the command does (and, for most, what it writes)
        assert p.description and len(p.description) >= 20, name
        assert summaries.get(name), name  # its line in `bubsub --help`


def test_every_option_has_help():
    for name, p in _commands().items():
        for a in p._actions:
            if a.option_strings and a.dest != "help":
                assert a.help, (name, a.option_strings)


def test_experiment_help_lists_every_experiment(capsys):
    from bubsub.clients.cli.experiment import DYNAMIC_EXPERIMENTS
    from bubsub.clients.experiments.runner import EXPERIMENTS

    assert main(["experiment", "--help"]) == 0
    out = capsys.readouterr().out
    listed = set(re.findall(r"^  (\S+) +\S", out[out.index("experiments (the setting swept"):], re.M))
    names = set(EXPERIMENTS) | set(DYNAMIC_EXPERIMENTS)
    assert names == listed, (names, listed)
    choices = next(a for a in _commands()["experiment"]._actions if a.dest == "name").choices
    assert set(choices) == names


def test_readme_shows_every_command_and_links_every_doc():
    readme = (ROOT / "README.md").read_text()
    for name in _commands():
        assert re.search(rf"`?bubsub {name}\b", readme), name
    assert re.search(r"^bubsub analyse \S+ --out", readme, re.M)  # an example, not only a mention
    for doc in sorted((ROOT / "docs").glob("*.md")):
        assert f"](docs/{doc.name}" in readme, doc.name
