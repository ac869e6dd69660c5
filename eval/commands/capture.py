"""`dmesh capture`: multi-view diffuse, depth and mask images of a mesh, with their cameras."""
from __future__ import annotations

import contextlib
import logging
import os
import shutil
import tempfile
import time
from pathlib import Path

NAME = "capture"
HELP = "render diffuse + depth + mask images of MESH from a ring of cameras into folder DIR"

log = logging.getLogger(__name__)


def add_arguments(p):
    p.add_argument("mesh", metavar="MESH", help="mesh file (OBJ, PLY, OFF, STL, GLB)")
    p.add_argument("-o", "--out", metavar="DIR", required=True,
                   help="output folder (created; a previous capture there is replaced, a folder holding other "
                        "files refused)")
    p.add_argument("--views", type=int, default=64, help="number of cameras (default: 64 = 8 x 8)")
    p.add_argument("--resolution", type=int, default=256, help="image side in pixels (default: 256)")
    p.add_argument("--distance", type=float, default=2.0, help="camera distance from the origin (default: 2.0)")
    p.add_argument("--no-normalize", action="store_true",
                   help="use the mesh as it is (default: vertex mean at the origin, max vertex norm 1)")
    p.add_argument("--seed", type=int, default=0, help="0: canonical rig; else a seeded azimuth offset")


def run(args) -> int:
    import json

    from datasets import capture as cap
    from datasets.meshes import load_mesh
    from datasets.normalize import normalize
    from eval.cli import check_output_dir
    from eval.progress import progress
    from eval.values import check_capture_size, check_seed

    logging.getLogger("OpenGL").setLevel(logging.WARNING)  # PyOpenGL logs its accelerate check at INFO
    if args.views < 1:
        raise ValueError(f"--views must be >= 1, got {args.views}")
    if args.resolution < 1:
        raise ValueError(f"--resolution must be >= 1, got {args.resolution}")
    check_capture_size(args.views, args.resolution, ("--views", "--resolution"))
    if not (args.distance > 0 and args.distance < float("inf")):
        raise ValueError(f"--distance must be a positive finite number, got {args.distance}")
    check_seed("--seed", args.seed)
    out = check_output_dir(args.out, "-o")
    _check_replaceable(out)

    mesh = load_mesh(args.mesh, orient=True)  # an inside-out closed mesh is flipped before rendering
    transform = None
    if not args.no_normalize:
        mesh, transform = normalize(mesh, radius=1.0)
    t0 = time.perf_counter()
    try:
        with progress(total=args.views, desc="capture", unit="view") as bar:
            views = cap.capture(mesh, views=args.views, resolution=args.resolution, distance=args.distance,
                                seed=args.seed, callback=lambda done, total: bar.update(1))
    except cap.GLUnavailableError as exc:
        from eval.cli import CliError

        raise CliError(str(exc)) from None
    elapsed = time.perf_counter() - t0

    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".tmp", dir=out.parent))
    try:
        from eval.io import honour_umask

        honour_umask(tmp)  # mkdtemp makes it 0o700
        views.save(tmp)
        info = {"mesh": str(Path(args.mesh).resolve()), "faces": int(len(mesh.faces)),
                "vertices": int(len(mesh.vertices)), "normalized": transform is not None,
                "transform": transform.to_dict() if transform is not None else None,
                "views": views.views, "resolution": views.resolution, "distance": args.distance,
                "seed": args.seed, "fov_y_degrees": views.fov_y_degrees,
                "gl_platform": cap.gl_platform(), "capture_seconds": round(elapsed, 3)}
        (tmp / "capture.json").write_text(json.dumps(info, indent=1) + "\n")
        _replace_dir(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    print(f"wrote {views.views} views at {views.resolution}x{views.resolution} to {out} "
          f"({elapsed:.2f} s, {cap.gl_platform()})")
    return 0


def _check_replaceable(out: Path) -> None:
    """ValueError (one line) unless `out` is absent, empty or holds only what a capture writes
    (`datasets.capture.foreign_files`): a capture replaces the whole folder, so it never deletes other files."""
    from datasets.capture import foreign_files

    if not out.exists():
        return
    others = foreign_files(out)
    if others:
        shown = ", ".join(others[:3]) + (f" and {len(others) - 3} more" if len(others) > 3 else "")
        raise ValueError(f"-o {out}: not a capture folder (it holds {shown}, which a capture does not write and "
                         "replacing the folder would delete); choose another -o")


def _replace_dir(tmp: Path, out: Path) -> None:
    """Rename the finished folder `tmp` to `out`, replacing a previous capture there (checked again, as files
    may have come while the views rendered)."""
    if not out.exists():
        os.replace(tmp, out)
        return
    _check_replaceable(out)
    old = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".old", dir=out.parent))
    os.rmdir(old)
    os.replace(out, old)
    try:
        os.replace(tmp, out)
    except BaseException:
        with contextlib.suppress(OSError):
            os.replace(old, out)
        raise
    shutil.rmtree(old, ignore_errors=True)
