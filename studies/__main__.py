"""Runs studies by name, each in a fresh subprocess: `python -m studies lids debris`. There is no `all`: each
takes minutes to hours, and several read the input cache or the results store of `runs/paper`. Reports go to
studies/reports/ unless `--out` says otherwise."""
from __future__ import annotations

import sys

from eval.bench.__main__ import main as _main

#: Modules here that are not studies: `surface_variants` holds what `lids` and `debris` share.
SKIP = frozenset({"surface_variants", "__main__"})


def main(argv=None) -> int:
    return _main(argv, package="studies", skip=SKIP, what="study", default_out="studies/reports", allow_all=False,
                 regenerate="python -m studies")


if __name__ == "__main__":
    sys.exit(main())
