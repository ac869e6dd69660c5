"""Mesh file checks that the loaders of trimesh skip: PLY and OFF data against their headers, and OBJ relative
face indices (`datasets.meshes.load_mesh` calls them before trimesh reads a file).

trimesh's ASCII PLY reader takes a short file without a word (a header of 5,000 vertices over 2,500 rows gives
2,500 points), its OFF reader does the same, and it reads an OBJ face's negative index as counting from the end of
the whole file rather than from the last vertex read. Each check raises a one-line ValueError naming the file and
the first disagreement.
"""
from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np

__all__ = ["check_ply", "check_off", "obj_with_absolute_indices"]

_RELATIVE_FACE = re.compile(rb"(?m)^[ \t]*f[ \t][^\n]*?(?<![^\s/])-\d")


def obj_with_absolute_indices(path: Path) -> bytes | None:
    """The OBJ file's bytes with relative (negative) face indices made absolute, or None when it has none.

    OBJ lets a face name its corners counting back from the last vertex read (`f -3 -2 -1`); trimesh reads
    them as counting from the end of the whole file. Written here because no library at hand reads them right;
    only files with a negative face index pay for this pass. Texture and normal indices (`v/vt/vn`) count
    back over their own lists."""
    data = path.read_bytes()
    if _RELATIVE_FACE.search(data) is None:
        return None
    counts = {b"v": 0, b"vt": 0, b"vn": 0}
    kinds = (b"v", b"vt", b"vn")
    out = []
    for number, line in enumerate(data.splitlines(), start=1):
        words = line.split()
        if words and words[0] in counts:
            counts[words[0]] += 1
        elif words and words[0] == b"f":
            corners = []
            for word in words[1:]:
                parts = word.split(b"/")
                for k, part in enumerate(parts[:3]):
                    if part.startswith(b"-"):
                        try:
                            parts[k] = str(counts[kinds[k]] + 1 + int(part)).encode()
                        except ValueError:
                            raise ValueError(f"line {number}: bad face index {part.decode(errors='replace')!r}")
                        if int(parts[k]) < 1:
                            raise ValueError(f"line {number}: face index {part.decode()} reaches before the first "
                                             f"{kinds[k].decode()} line")
                corners.append(b"/".join(parts))
            line = b"f " + b" ".join(corners)
        out.append(line)
    return b"\n".join(out) + b"\n"


_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
              "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
              "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}


def _ply_header(path: Path, data: bytes):
    """(format, [(element, count, [(name, dtype or (count dtype, item dtype))])], data offset)."""
    if not data.startswith(b"ply"):
        raise ValueError(f"{path}: not a PLY file (no 'ply' magic line)")
    end = data.find(b"end_header")
    if end < 0:
        raise ValueError(f"{path}: PLY header has no 'end_header' line")
    nl = data.find(b"\n", end)
    start = len(data) if nl < 0 else nl + 1
    try:
        lines = data[:end].decode("ascii").splitlines()[1:]
    except UnicodeDecodeError:
        raise ValueError(f"{path}: PLY header is not ASCII text") from None
    fmt, elements = None, []
    for number, line in enumerate(lines, start=2):
        words = line.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        bad = ValueError(f"{path}: malformed PLY header line {number}: {' '.join(words)[:80]!r}")
        if words[0] == "format":
            if len(words) < 2 or words[1] not in ("ascii", "binary_little_endian", "binary_big_endian"):
                raise bad
            fmt = words[1]
        elif words[0] == "element":
            if len(words) != 3 or not words[2].isdigit():
                raise bad
            elements.append((words[1], int(words[2]), []))
        elif words[0] == "property":
            if not elements:
                raise ValueError(f"{path}: PLY header line {number} declares a property before any element")
            if len(words) == 3 and words[1] in _PLY_TYPES:
                elements[-1][2].append((words[2], _PLY_TYPES[words[1]]))
            elif (len(words) == 5 and words[1] == "list" and words[2] in _PLY_TYPES
                  and words[3] in _PLY_TYPES and _PLY_TYPES[words[2]][0] in "iu"):
                elements[-1][2].append((words[4], (_PLY_TYPES[words[2]], _PLY_TYPES[words[3]])))
            else:
                raise bad
        else:
            raise bad
    if fmt is None:
        raise ValueError(f"{path}: PLY header has no 'format' line")
    return fmt, elements, start


def _ply_ascii_rows(path: Path, body: bytes, elements) -> None:
    rows = [r.split() for r in body.splitlines() if r.strip()]
    pos = 0
    for name, count, props in elements:
        block = rows[pos:pos + count]
        if len(block) < count:
            raise ValueError(f"{path}: PLY header declares {count} '{name}' elements but the file holds "
                             f"only {len(block)}")
        if all(isinstance(dt, str) for _, dt in props):
            sizes = np.fromiter((len(r) for r in block), np.int64, len(block))
            wrong = np.flatnonzero(sizes != len(props))
            if len(wrong):
                raise ValueError(f"{path}: PLY '{name}' element {int(wrong[0])} has {int(sizes[wrong[0]])} values, "
                                 f"its header declares {len(props)} properties")
        else:
            for i, row in enumerate(block):
                at = 0
                for _, dt in props:
                    if isinstance(dt, str):
                        at += 1
                    else:
                        try:
                            n = int(row[at])
                        except (IndexError, ValueError):
                            n = -1
                        if n < 0:
                            at = -1
                            break
                        at += 1 + n
                if at != len(row):
                    raise ValueError(f"{path}: PLY '{name}' element {i} does not match its header's "
                                     f"properties ({len(row)} values)")
        pos += count
    if pos < len(rows):
        raise ValueError(f"{path}: PLY file holds {len(rows) - pos} data lines more than its header declares")


def _uniform_list_rows(body: bytes, pos: int, count: int, props, endian: str) -> int:
    """End offset of an element with one list property whose rows all have the first row's length, else 0."""
    lists = [i for i, (_, dt) in enumerate(props) if not isinstance(dt, str)]
    if count == 0 or len(lists) != 1:
        return 0
    k = lists[0]
    before = sum(np.dtype(dt).itemsize for _, dt in props[:k])
    after = sum(np.dtype(dt).itemsize for _, dt in props[k + 1:])
    cdt, idt = np.dtype(endian + props[k][1][0]), np.dtype(props[k][1][1])
    if pos + before + cdt.itemsize > len(body):
        return 0
    n = int(np.frombuffer(body, cdt, 1, pos + before)[0])
    stride = before + cdt.itemsize + n * idt.itemsize + after
    if n < 0 or pos + count * stride > len(body):
        return 0
    lengths = np.ndarray((count,), cdt, buffer=body, offset=pos + before, strides=(stride,))
    return pos + count * stride if (lengths == n).all() else 0


def _ply_binary_rows(path: Path, body: bytes, elements, endian: str) -> None:
    pos = 0
    for name, count, props in elements:
        if all(isinstance(dt, str) for _, dt in props):
            size = sum(np.dtype(dt).itemsize for _, dt in props)
            if pos + count * size > len(body):
                have = (len(body) - pos) // size if size else 0
                raise ValueError(f"{path}: PLY header declares {count} '{name}' elements but the binary data "
                                 f"holds only {max(have, 0)}")
            pos += count * size
            continue
        if _uniform_list_rows(body, pos, count, props, endian):
            pos = _uniform_list_rows(body, pos, count, props, endian)
            continue
        for i in range(count):  # list properties whose lengths vary: walk the rows
            for _, dt in props:
                if isinstance(dt, str):
                    pos += np.dtype(dt).itemsize
                    continue
                cdt = np.dtype(endian + dt[0])
                if pos + cdt.itemsize > len(body):
                    pos = len(body) + 1
                    break
                n = int(np.frombuffer(body, cdt, 1, pos)[0])
                pos += cdt.itemsize + n * np.dtype(dt[1]).itemsize
            if pos > len(body):
                raise ValueError(f"{path}: PLY header declares {count} '{name}' elements but the binary data "
                                 f"holds only {i}")
    if pos < len(body):
        raise ValueError(f"{path}: PLY binary data has {len(body) - pos} bytes more than its header declares")


def check_ply(path: str | os.PathLike) -> dict[str, int]:
    """Check a PLY file's data against its header: every element count, row and (binary) byte.

    trimesh's ASCII reader takes a short file without a word (a header of 5,000 vertices over 2,500 rows
    gives 2,500 points), so loaders call this first.

    Args:
        path: a .ply file.

    Returns:
        {element name: count} as the header declares them.

    Raises:
        ValueError: one line naming the file and the first disagreement, or a missing 'vertex' element.
    """
    path = Path(path)
    data = path.read_bytes()
    fmt, elements, start = _ply_header(path, data)
    counts = {name: count for name, count, _ in elements}
    if "vertex" not in counts:
        raise ValueError(f"{path}: PLY header declares no 'vertex' element")
    body = data[start:]
    if fmt == "ascii":
        _ply_ascii_rows(path, body, elements)
    else:
        _ply_binary_rows(path, body, elements, "<" if fmt == "binary_little_endian" else ">")
    return counts


def check_off(path: str | os.PathLike) -> tuple[int, int]:
    """Check an OFF file's vertex and face lines against the counts in its header (as trimesh reads it:
    '#' comments and blank lines ignored, one vertex or face a line).

    Returns:
        (vertices, faces) as the header declares them.

    Raises:
        ValueError: one line naming the file and the first disagreement.
    """
    path = Path(path)
    try:
        text = path.read_bytes().decode("utf-8")
    except UnicodeDecodeError:
        raise ValueError(f"{path}: not an OFF file (not text)") from None
    lines = [line.split("#", 1)[0].strip() for line in text.splitlines()]
    lines = [line for line in lines if line]
    head = re.match(r"^C?OFF(?=\s|$)", lines[0]) if lines else None
    if head is None:
        raise ValueError(f"{path}: not an OFF file (no 'OFF' header)")
    rest = lines[0][head.end():].split()
    body = lines[1:] if not rest else [" ".join(rest)] + lines[1:]
    counts = body[0].split() if body else []
    if len(counts) < 2 or not all(c.isdigit() for c in counts[:3]):
        raise ValueError(f"{path}: OFF header has no valid vertex/face count line")
    nv, nf = int(counts[0]), int(counts[1])
    ne = int(counts[2]) if len(counts) > 2 else 0
    data = body[1:]
    if len(data) < nv:
        raise ValueError(f"{path}: OFF header declares {nv} vertices but the file holds only {len(data)} lines")
    short = [i for i, line in enumerate(data[:nv]) if len(line.split()) < 3]
    if short:
        raise ValueError(f"{path}: OFF vertex {short[0]} has fewer than 3 coordinates")
    faces = data[nv:nv + nf]
    if len(faces) < nf:
        raise ValueError(f"{path}: OFF header declares {nf} faces but the file holds only {len(faces)}")
    for i, line in enumerate(faces):
        words = line.split()
        if not words[0].isdigit() or len(words) < int(words[0]) + 1:
            raise ValueError(f"{path}: OFF face {i} does not list the vertex count it declares")
    extra = len(data) - nv - nf
    if extra > ne:
        raise ValueError(f"{path}: OFF file holds {extra} lines more than its header declares")
    return nv, nf
