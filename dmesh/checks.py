"""Checks of config fields and input coordinates, written once; each raises a one-line ValueError naming the
problem (the config class and field, or the input)."""
from __future__ import annotations

import numpy as np

from dmesh.tolerances import LINE_RATIO, MAX_COORDINATE


def require_positive(config, names) -> None:
    """ValueError unless every field in `names` of the dataclass instance `config` is > 0 (NaN fails)."""
    for name in names:
        if not getattr(config, name) > 0:
            raise ValueError(f"{type(config).__name__}.{name} must be positive, got {getattr(config, name)}")


def check_coordinates(values, what: str) -> None:
    """ValueError unless every coordinate of `values` ((N, 3) floats, finite) is within `MAX_COORDINATE`.

    Inputs are raised to powers up to the fourth before they are normalised (distances, volumes, areas); past
    the limit those overflow float64 and the failure would surface far away as a traceback or a silent NaN."""
    largest = float(np.abs(np.asarray(values, np.float64)).max(initial=0.0))
    if largest > MAX_COORDINATE:
        raise ValueError(f"{what}: coordinates up to {largest:.3g} in absolute value; at most {MAX_COORDINATE:.0e} "
                         f"are supported (their powers overflow float64): scale the input down")


def check_not_a_line(points, what: str) -> None:
    """ValueError when the (N, 3) finite points lie on one line (the second principal extent below `LINE_RATIO`
    of the first): they bound no surface."""
    p = np.asarray(points, np.float64)
    if len(p) == 0 or (p == p[0]).all():
        return  # one point repeated: the callers say so in their own words
    centred = p - p.mean(axis=0)
    s = np.linalg.svd(centred / np.abs(centred).max(), compute_uv=False)
    if s[1] <= LINE_RATIO * s[0]:
        raise ValueError(f"{what}: all {len(p)} points lie on one line (no surface to reconstruct)")


__all__ = ["check_coordinates", "check_not_a_line", "require_positive"]
