"""The inputs of a sweep's runs, prepared once and cached in the work folder.

The GT of each shape is prepared once (`prepare_gt`, cached under `WORK/inputs/<shape>-<gt hash>/`): loaded or
generated, classified (closed / open / mixed), turned outward when inside out, and normalised (vertex mean at
the origin, max vertex norm `radius`), then written as `gt.ply` beside `meta.json` (and, once a run is scored against it, `gt_figures.json`: the GT's
own figures, `eval.execute.with_gt_figures`). The inputs of the pending
runs are prepared once per (shape, input kind, settings, seed), cached beside the GT (`prepare_input`,
`input_path`): `pc_n<N>_s<seed>.npz` holds `points` (N, 3) float32 and `normals` (N, 3) float32 (area-uniform
samples of the normalised GT); `mv_v<V>_r<R>_d<D>/` holds the multi-view capture (`datasets.capture.MultiView`).
A corrupted input is made from the clean one; a pre-processed input (`"preprocess"` in the settings) is made
from the raw one by `eval.preprocess.apply` and cached beside it (`<raw>.pre-<spec>-<code>.npz`), and a
point-cloud method on a multi-view input (`"lift"`) gets the capture's lifted depth pixels
(`eval.preprocess.lift_depth`, `mv_..._lift<N>_s<seed>-<code>.npz`). `load_inputs` reads a run's
`baselines.base.Inputs` back from the cache in its worker.
"""
from __future__ import annotations

import dataclasses
import json
import logging
import os
import shutil
import tempfile
from pathlib import Path

import numpy as np

from eval.code_hash import INPUT_VERSION
from eval.io import atomic_path, honour_umask, write_mesh, write_text
from eval.plain import jsonable, one_line
from eval.shapes import ShapeRef
from eval.sweep import RunSpec, Sweep, canonical_json

log = logging.getLogger(__name__)



def shape_dir(work: str | Path, shape: ShapeRef, radius: float) -> Path:
    """Cache folder of one GT shape in one normalisation, at the inputs' version (`eval.code_hash.INPUT_VERSION`:
    bump it when `prepare_gt` or the input generation changes the data it writes, so that no input made from an
    earlier GT is reused)."""
    safe = "".join(c if c.isalnum() or c in "-_@." else "_" for c in shape.id)
    return Path(work) / "inputs" / f"{safe}-{shape.gt_hash[:12]}-r{radius:g}-v{INPUT_VERSION}"


def prepare_gt(shape: ShapeRef, work: str | Path, radius: float = 1.0) -> tuple[ShapeRef, Path]:
    """Loads or generates, classifies and normalises the GT once; returns (shape with category, gt.ply path)."""
    folder = shape_dir(work, shape, radius)
    meta_path, gt_path = folder / "meta.json", folder / "gt.ply"
    if meta_path.is_file() and gt_path.is_file():
        meta = json.loads(meta_path.read_text())
        return dataclasses.replace(shape, category=meta["category"]), gt_path
    from datasets.normalize import normalize

    if shape.kind == "synthetic":
        from datasets import synthetic

        mesh = synthetic.generate(shape.source, seed=shape.gen_seed)
        category = shape.category
    else:
        from datasets.meshes import classify, load_mesh

        mesh = load_mesh(shape.source)
        category = classify(mesh)
    if category not in ("closed", "open", "mixed"):
        raise ValueError(f"shape {shape.id}: unexpected category {category!r}")
    from datasets.meshes import orient_outward

    mesh, orientation = orient_outward(mesh, name=shape.source)  # before anything is sampled or rendered
    mesh, transform = normalize(mesh, radius=radius)
    folder.mkdir(parents=True, exist_ok=True)
    write_mesh(mesh, gt_path)
    meta = {"id": shape.id, "kind": shape.kind, "source": shape.source, "gen_seed": shape.gen_seed,
            "category": category, "gt_hash": shape.gt_hash, "radius": radius, "orientation": orientation,
            "vertices": int(len(mesh.vertices)), "faces": int(len(mesh.faces)),
            "transform": jsonable(transform)}
    write_text(meta_path, json.dumps(meta, indent=2) + "\n")
    return dataclasses.replace(shape, category=category), gt_path


def load_gt(gt_path: str | Path):
    """The cached normalised GT as a trimesh.Trimesh (exact vertices and faces, no processing), oriented.

    `prepare_gt` turns an inside-out closed GT outward before writing it and records what it found in
    meta.json ("orientation"); that status goes into `mesh.metadata["orientation"]`, where
    `eval.metrics.compute_metrics` reports it. A gt.ply without that record (written elsewhere) is passed
    through `datasets.meshes.orient_outward` here.
    """
    import trimesh

    gt_path = Path(gt_path)
    mesh = trimesh.load(gt_path, process=False, force="mesh")
    meta_path = gt_path.parent / "meta.json"
    found = json.loads(meta_path.read_text()).get("orientation") if meta_path.is_file() else None
    if found is not None:
        mesh.metadata["orientation"] = found
        return mesh
    from datasets.meshes import orient_outward

    return orient_outward(mesh, name=str(gt_path))[0]


def input_path(work: str | Path, shape: ShapeRef, kind: str, settings: dict, seed: int) -> Path:
    """Cache path of one prepared input (a .npz file for point clouds, a folder for multi-view).

    A corrupted input (settings["corruption"], see `eval.sweep.Sweep.input_variants`) gets the suffix
    `datasets.corrupt.cache_tag` of its corruption, e.g. `pc_n100000_s0_noise0.005.npz`."""
    from datasets.corrupt import cache_tag

    if "preprocess" in settings:  # beside the raw input it is made from
        pre = settings["preprocess"]
        raw = input_path(work, shape, kind, _without(settings, "preprocess"), seed)
        return raw.with_name(f"{raw.name[:-4] if raw.suffix == '.npz' else raw.name}.pre-{pre['stages']}-"
                             f"{pre['code'][:8]}.npz")
    if "lift" in settings:  # beside the capture it is lifted from
        lift = settings["lift"]
        capture = input_path(work, shape, kind, _without(settings, "lift"), seed)
        return capture.with_name(f"{capture.name}_lift{lift['points']}_s{seed}-{lift['code'][:8]}.npz")
    folder = shape_dir(work, shape, settings["radius"])
    tag = cache_tag(settings.get("corruption"))
    if kind == "pointcloud":
        return folder / f"pc_n{settings['n_points']}_s{seed}{tag}.npz"
    if kind == "multiview":
        return folder / f"mv_v{settings['views']}_r{settings['resolution']}_d{settings['distance']:g}{tag}"
    return folder / "gt.ply"


def _without(settings: dict, key: str) -> dict:
    return {k: v for k, v in settings.items() if k != key}


def input_id(spec: RunSpec) -> tuple:
    """What identifies the prepared input of a run: (shape id, input kind, seed, input settings as JSON)."""
    return spec.shape.id, spec.input_kind, spec.seed, canonical_json(dict(spec.inputs))


def prepare_input(shape: ShapeRef, gt_path: Path, kind: str, settings: dict, seed: int, work: str | Path) -> Path:
    """Creates the cached input of (shape, kind, settings, seed) unless it exists; returns its path.

    A corrupted input is made from the clean one of the same sizes (prepared first, and cached too):
    `datasets.corrupt.corrupt_cloud` for point clouds (its extra arrays, e.g. a scan's cameras, are saved
    beside `points` and `normals`), `datasets.corrupt.add_depth_noise` for a multi-view capture."""
    path = input_path(work, shape, kind, settings, seed)
    if path.exists():
        return path
    if "preprocess" in settings or "lift" in settings:
        _prepare_harness_input(shape, gt_path, kind, settings, seed, work, path)
        return path
    from datasets.corrupt import cache_tag

    corruption = dict(settings.get("corruption") or {})
    clean = {k: v for k, v in settings.items() if k != "corruption"}
    if kind == "pointcloud" and cache_tag(corruption):
        from datasets.corrupt import corrupt_cloud

        with np.load(prepare_input(shape, gt_path, kind, clean, seed, work)) as z:
            points, normals = z["points"], z["normals"]
        arrays = corrupt_cloud(load_gt(gt_path), points, normals, corruption, seed, float(settings["radius"]))
        with atomic_path(path) as tmp:
            with open(tmp, "wb") as fh:
                np.savez(fh, **arrays)
    elif kind == "pointcloud":
        from datasets.sampling import sample_points

        points, normals = sample_points(load_gt(gt_path), settings["n_points"], seed)
        with atomic_path(path) as tmp:
            with open(tmp, "wb") as fh:
                np.savez(fh, points=np.asarray(points, np.float32), normals=np.asarray(normals, np.float32))
    elif kind == "multiview":
        from datasets.capture import MultiView, capture
        from datasets.corrupt import add_depth_noise

        if cache_tag(corruption):
            views = MultiView.load(prepare_input(shape, gt_path, kind, clean, seed, work))
            views = add_depth_noise(views, float(corruption.get("depth_noise", 0.0)) * float(settings["radius"]), seed)
        else:
            views = capture(load_gt(gt_path), views=settings["views"], resolution=settings["resolution"],
                            distance=settings["distance"])
        tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.", dir=path.parent))
        try:
            honour_umask(tmp)  # mkdtemp makes it 0o700
            views.save(tmp)
            os.replace(tmp, path)
        except OSError:
            shutil.rmtree(tmp, ignore_errors=True)
            if not path.exists():
                raise
            # Another process sharing the work folder finished the same capture first: use its copy.
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
    return path


def _prepare_harness_input(shape: ShapeRef, gt_path: Path, kind: str, settings: dict, seed: int, work,
                           path: Path) -> None:
    """Writes `path`: the pre-processed points of the input without `"preprocess"` (`eval.preprocess.apply`,
    with its record as `preprocess_info`), or the lifted depth pixels of the capture without `"lift"`
    (`eval.preprocess.lift_depth`, record `lift_info`). Points and normals are float32, as every raw input."""
    from eval import preprocess

    if "preprocess" in settings:
        raw = prepare_input(shape, gt_path, kind, _without(settings, "preprocess"), seed, work)
        with np.load(raw) as z:
            arrays = {k: z[k] for k in z.files}
        points, normals, info = preprocess.apply(arrays["points"], arrays["normals"], settings["preprocess"]["stages"],
                                                 is_outlier=arrays.get("is_outlier"))
        out = {"preprocess_info": np.array(json.dumps(info))}
        if "lift_info" in arrays:  # pre-processed lifted depth pixels keep the lift's record
            out["lift_info"] = arrays["lift_info"]
    else:
        from datasets.capture import MultiView

        views = MultiView.load(prepare_input(shape, gt_path, kind, _without(settings, "lift"), seed, work))
        points, normals, info = preprocess.lift_depth(views, int(settings["lift"]["points"]), seed)
        out = {"lift_info": np.array(json.dumps(info))}
    out.update(points=np.asarray(points, np.float32), normals=np.asarray(normals, np.float32))
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            np.savez(fh, **out)


def load_inputs(spec: RunSpec, gt_path: Path, work: str | Path):
    """The `baselines.base.Inputs` of a run, read from the cache. A pre-processed input's record goes to
    `Inputs.preprocess`, a lifted one's to the attribute `lifted_depth` (the runner puts both in the run's
    info)."""
    from baselines.base import Inputs

    path = input_path(work, spec.shape, spec.input_kind, dict(spec.inputs), spec.seed)
    if spec.input_kind == "pointcloud" or "lift" in spec.inputs:
        with np.load(path) as z:
            inputs = Inputs(points=z["points"], normals=z["normals"], views=None, seed=spec.seed)
            if "preprocess_info" in z.files:
                inputs.preprocess = json.loads(str(z["preprocess_info"]))
            if "lift_info" in z.files:
                inputs.lifted_depth = json.loads(str(z["lift_info"]))
        return inputs
    if spec.input_kind == "multiview":
        from datasets.capture import MultiView

        return Inputs(points=None, normals=None, views=MultiView.load(path), seed=spec.seed)
    # "mesh" input (mesh to DMesh, Table 1): the normalised GT mesh itself, as `inputs.mesh`.
    inputs = Inputs(points=None, normals=None, views=None, seed=spec.seed)
    inputs.mesh = load_gt(gt_path)
    return inputs


def resolve_and_prepare_shapes(sweep: Sweep, work: str | Path, progress=None) -> tuple[list[ShapeRef], dict]:
    """Resolves the sweep's shapes and prepares their GT; returns (shapes, {shape id: gt path})."""
    from eval.progress import progress as bar

    refs = sweep.resolved_shapes()
    shapes, gts = [], {}
    for ref in (progress or bar)(refs, desc="ground truth", unit="shape", leave=False):
        ref, gt = prepare_gt(ref, work, sweep.radius)
        shapes.append(ref)
        gts[ref.id] = gt
    return shapes, gts


def prepare_inputs(pending: list[RunSpec], shapes: list[ShapeRef], gts: dict, work: str | Path,
                   progress=None) -> dict:
    """Prepares the input of every run of `pending` once (`prepare_input`); returns {`input_id`: one-line error}
    for the inputs that could not be prepared (their runs are stored failed when claimed)."""
    if progress is None:
        from eval.progress import progress
    needed = sorted({input_id(s) for s in pending})
    by_id = {s.id: s for s in shapes}
    input_errors = {}
    for ident in progress(needed, desc="inputs", unit="input", leave=False):
        shape_id, kind, seed, _ = ident
        spec = next(s for s in pending if input_id(s) == ident)
        try:
            prepare_input(by_id[shape_id], gts[shape_id], kind, dict(spec.inputs), seed, work)
        except Exception as exc:  # noqa: BLE001 - an input that cannot be prepared fails its runs
            err = f"input preparation failed: {one_line(exc)}"
            log.warning("%s %s seed %d: %s", shape_id, kind, seed, err)
            input_errors[ident] = err
    return input_errors
