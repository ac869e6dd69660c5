"""Checks of config fields, written once; each raises ValueError naming the config class and the field."""
from __future__ import annotations


def require_positive(config, names) -> None:
    """ValueError unless every field in `names` of the dataclass instance `config` is > 0 (NaN fails)."""
    for name in names:
        if not getattr(config, name) > 0:
            raise ValueError(f"{type(config).__name__}.{name} must be positive, got {getattr(config, name)}")


__all__ = ["require_positive"]
