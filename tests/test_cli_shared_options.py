"""``bubsub reconstruct`` and ``bubsub reconstruct4d`` accept and refuse the options they share alike."""

import pytest

from bubsub.clients.cli.main import build_parser

#: (option, value, what the command line means by it: the parsed value, or the words of its refusal)
CASES = [
    ("--iterations", "7", 7),
    ("--iterations", "0", 0),
    ("--iterations", "-1", "must be 0 or a positive integer"),
    ("--iterations", "2.5", "must be an integer"),
    ("--levels", "3", 3),
    ("--levels", "-2", "must be 0 or a positive integer"),
    ("--levels", "x", "must be an integer"),
    ("--control-points", "42", 42),
    ("--control-points", "0", "must be a positive integer"),
    ("--facet-pixels", "0.5", 0.5),
    ("--facet-pixels", "wide", "invalid float value"),
    ("--holdout", "odd", "odd"),
    ("--holdout", "third", "invalid choice"),
    ("--slabs", "auto", None),
    ("--slabs", "3", 3),
    ("--slabs", "0", "must be a positive integer"),
    ("--slab-halo", "12", 12),
    ("--slab-halo", "-4", "must be a positive integer"),
    ("--workers", "0", "must be a positive integer"),
]


def _parse(capsys, command, scan, out, option, value):
    """``(parsed value, None)`` or ``(None, the refusal after 'error:')`` of ``bubsub COMMAND ... OPTION VALUE``."""
    try:
        args = build_parser().parse_args([command, str(scan), "--out", str(out), option, value])
    except SystemExit as refused:
        assert refused.code == 2
        # "bubsub COMMAND: error: MESSAGE (bubsub COMMAND --help lists the options)": the message alone
        return None, capsys.readouterr().err.split("error:", 1)[1].split(f"(bubsub {command} --help")[0].strip()
    return getattr(args, option.lstrip("-").replace("-", "_")), None


@pytest.mark.parametrize("option, value, meaning", CASES)
def test_both_commands_read_a_shared_option_alike(tmp_path, capsys, option, value, meaning):
    scan = tmp_path / "scan.h5"
    scan.write_bytes(b"")  # the parsers only check that it exists
    got = {c: _parse(capsys, c, scan, tmp_path / "rec", option, value) for c in ("reconstruct", "reconstruct4d")}
    (v1, e1), (v2, e2) = got["reconstruct"], got["reconstruct4d"]
    if isinstance(meaning, str) and e1 is not None:
        assert meaning in e1 and e1 == e2, got
    else:
        assert e1 is None and e2 is None, got
        assert v1 == v2 == meaning and type(v1) is type(v2)


def test_the_shared_defaults_are_the_same():
    commands = build_parser()._subparsers._group_actions[0].choices
    a, b = commands["reconstruct"], commands["reconstruct4d"]
    shared = {"--iterations", "--control-points", "--levels", "--facet-pixels", "--holdout", "--quiet", "--slabs",
              "--slab-halo", "--workers", "--scheduler", "--scheduler-file", "--dashboard", "--out", "--overwrite"}
    for option in shared:
        x, y = (next(act for act in p._actions if option in act.option_strings) for p in (a, b))
        assert (x.default, x.type, x.choices, x.nargs) == (y.default, y.type, y.choices, y.nargs), option
    assert a.get_default("iterations") == b.get_default("iterations") == 80  # the paper's
