"""Shape specs: a synthetic generator (with its seed) or a mesh file, resolved to a `ShapeRef` with its GT hash.

Specs (strings):
    "torus"                a synthetic shape of `datasets.synthetic.SHAPES`, generator seed 0
    "torus@3"              the same generator with seed 3
    "closed/spot.obj"      a mesh file: as given if it exists, else relative to the data root
Data root: `--data-root` flag, else the `DMESH_DATA` environment variable, else `../shared/meshes`
relative to the repository. The GT hash, in every run's key (`eval.sweep.run_key`), is the SHA-256 of a real
mesh's file bytes, or of a synthetic shape's generator name and seed.
"""
from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass
from pathlib import Path

from eval.code_hash import REPO

CATEGORIES = ("closed", "open", "mixed")
MESH_SUFFIXES = (".obj", ".ply", ".off", ".stl", ".glb", ".gltf")


def default_data_root() -> Path:
    """Data root for real meshes: $DMESH_DATA, else ../shared/meshes beside the repository."""
    env = os.environ.get("DMESH_DATA")
    return Path(env) if env else REPO.parent / "shared" / "meshes"


@dataclass(frozen=True)
class ShapeRef:
    """A resolved shape spec."""

    id: str                 # shape id used in tables ("torus", "torus@3", "spot")
    kind: str               # "synthetic" or "file"
    source: str             # synthetic generator name, or the absolute mesh path
    gen_seed: int = 0       # synthetic generator seed
    category: str | None = None  # closed/open/mixed; None for a file until it is classified
    gt_hash: str = ""       # SHA-256 of the file bytes / generator name and seed

    def __post_init__(self):
        if self.kind not in ("synthetic", "file"):
            raise ValueError(f"ShapeRef.kind: expected 'synthetic' or 'file', got {self.kind!r}")


def resolve_shape(spec: str, data_root: str | Path | None = None) -> ShapeRef:
    """Resolves a shape spec (see module docstring); raises ValueError for an unknown shape."""
    spec = str(spec).strip()
    if spec.lower().endswith(MESH_SUFFIXES) or os.sep in spec:
        candidates = [Path(spec).expanduser()]
        if not Path(spec).is_absolute():
            candidates.append(Path(data_root or default_data_root()) / spec)
        for p in candidates:
            if p.is_file():
                digest = hashlib.sha256(p.read_bytes()).hexdigest()
                return ShapeRef(id=p.stem, kind="file", source=str(p.resolve()), gt_hash=digest)
        raise ValueError(f"unknown shape {spec!r}: no such mesh file (looked in "
                         f"{', '.join(str(c) for c in candidates)})")
    name, _, seed_txt = spec.partition("@")
    try:
        gen_seed = int(seed_txt) if seed_txt else 0
    except ValueError:
        raise ValueError(f"unknown shape {spec!r}: the generator seed after '@' must be an integer") from None
    from datasets import synthetic

    if name not in synthetic.SHAPES:
        raise ValueError(f"unknown shape {spec!r}; synthetic shapes: {', '.join(sorted(synthetic.SHAPES))}; "
                         f"or give a mesh file path")
    category = synthetic.SHAPES[name][0]
    digest = hashlib.sha256(f"synthetic/{name}/seed={gen_seed}".encode()).hexdigest()
    return ShapeRef(id=spec, kind="synthetic", source=name, gen_seed=gen_seed, category=category, gt_hash=digest)
