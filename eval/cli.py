"""The `dmesh` console script.

Each subcommand is a module in `eval/commands/` defining `NAME`, `HELP`, `add_arguments(parser)` and
`run(args) -> int`; they are discovered here, so adding a command never edits this file.

Every failure is one line on stderr, `dmesh <command>: error: <what is wrong>`, with exit status 2: argparse's
own errors (without the usage block), and the ValueError, OSError, MemoryError or `CliError` a command
raises. Commands check their inputs and output paths (`check_output_file`, `check_output_dir`) before any
work starts, so a failure leaves no partial output; an output path that is (or, a folder, holds) one of the
command's inputs is refused, so no input file is ever written.
"""
from __future__ import annotations

import argparse
import importlib
import logging
import os
import pkgutil
import sys
import warnings
from pathlib import Path

import eval.commands as commands_pkg

log = logging.getLogger("dmesh")


class CliError(Exception):
    """A user-facing failure: printed as one line, exit status 2."""


class _Parser(argparse.ArgumentParser):
    """argparse, with its errors on one line (`dmesh <command>: error: ...`) instead of the usage block."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {one_line(message)} (see {self.prog} --help)\n")


def one_line(text) -> str:
    """`text` with its whitespace (newlines included) collapsed to single spaces."""
    return " ".join(str(text).split())


# --------------------------------------------------------------------------------------------- output paths

def _nearest_existing(path: Path) -> Path:
    path = path.absolute()
    while not path.exists() and path != path.parent:
        path = path.parent
    return path


def _check_can_create(path: Path, flag: str) -> None:
    """ValueError unless `path` (absent) could be created: its nearest existing ancestor is a writable folder."""
    above = _nearest_existing(path.absolute().parent)
    if not above.is_dir():
        raise ValueError(f"{flag} {path}: {above} is a file, not a folder")
    if not os.access(above, os.W_OK | os.X_OK):
        raise ValueError(f"{flag} {path}: folder {above} is not writable")


def _same_file(a: Path, b: Path) -> bool:
    """Whether `a` and `b` name one file: the same path once links are followed, or one inode (hard links)."""
    if a.resolve() == b.resolve():
        return True
    try:
        return a.exists() and b.exists() and os.path.samefile(a, b)
    except OSError:
        return False


def _check_not_an_input(path: Path, flag: str, inputs, folder: bool) -> None:
    """ValueError when the output `path` is one of `inputs`, or (a `folder` the command writes) holds one."""
    for given in inputs:
        if given is None:
            continue
        inp = Path(given)
        if _same_file(path, inp):
            raise ValueError(f"{flag} {path}: is the input {inp}; the output would overwrite it: give another path")
        if folder and path.resolve() in inp.resolve().parents:
            raise ValueError(f"{flag} {path}: holds the input {inp}, which the output could replace: give another "
                             f"folder")


def check_output_file(path, flag: str = "-o", suffixes: tuple[str, ...] | None = None, inputs=()) -> Path:
    """`path` as a Path if a file can be written there; else ValueError naming `flag` and the problem.

    Checked before any work starts: not an existing folder, none of the command's `inputs` (also through
    links), one of `suffixes` (when given), and a writable folder to hold it (created if missing)."""
    path = Path(path)
    if path.is_dir():
        raise ValueError(f"{flag} {path}: is a folder; give a file name")
    _check_not_an_input(path, flag, inputs, folder=False)
    if suffixes is not None and path.suffix.lower() not in suffixes:
        raise ValueError(f"{flag} {path}: expected a file ending in {', '.join(suffixes)}")
    _check_can_create(path, flag)
    return path


def check_output_dir(path, flag: str = "-o", inputs=()) -> Path:
    """`path` as a Path if it is a writable folder or can be created as one, and neither is nor holds one of
    the command's `inputs` (files or folders, also through links); else ValueError."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise ValueError(f"{flag} {path}: is a file, not a folder")
    _check_not_an_input(path, flag, inputs, folder=True)
    if path.is_dir():
        if not os.access(path, os.W_OK | os.X_OK):
            raise ValueError(f"{flag} {path}: folder is not writable")
    else:
        _check_can_create(path, flag)
    return path


def _commands():
    found = {}
    for info in pkgutil.iter_modules(commands_pkg.__path__):
        if info.name.startswith("_"):
            continue
        mod = importlib.import_module(f"{commands_pkg.__name__}.{info.name}")
        found[mod.NAME] = mod
    return dict(sorted(found.items()))


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="dmesh", description="DMesh: differentiable meshes on the CPU, "
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
    # A library's warning as one line that names the command (Python prints it with its source line).
    formatwarning = warnings.formatwarning
    warnings.formatwarning = lambda message, category, *_, **__: \
        f"dmesh {args.command}: warning: {category.__name__}: {one_line(message)}\n"
    try:
        return int(args._run(args) or 0)
    except KeyboardInterrupt:
        print("dmesh: interrupted", file=sys.stderr)
        return 130
    except (CliError, ValueError, OSError, MemoryError) as exc:
        if args.verbose >= 2:
            raise
        msg = one_line(exc) or type(exc).__name__
        if isinstance(exc, MemoryError):
            msg = f"out of memory ({msg}); use smaller sizes"
        print(f"dmesh {args.command}: error: {msg}", file=sys.stderr)
        return 2
    finally:
        warnings.formatwarning = formatwarning


if __name__ == "__main__":
    sys.exit(main())
