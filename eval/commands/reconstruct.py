"""`dmesh reconstruct pointcloud|multiview INPUT -o OUT.obj`: DMesh reconstruction of a point cloud or of
multi-view images.

For `pointcloud`, INPUT is a point cloud (`.npy` with 3 or 6 columns, `.xyz`/`.txt`/`.pts` text with 3 or 6
columns, or a `.ply` without faces, optionally with nx/ny/nz) or a mesh (OBJ, OFF, STL, GLB, or PLY with
faces), which is sampled (`--samples` area-uniform points with face normals). For `multiview`, INPUT is a
capture folder written by `dmesh capture` (its `views.npz`: diffuse, depth, mask, cameras). The output mesh is
in INPUT's frame; `OUT.timings.json` beside it holds the seconds per stage, the config and the final figures.
Every file is written under a temporary name and renamed.
"""
from __future__ import annotations

import dataclasses
import json
import math
import warnings
from pathlib import Path

import numpy as np

NAME = "reconstruct"
HELP = "reconstruct a mesh with DMesh from a point cloud (or a mesh, sampled) or from multi-view images"

POINT_SUFFIXES = (".npy", ".xyz", ".txt", ".pts")
MESH_SUFFIXES = (".obj", ".off", ".stl", ".glb", ".gltf")



def add_arguments(p):
    p.add_argument("kind", choices=["pointcloud", "multiview"], help="input kind")
    p.add_argument("input", metavar="INPUT", help="points (.npy/.xyz/.txt/.pts/.ply) or a mesh (sampled); "
                   "multiview: a folder written by `dmesh capture`")
    p.add_argument("-o", "--out", required=True, help="output mesh (.obj, .ply, .off or .stl)")
    from dmesh.recon.config import DEFAULT_PRESET, MULTIVIEW_PRESETS, POINTCLOUD_PRESETS  # torch-free

    names = POINTCLOUD_PRESETS + tuple(n for n in MULTIVIEW_PRESETS if n not in POINTCLOUD_PRESETS)
    p.add_argument("--preset", choices=names, default=DEFAULT_PRESET,
                   help="settings preset (default: fast; noisy: point clouds only, for noisy scans; compact: point "
                   "clouds only, the fast mesh reduced to --faces faces (no gradient step; compact_steps: with steps); depth and "
                   "refine: multiview only, DMesh's point-cloud fit to the lifted depth pixels, refine with "
                   "image-loss steps after it)")
    p.add_argument("--normals", action="store_true",
                   help="use the input normals in the loss (Eq. 13; lambda_normal 1e-3 unless --set)")
    p.add_argument("--seed", type=int, default=0, help="seed of every random choice (default: 0)")
    p.add_argument("--steps", type=int, default=None,
                   help="total optimisation steps, split 2:1 between phase 1 and phase 2 as in the paper")
    p.add_argument("--samples", type=int, default=100_000,
                   help="points sampled when INPUT is a mesh (default: 100000)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override a PointCloudConfig (MultiViewConfig) field (repeatable), e.g. --set num_init=5000")
    p.add_argument("--surface", choices=["auto", "closed", "open"], default=None,
                   help="which holes the surface step closes: auto (default) those the input shows surface "
                        "across, closed every hole it can (a shape known to be closed), open none (the input's "
                        "boundary is the shape's); docs/surface.md")
    p.add_argument("--faces", type=int, default=None, metavar="N",
                   help="point clouds: a face budget; the mesh is reduced to N faces when it has more (with "
                        "--preset compact, which seeds for it: default 5000); docs/presets.md")
    p.add_argument("--state", default=None, help="resumable state file (resumed when it matches)")
    p.add_argument("--preprocess", default="none", metavar="SPEC",
                   help="point clouds: the harness's pre-processing before DMesh, as `dmesh bench --preprocess` "
                        "gives it to every method: none (default), or stages joined by '+' (outliers[=STD], "
                        "smooth[=K], autosmooth[=K]); DMesh's own input filters are then off, as in the benchmark "
                        "rows (docs/preprocessing.md)")


def read_points(path: str | Path, samples: int = 100_000, seed: int = 0):
    """(G, 3) float64 points and (G, 3) normals or None from a point file or a sampled mesh.

    Raises ValueError (one line) for unreadable, empty or malformed files: a PLY whose data disagrees with
    its header, arrays that are not real numbers (complex, boolean, text, objects, records), NaN or
    infinite values."""
    path = Path(path)

    def finite(pts, normals):
        from dmesh.checks import check_coordinates, check_not_a_line

        for what, arr in (("points", pts), ("normals", normals)):
            if arr is not None and not np.isfinite(arr).all():
                bad = int((~np.isfinite(arr).all(axis=1)).sum())
                raise ValueError(f"{path}: {bad} {what} have NaN or infinite values")
        check_coordinates(pts, str(path))
        check_not_a_line(pts, str(path))
        if normals is not None and not (np.linalg.norm(normals, axis=1) > 0).all():
            bad = int((np.linalg.norm(normals, axis=1) <= 0).sum())
            raise ValueError(f"{path}: {bad} normals have zero length (give a direction at every point, or no "
                             f"normal columns)")
        return pts, normals

    if not path.exists():
        raise FileNotFoundError(f"{path}: no such file")
    if path.is_dir():
        raise ValueError(f"{path}: is a folder, not a point cloud")
    suffix = path.suffix.lower()
    if path.stat().st_size == 0:
        raise ValueError(f"{path}: empty file")
    if suffix in POINT_SUFFIXES:
        if suffix == ".npy":
            try:
                arr = np.load(path, allow_pickle=False)
            except Exception as exc:  # numpy raises several types for corrupt files
                raise ValueError(f"{path}: cannot read ({type(exc).__name__}: {exc})".splitlines()[0]) from None
        else:
            try:
                with warnings.catch_warnings():  # "input contained no data": said below as one line
                    warnings.simplefilter("ignore", UserWarning)
                    arr = np.loadtxt(path, ndmin=2, comments="#")
            except Exception as exc:
                raise ValueError(f"{path}: cannot read ({type(exc).__name__}: {exc})".splitlines()[0]) from None
        kinds = {"c": "complex numbers", "b": "booleans", "O": "Python objects", "U": "text", "S": "text",
                 "V": "records", "M": "dates", "m": "time spans"}
        if arr.dtype.kind in kinds:  # e.g. complex would otherwise lose its imaginary part with a warning
            raise ValueError(f"{path}: holds {kinds[arr.dtype.kind]} (dtype {arr.dtype}), expected real coordinates")
        return finite(*_columns(arr, path))
    if suffix == ".ply":
        import trimesh

        from datasets.meshes import check_ply

        check_ply(path)  # trimesh reads an ASCII PLY shorter than its header says without a word
        try:
            loaded = trimesh.load(str(path), process=False)
        except Exception as exc:
            raise ValueError(f"{path}: cannot read ({type(exc).__name__}: {exc})".splitlines()[0]) from None
        if isinstance(loaded, trimesh.Trimesh) and len(loaded.faces):
            return _sample_mesh(path, samples, seed)
        pts = np.asarray(getattr(loaded, "vertices", np.zeros((0, 3))), dtype=np.float64)
        normals = None
        raw = getattr(loaded, "metadata", {}).get("_ply_raw", {}).get("vertex", {}).get("data")
        names = set(raw.dtype.names or ()) if isinstance(raw, np.ndarray) else set(raw or ())
        if {"nx", "ny", "nz"} <= names:  # trimesh keeps PLY vertex properties as a dict or a record array
            normals = np.concatenate([np.asarray(raw[k], np.float64).reshape(-1, 1) for k in ("nx", "ny", "nz")],
                                     axis=1)
            if len(normals) != len(pts):
                normals = None
        if len(pts) == 0:
            raise ValueError(f"{path}: no points")
        return finite(pts, normals)
    if suffix in MESH_SUFFIXES:
        return _sample_mesh(path, samples, seed)
    raise ValueError(f"{path}: unsupported input format {suffix or '(none)'!r}; use one of "
                     f"{', '.join(POINT_SUFFIXES + ('.ply',) + MESH_SUFFIXES)}")


def _columns(arr: np.ndarray, path: Path):
    arr = np.asarray(arr)
    if arr.size == 0:
        raise ValueError(f"{path}: no points")
    if not np.issubdtype(arr.dtype, np.number):
        raise ValueError(f"{path}: expected numbers, got dtype {arr.dtype}")
    arr = arr.astype(np.float64)
    if arr.ndim != 2 or arr.shape[1] not in (3, 6):
        raise ValueError(f"{path}: expected rows of 3 (x y z) or 6 (x y z nx ny nz) numbers, got shape {arr.shape}")
    return arr[:, :3], (arr[:, 3:] if arr.shape[1] == 6 else None)


def _sample_mesh(path: Path, samples: int, seed: int):
    from datasets.meshes import load_mesh
    from datasets.sampling import sample_points

    if samples < 1:
        raise ValueError(f"--samples must be >= 1, got {samples}")
    pts, nrm = sample_points(load_mesh(path, orient=True), samples, seed=seed)
    return pts.astype(np.float64), nrm.astype(np.float64)


def _parse_overrides(items: list[str]) -> dict:
    """KEY=VALUE strings to a dict of Python values, parsed as YAML like every `--set` (`eval.sweep.parse_sets`)."""
    from eval.values import parse_sets

    return parse_sets(items)


def check_args(args) -> Path:
    """Checks the flags, the input's existence and the output paths before any work; returns the output path."""
    from eval.cli import check_output_file
    from eval.values import check_points, check_seed

    check_seed("--seed", args.seed)
    check_points("--samples", args.samples)
    from eval.preprocess import NONE, parse_spec

    if parse_spec(args.preprocess, "--preprocess")[0] != NONE:
        if args.kind != "pointcloud":
            raise ValueError("--preprocess applies to point clouds only (multi-view input is images)")
        if args.preset == "noisy":
            raise ValueError("--preprocess replaces the noisy preset's own smoothing; use --preset fast "
                             "--preprocess outliers+smooth")
    if not Path(args.input).exists():
        raise FileNotFoundError(f"{args.input}: no such {'folder' if args.kind == 'multiview' else 'file'}")
    out = check_output_file(args.out, "-o", (".obj", ".ply", ".off", ".stl"), inputs=[args.input])
    timings = check_output_file(out.with_name(out.stem + ".timings.json"), "-o", inputs=[args.input])
    if args.state is not None:
        state = check_output_file(args.state, "--state", inputs=[args.input])
        if state.exists() and not state.is_file():
            raise ValueError(f"--state {state}: not a regular file")
        if state.resolve() in {out.resolve(), timings.resolve()}:
            raise ValueError(f"--state {state}: is an output too; give a file of its own")
        if state.is_file():  # a file that is not a state is refused here, before any work
            from dmesh.recon.loop import read_state

            read_state(state)
    return out


def config_error(exc: Exception, overrides: dict) -> str:
    """One line for a config that rejected `overrides`, naming them when the config's message does not."""
    msg = " ".join(str(exc).split())
    if overrides and not any(k in msg for k in overrides):
        given = " ".join(f"{k}={v!r}" for k, v in overrides.items())
        return f"bad config value (--set {given}): {msg}"
    return msg if isinstance(exc, ValueError) else f"bad config value: {msg}"


def build_config(kind: str, preset: str, seed: int, overrides: dict, steps: int | None = None,
                 normals: bool = False):
    """The `PointCloudConfig` or `MultiViewConfig` of `kind` from a preset, the seed, `--steps` / `--normals`
    (point clouds only) and `--set` overrides (the config's `from_preset`); one-line ValueError for an
    unknown preset or key, a flag the kind does not take, or a bad value."""
    from dmesh.recon.config import MULTIVIEW_PRESETS, POINTCLOUD_PRESETS, PointCloudConfig
    from dmesh.recon.multiview_config import MultiViewConfig

    cls, presets = (PointCloudConfig, POINTCLOUD_PRESETS) if kind == "pointcloud" else (MultiViewConfig,
                                                                                     MULTIVIEW_PRESETS)
    if preset not in presets:
        other = "multi-view" if kind == "pointcloud" else "point-cloud"
        raise ValueError(f"preset {preset!r} is for {other} input only; {kind} input takes {', '.join(presets)}")
    values = {"seed": seed}
    if kind == "multiview" and (normals or steps is not None):
        raise ValueError("--normals and --steps apply to point clouds only (use --set for multi-view steps)")
    if steps is not None:
        if steps < 0:
            raise ValueError(f"--steps must be >= 0, got {steps}")
        values["steps_phase1"] = int(math.ceil(steps * 2 / 3))
        values["steps_phase2"] = steps - values["steps_phase1"]
    if normals:
        values["lambda_normal"] = 1e-3
    values.update(overrides)
    try:
        return cls.from_preset(preset, values)
    except (TypeError, ValueError) as exc:
        raise ValueError(config_error(exc, overrides)) from None


def read_capture(directory: str | Path):
    """The `datasets.capture.MultiView` in `directory`; one-line FileNotFoundError / ValueError otherwise."""
    from datasets.capture import MultiView

    d = Path(directory)
    if not d.exists():
        raise FileNotFoundError(f"{d}: no such folder")
    if not d.is_dir():
        raise ValueError(f"{d}: not a folder (give the capture folder written by `dmesh capture`)")
    if not (d / "views.npz").is_file():
        raise ValueError(f"{d}: not a capture folder (no views.npz; write one with `dmesh capture MESH -o {d}`)")
    try:
        return MultiView.load(d)
    except ValueError as exc:
        if str(d / "views.npz") in str(exc):  # MultiView.load's own check, which names the file already
            raise
        raise ValueError(f"{d / 'views.npz'}: cannot read ({' '.join(str(exc).split())})") from None
    except Exception as exc:  # numpy and zipfile raise several types for corrupt or incomplete archives
        msg = " ".join(f"{type(exc).__name__}: {exc}".split())
        raise ValueError(f"{d / 'views.npz'}: cannot read ({msg})") from None


def write_outputs(out: Path, res, cfg, report: dict) -> None:
    """Writes a reconstruction's mesh to `out` and `OUT.timings.json` beside it (`report` + the timings,
    info, last step and config), each under a temporary name, renamed when complete.

    Raises ValueError (one line) when the mesh has no faces; nothing is written then."""
    from eval.io import write_mesh, write_text

    if len(res.mesh.faces) == 0:
        raise ValueError("the reconstruction has no faces (no point kept a real value above the threshold)")
    write_mesh(res.mesh, out)
    report = {**report, "timings_s": {k: round(v, 4) for k, v in res.timings.items()}, "info": res.info,
              "final": res.history[-1] if res.history else None, "config": dataclasses.asdict(cfg)}
    timings_path = out.with_name(out.stem + ".timings.json")
    write_text(timings_path, json.dumps(report, indent=2, default=str) + "\n")
    print(f"wrote {out} ({len(res.mesh.faces)} faces, {res.timings['total']:.1f} s) and {timings_path}")


def run(args) -> int:
    from eval.progress import progress

    out = check_args(args)
    pre = None  # the pre-processing's record (point clouds with --preprocess)
    overrides = _parse_overrides(args.set)
    if args.surface is not None:
        overrides["surface.mode"] = args.surface
    if args.faces is not None:
        if args.kind != "pointcloud":
            raise ValueError("--faces applies to point clouds only")
        overrides["faces"] = args.faces
    cfg = build_config(args.kind, args.preset, args.seed, overrides, args.steps, args.normals)
    if args.kind == "multiview":
        from dmesh.recon.multiview import reconstruct as reconstruct_views

        views = read_capture(args.input)
        total = cfg.total_steps()
        call = lambda **kw: reconstruct_views(views, cfg, **kw)  # noqa: E731
    else:
        from dmesh.recon.pointcloud import reconstruct as reconstruct_points

        points, normals = read_points(args.input, args.samples, args.seed)
        if args.normals and normals is None:
            raise ValueError(f"{args.input}: --normals given but the input has no normals")
        from eval.preprocess import NONE, apply, parse_spec

        if parse_spec(args.preprocess, "--preprocess")[0] != NONE:
            from baselines.dmesh_pointcloud import harness_config, seeds_for_input

            points, normals, pre = apply(points, normals, args.preprocess)
            cfg, _ = seeds_for_input(harness_config(cfg), pre)
        total = cfg.steps_phase1 + cfg.steps_phase2
        call = lambda **kw: reconstruct_points(points, normals, cfg, **kw)  # noqa: E731

    bar = progress(total=total, desc="dmesh", unit="step")

    def on_step(rec: dict) -> None:
        if "stage" in rec:
            bar.set_description(f"dmesh {rec['stage']}")
            return
        bar.update(1)
        bar.set_postfix(loss=f"{rec['loss']:.4g}", faces=rec["faces"], refresh=False)

    try:
        res = call(callback=on_step, state_path=args.state)
    finally:
        bar.close()
    report = {"input": str(args.input), "output": str(out), "preset": args.preset}
    if args.kind == "multiview":
        report["kind"] = "multiview"
    elif pre is not None:
        report["preprocess"] = pre
    write_outputs(out, res, cfg, report)
    return 0
