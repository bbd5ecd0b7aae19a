"""``python -m bubsub.bench [projector|remote|prepare|cluster] [options]``: print benchmark tables."""

import sys


def main(argv=None):
    argv = list(sys.argv[1:] if argv is None else argv)
    name = argv.pop(0) if argv and not argv[0].startswith("-") else "projector"
    if name == "projector":
        from .projector import main as run
    elif name == "remote":
        from .remote import main as run
    elif name == "prepare":
        from .prepare import main as run
    elif name == "cluster":
        from .cluster import main as run
    else:
        print(f"unknown benchmark {name!r}; choose 'projector', 'remote', 'prepare' or 'cluster'", file=sys.stderr)
        return 2
    return run(argv)


if __name__ == "__main__":
    sys.exit(main())
