"""Runs benchmarks by name, each in a fresh subprocess: `python -m eval.bench wdt probability`, or `all`."""
from __future__ import annotations

import argparse
import importlib
import pkgutil
import subprocess
import sys

import eval.bench as pkg

SKIP = {"common", "surface_variants", "__main__"}


def available() -> list[str]:
    return sorted(m.name for m in pkgutil.iter_modules(pkg.__path__) if m.name not in SKIP)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m eval.bench")
    parser.add_argument("names", nargs="+", help=f"benchmarks to run: {', '.join(available())} or all")
    parser.add_argument("--out", default="reports", help="folder for the tables (default: reports)")
    parser.add_argument("--quick", action="store_true", help="smaller grid and fewer repeats (smoke run)")
    parser.add_argument("--in-process", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    names = available() if args.names == ["all"] else args.names
    unknown = [n for n in names if n not in available()]
    if unknown:
        print(f"eval.bench: error: unknown benchmark {', '.join(unknown)}; choose from {', '.join(available())}",
              file=sys.stderr)
        return 2
    if args.in_process:
        for name in names:
            importlib.import_module(f"eval.bench.{name}").main(out=args.out, quick=args.quick)
        return 0
    failed = []
    for name in names:
        cmd = [sys.executable, "-m", "eval.bench", name, "--out", args.out, "--in-process"]
        cmd += ["--quick"] if args.quick else []
        print(f"== bench {name}", flush=True)
        if subprocess.call(cmd) != 0:  # option-safe: names are checked against the bench modules above
            failed.append(name)
    if failed:
        print(f"eval.bench: error: failed: {', '.join(failed)}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
