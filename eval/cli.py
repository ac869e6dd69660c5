"""The `dmesh` console script.

Each subcommand is a module in `eval/commands/` defining `NAME`, `HELP`, `add_arguments(parser)` and
`run(args) -> int`; they are discovered here, so adding a command never edits this file. Failures print
one line to stderr and exit non-zero.
"""
from __future__ import annotations

import argparse
import importlib
import logging
import pkgutil
import sys

import eval.commands as commands_pkg

log = logging.getLogger("dmesh")


class CliError(Exception):
    """A user-facing failure: printed as one line, exit status 2."""


def _commands():
    found = {}
    for info in pkgutil.iter_modules(commands_pkg.__path__):
        if info.name.startswith("_"):
            continue
        mod = importlib.import_module(f"{commands_pkg.__name__}.{info.name}")
        found[mod.NAME] = mod
    return dict(sorted(found.items()))


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="dmesh", description="DMesh: differentiable meshes on the CPU, "
                                     "with a benchmark and evaluation harness.")
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more log output (-vv: debug)")
    parser.add_argument("-q", "--quiet", action="store_true", help="no progress bars, warnings only")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name, mod in _commands().items():
        p = sub.add_parser(name, help=mod.HELP, description=mod.HELP)
        mod.add_arguments(p)
        p.set_defaults(_run=mod.run)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    level = logging.WARNING if args.quiet else (logging.INFO, logging.INFO, logging.DEBUG)[min(args.verbose, 2)]
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s")
    # PyOpenGL reports platform probing (and its own shutdown) at INFO: noise for users.
    logging.getLogger("OpenGL").setLevel(max(level, logging.WARNING))
    import eval.progress

    eval.progress.QUIET = bool(args.quiet)
    try:
        return int(args._run(args) or 0)
    except KeyboardInterrupt:
        print("dmesh: interrupted", file=sys.stderr)
        return 130
    except (CliError, ValueError, FileNotFoundError, IsADirectoryError, PermissionError) as exc:
        if args.verbose >= 2:
            raise
        print(f"dmesh {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
