"""Shared test helpers, imported by the test modules (pytest puts tests/ on sys.path): array comparison,
input generators, the shared test meshes, and the checks on closed output surfaces. Fixtures live in
conftest.py."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

#: Real test meshes live beside the checkout (never copied into the repository).
SHARED_MESHES = Path(__file__).resolve().parents[1].parent / "shared" / "meshes"


def assert_close(actual, expected, rtol: float = 0.0, atol: float = 0.0, what: str = ""):
    """|actual - expected| <= atol + rtol * max|expected| everywhere; on failure, reports the worst element
    (STYLE rule 17). Tensors (detached) or arrays of the same shape."""
    a = np.asarray(actual.detach() if isinstance(actual, torch.Tensor) else actual, np.float64)
    e = np.asarray(expected.detach() if isinstance(expected, torch.Tensor) else expected, np.float64)
    assert a.shape == e.shape, f"{what}: shape {a.shape} != {e.shape}"
    if a.size == 0:
        return
    err = np.abs(a - e)
    scale = np.abs(e).max()
    tol = atol + rtol * scale
    k = np.unravel_index(int(np.argmax(err)), err.shape)
    assert err.max() <= tol, (f"{what}: max abs diff {err.max():.3g} > {tol:.3g} at {k} "
                              f"(actual {a[k]:.6g}, expected {e[k]:.6g}, max rel {err.max() / max(scale, 1e-300):.3g})")


# ------------------------------------------------------------------------------------------------ inputs

def spacing_weights(rng: np.random.Generator, n: int, scale: float = 0.1) -> np.ndarray:
    """Weights in [0, scale * h^2] with h = n^(-1/3): relative to the point spacing, so few are hidden."""
    return rng.random(n) * scale * n ** (-2.0 / 3.0)


def leaves(p, w):
    """Points and weights as float64 leaf tensors that collect gradients."""
    return torch.tensor(p, requires_grad=True), torch.tensor(w, requires_grad=True)


def shared_mesh(rel: str) -> Path:
    path = SHARED_MESHES / rel
    if not path.exists():
        pytest.skip(f"shared test mesh {rel} not found beside the checkout")
    return path


def fake_views(v=2, res=8, **changes):
    """A MultiView with a lit square in every view (no OpenGL), for the input checks."""
    from datasets import capture as cap

    depth = np.zeros((v, res, res), np.float32)
    depth[:, 2:6, 2:6] = 1.5
    fields = dict(diffuse=(depth > 0).astype(np.float32), depth=depth, mask=depth > 0,
                  world_to_camera=cap.camera_rig(v)[0], projection=cap.perspective(65.0, 1.0, 0.1, 100.0),
                  fov_y_degrees=65.0, resolution=res)
    fields.update(changes)
    return cap.MultiView(**fields)


# ------------------------------------------------------------------------------------------ closed surfaces

def cloud_diagram(n: int = 500, seed: int = 0):
    """The power diagram of n uniform points in [-1, 1]^3 (unweighted)."""
    from dmesh.wdt import PowerDiagram

    rng = np.random.default_rng(seed)
    return PowerDiagram.from_points(rng.uniform(-1, 1, (n, 3)), None)


def ball_labels(pd, radius: float = 0.6) -> np.ndarray:
    """Tets whose centroid lies in the ball, made pinch-free (so their boundary is a closed 2-manifold)."""
    from dmesh import solid

    inside = np.linalg.norm(pd.points[pd.tets.astype(np.int64)].mean(1), axis=1) < radius
    return solid.repair_pinches(pd, inside)[0]


def cycle(face) -> tuple:
    """A face's vertex cycle, rotated to start at its smallest id (equal for equal windings)."""
    k = int(np.argmin(face))
    return tuple(face[k:]) + tuple(face[:k])


def grid_sheet(n: int, z: float = 0.0, offset=(0.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
    """An n x n vertex grid of unit spacing in the plane z, two triangles per square, wound upward."""
    x, y = np.meshgrid(np.arange(n, dtype=float), np.arange(n, dtype=float), indexing="ij")
    v = np.stack([x.ravel() + offset[0], y.ravel() + offset[1], np.full(n * n, z)], 1)
    i, j = np.meshgrid(np.arange(n - 1), np.arange(n - 1), indexing="ij")
    a, b, c, d = (i * n + j).ravel(), ((i + 1) * n + j).ravel(), ((i + 1) * n + j + 1).ravel(), (i * n + j + 1).ravel()
    return v, np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])


def check_manifold(faces: np.ndarray, points: np.ndarray):
    """Asserts no edge has more than two faces and every vertex one fan, once vertices on one position are
    merged (as a file of the mesh reads back: a pinch split into copies on one point is still a pinch)."""
    from datasets.meshes import merge_vertices
    from dmesh.surface.topology import nonmanifold_edges, nonmanifold_vertices

    _, merged = merge_vertices(points, faces)
    assert len(nonmanifold_edges(merged)) == 0 and len(nonmanifold_vertices(merged)) == 0


def check_closed(faces: np.ndarray, points: np.ndarray):
    """Asserts the faces form a watertight, consistently wound 2-manifold (`check_manifold`); returns it as a
    trimesh."""
    import trimesh

    mesh = trimesh.Trimesh(points, faces, process=False)
    assert mesh.is_watertight and mesh.is_winding_consistent
    check_manifold(faces, points)
    return mesh


# --------------------------------------------------------------------------------------- bad-input contract

def refused(capsys, argv: list[str], command: str | None = None, *expect: str) -> str:
    """Runs `dmesh -q ARGV` in-process and checks the bad-input contract: exit status 2, one non-empty line
    on stderr, `dmesh <command>: error: ...` holding every `expect` text, no traceback, nothing on stdout.
    Returns the error line."""
    from eval.cli import main

    try:
        code = main(["-q", *argv])
    except SystemExit as exc:  # argparse's own errors exit through SystemExit
        code = exc.code
    out, err = capsys.readouterr()
    lines = [line for line in err.splitlines() if line.strip()]
    assert code == 2, err
    assert len(lines) == 1 and "Traceback" not in err, err
    assert lines[0].startswith(f"dmesh {command}: error: " if command else "dmesh"), err
    assert ": error: " in lines[0] and all(e in lines[0] for e in expect), err
    assert out == ""
    return lines[0]
