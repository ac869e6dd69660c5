"""Output files: atomic writes that honour the umask, and full-precision mesh writers.

Every output is written under a temporary name beside its target and renamed when complete (no
half-written files), and gets the mode a plain `open()` would give it (0o666, or 0o777 for a folder, less
the umask) rather than tempfile's private 0o600 / 0o700, so colleagues sharing a machine can read results.

Shape letters: V vertices, F faces.
"""
from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path

import numpy as np

__all__ = ["atomic_path", "write_text", "write_mesh", "honour_umask", "current_umask", "MESH_SUFFIXES"]

#: Suffixes `write_mesh` writes.
MESH_SUFFIXES = (".obj", ".ply", ".off", ".stl")


def current_umask() -> int:
    """The process umask, read without changing it where Linux allows (/proc), else by a set-and-restore."""
    with contextlib.suppress(OSError, ValueError):
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    mask = os.umask(0o022)  # no way to read it otherwise; restored at once
    os.umask(mask)
    return mask


def honour_umask(path: str | os.PathLike) -> None:
    """Give a file made by `tempfile.mkstemp` (0o600) or a folder made by `mkdtemp` (0o700) the mode plain
    `open()` / `mkdir()` would have given it: 0o666 (0o777 for a folder) less the umask."""
    full = 0o777 if os.path.isdir(path) else 0o666
    os.chmod(path, full & ~current_umask())


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike):
    """Yields a temporary path in the target's folder; on success it is renamed to `path`, else removed.

    The temporary file already exists (empty) with the umask's mode, so writers that open it keep that."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=path.suffix + ".tmp", dir=path.parent)
    os.close(fd)
    try:
        honour_umask(tmp)
        yield Path(tmp)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def write_text(path: str | os.PathLike, text: str) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(text)


# ------------------------------------------------------------------------------------------------ meshes

def _arrays(mesh) -> tuple[np.ndarray, np.ndarray]:
    """(V, 3) float64 vertices and (F, 3) int64 faces ((0, 3) for a point cloud) of a trimesh object."""
    verts = np.asarray(mesh.vertices, dtype=np.float64).reshape(-1, 3)
    faces = getattr(mesh, "faces", None)
    faces = np.zeros((0, 3), np.int64) if faces is None else np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    if len(faces) and (faces.min() < 0 or faces.max() >= len(verts)):
        raise ValueError(f"mesh faces index vertices outside [0, {len(verts)})")
    return verts, faces


def _float_rows(prefix: str, values: np.ndarray) -> str:
    # repr() is Python's shortest string that reads back to the same float64: no digits lost, none wasted.
    return "".join(f"{prefix}{x!r} {y!r} {z!r}\n" for x, y, z in values.tolist())


def _obj(verts: np.ndarray, faces: np.ndarray) -> bytes:
    body = _float_rows("v ", verts) + "".join(f"f {a} {b} {c}\n" for a, b, c in (faces + 1).tolist())
    return body.encode("ascii")


def _off(verts: np.ndarray, faces: np.ndarray) -> bytes:
    body = (f"OFF\n{len(verts)} {len(faces)} 0\n" + _float_rows("", verts)
            + "".join(f"3 {a} {b} {c}\n" for a, b, c in faces.tolist()))
    return body.encode("ascii")


def _ply(verts: np.ndarray, faces: np.ndarray) -> bytes:
    # Binary little-endian with *double* coordinates: trimesh's own PLY export stores float32, which keeps
    # 7 significant digits (a 1e-6 offset on a 1e3 coordinate, or any detail of a far-translated mesh, is lost).
    if len(faces) and faces.max() > np.iinfo(np.int32).max:
        raise ValueError(f"PLY output: {faces.max() + 1} vertices do not fit 32-bit face indices")
    header = ["ply", "format binary_little_endian 1.0", "comment written by dmesh (eval.io.write_mesh)",
              f"element vertex {len(verts)}", "property double x", "property double y", "property double z"]
    if len(faces):
        header += [f"element face {len(faces)}", "property list uchar int vertex_indices"]
    header.append("end_header\n")
    packed = np.zeros(len(faces), dtype=[("n", "u1"), ("idx", "<i4", (3,))])
    packed["n"] = 3
    packed["idx"] = faces
    return "\n".join(header).encode("ascii") + verts.astype("<f8").tobytes() + packed.tobytes()


def _stl(verts: np.ndarray, faces: np.ndarray) -> bytes:
    # ASCII STL: binary STL can only hold float32 (the format fixes it), so full precision needs text.
    if not len(faces):
        raise ValueError("STL output needs faces; write a point cloud as .ply, .obj or .off")
    tri = verts[faces]
    scale = float(np.abs(tri).max())
    unit = tri / scale if scale > 0 else tri  # normals from unit-scale corners: no overflow or underflow
    normals = np.cross(unit[:, 1] - unit[:, 0], unit[:, 2] - unit[:, 0])
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    normals = np.divide(normals, length, out=np.zeros_like(normals), where=length > 0)
    out = ["solid dmesh\n"]
    for n, t in zip(normals.tolist(), tri.tolist()):
        out.append(f"facet normal {n[0]!r} {n[1]!r} {n[2]!r}\nouter loop\n")
        out.extend(f"vertex {x!r} {y!r} {z!r}\n" for x, y, z in t)
        out.append("endloop\nendfacet\n")
    out.append("endsolid dmesh\n")
    return "".join(out).encode("ascii")


_WRITERS = {".obj": _obj, ".ply": _ply, ".off": _off, ".stl": _stl}


def write_mesh(mesh, path: str | os.PathLike) -> None:
    """Write a mesh (or a point cloud) atomically, in the format its suffix names, with full float64 precision.

    Formats: `.obj` and `.off` text with each coordinate as Python's shortest round-trip repr (reads back
    bit for bit), `.ply` binary little-endian with double coordinates and int32 face indices, `.stl` ASCII
    (binary STL is float32 by definition). Only positions and faces are written: no normals, colours or UVs.

    Args:
        mesh: anything with `vertices` (V, 3) and optionally `faces` (F, 3) integer indices into vertices
            (a `trimesh.Trimesh` or `trimesh.PointCloud`).
        path: target file; its folder is created if missing.

    Raises:
        ValueError: unsupported suffix, face indices out of range, or faces for STL missing.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in _WRITERS:
        raise ValueError(f"{path}: cannot write mesh format {suffix or '(none)'!r}; use one of "
                         f"{', '.join(MESH_SUFFIXES)}")
    verts, faces = _arrays(mesh)
    data = _WRITERS[suffix](verts, faces)
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
