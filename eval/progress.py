"""Progress bars for the CLI and the harness (the library never shows any)."""
from __future__ import annotations

import sys

from tqdm.auto import tqdm

#: Set by the CLI's --quiet flag.
QUIET = False


def progress(iterable=None, **kwargs):
    """tqdm, disabled when quiet or when stderr is not a terminal (CI logs stay readable)."""
    kwargs.setdefault("disable", QUIET or not sys.stderr.isatty())
    kwargs.setdefault("dynamic_ncols", True)
    return tqdm(iterable, **kwargs)
