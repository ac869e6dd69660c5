"""Plain forms of values for the results store and the log: an exception as one line, any value as JSON data."""
from __future__ import annotations

import dataclasses


def one_line(exc: BaseException) -> str:
    """`Type: message` on one line, at most 500 characters."""
    msg = " ".join(str(exc).split()) or repr(exc)
    return f"{type(exc).__name__}: {msg}"[:500]


def jsonable(obj):
    """`obj` as JSON-able data: dicts (keys as text), lists, numbers, text, booleans and None; a dataclass or an
    object with `to_dict` by its fields, an array by `tolist`, anything else as its text."""
    if hasattr(obj, "to_dict"):
        obj = obj.to_dict()
    elif dataclasses.is_dataclass(obj):
        obj = dataclasses.asdict(obj)
    if isinstance(obj, dict):
        return {str(k): jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [jsonable(v) for v in obj]
    if hasattr(obj, "tolist"):
        return obj.tolist()
    return obj if isinstance(obj, (int, float, str, bool, type(None))) else str(obj)
