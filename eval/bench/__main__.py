"""Runs benchmarks by name, each in a fresh subprocess: `python -m eval.bench wdt probability`, or `all`.
`make bench` runs `all --quick` into out/bench/; the committed reports/bench_*.md are the full grids."""
from __future__ import annotations

import argparse
import importlib
import pkgutil
import subprocess
import sys

SKIP = {"common", "__main__"}


def available(package: str = "eval.bench", skip: frozenset | set = frozenset(SKIP)) -> list[str]:
    """The runnable modules of `package` (every module but those in `skip`)."""
    path = importlib.import_module(package).__path__
    return sorted(m.name for m in pkgutil.iter_modules(path) if m.name not in skip)


def main(argv=None, package: str = "eval.bench", skip: frozenset | set = frozenset(SKIP), what: str = "benchmark",
         default_out: str = "reports", allow_all: bool = True, regenerate: str | None = None) -> int:
    """The runner of `python -m eval.bench` and, with its own arguments, of `python -m studies`."""
    names_ok = available(package, skip)
    parser = argparse.ArgumentParser(prog=f"python -m {package}")
    parser.add_argument("names", nargs="+", help=f"{what}s to run: {', '.join(names_ok)}"
                        + (" or all" if allow_all else ""))
    parser.add_argument("--out", default=default_out, help=f"folder for the tables (default: {default_out})")
    parser.add_argument("--quick", action="store_true", help="smaller grid and fewer repeats (smoke run)")
    parser.add_argument("--in-process", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    names = names_ok if allow_all and args.names == ["all"] else args.names
    unknown = [n for n in names if n not in names_ok]
    if unknown:
        print(f"{package}: error: unknown {what} {', '.join(unknown)}; choose from {', '.join(names_ok)}",
              file=sys.stderr)
        return 2
    if args.in_process:
        if regenerate:
            import eval.bench.common as common

            common.REGENERATE = regenerate
        for name in names:
            importlib.import_module(f"{package}.{name}").main(out=args.out, quick=args.quick)
        return 0
    failed = []
    for name in names:
        cmd = [sys.executable, "-m", package, name, "--out", args.out, "--in-process"]
        cmd += ["--quick"] if args.quick else []
        print(f"== {what} {name}", flush=True)
        if subprocess.call(cmd) != 0:  # option-safe: names are checked against the modules above
            failed.append(name)
    if failed:
        print(f"{package}: error: failed: {', '.join(failed)}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
