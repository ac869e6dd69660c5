"""Figures from the results store: side-by-side renders (GT, input, each method) and per-class bar plots.

Renders use pyrender offscreen (OSMesa unless `PYOPENGL_PLATFORM` is already set) with a fixed camera that
sees the whole normalised frame (max vertex norm 1), a key light from the upper left and a headlight. Faces are
drawn two-sided (a reversed copy, with back-face culling), front sides blue-grey and back sides tan, so
open sheets, double layers and inverted orientations are visible. Renders are cached under
`WORK/renders/` by the SHA-256 of the rendered file's bytes, so regenerating reports is cheap. Plots use
matplotlib's Agg backend.

Image arrays: (H, W, 3) uint8 RGB.
"""
from __future__ import annotations

import hashlib
import logging
import os
import shutil
from pathlib import Path

import numpy as np

from eval.io import atomic_path

log = logging.getLogger(__name__)

RENDER_SIZE = 360
_EYE = np.array([1.5, 1.7, 2.0])        # camera position, looking at the origin (y up)
_KEY_LIGHT = np.array([-0.8, 2.6, 1.6])  # key light position (direction towards the origin)
_MESH_COLOUR = (0.60, 0.69, 0.83, 1.0)   # front faces
_BACK_COLOUR = (0.86, 0.70, 0.52, 1.0)   # back faces
_POINT_COLOUR = (40, 90, 170)
_RENDERER = None


def _pyrender():
    if "PYOPENGL_PLATFORM" not in os.environ:
        try:  # the platform the capture module found working (OSMesa first, then EGL)
            from datasets.capture import gl_platform

            gl_platform()
        except Exception:  # noqa: BLE001 - fall back to OSMesa; pyrender then reports what is missing
            os.environ["PYOPENGL_PLATFORM"] = "osmesa"
    import pyrender

    return pyrender


def _look_at(eye: np.ndarray) -> np.ndarray:
    """(4, 4) float64 camera-to-world pose of a camera at `eye` looking at the origin, y up (OpenGL axes)."""
    z = eye / np.linalg.norm(eye)
    x = np.cross([0.0, 1.0, 0.0], z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    pose = np.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = x, y, z, eye
    return pose


def _renderer(size: int):
    global _RENDERER
    pr = _pyrender()
    if _RENDERER is None or _RENDERER.viewport_width != size:
        if _RENDERER is not None:
            _RENDERER.delete()
        _RENDERER = pr.OffscreenRenderer(size, size, point_size=2.0)
    return _RENDERER


def render(mesh=None, points=None, size: int = RENDER_SIZE) -> np.ndarray:
    """Renders a mesh (trimesh.Trimesh) or a point cloud ((N, 3) float) in the normalised frame.

    Returns:
        (size, size, 3) uint8 RGB image on a white background.
    """
    pr = _pyrender()
    scene = pr.Scene(bg_color=[1.0, 1.0, 1.0, 1.0], ambient_light=[0.22, 0.22, 0.22])
    if mesh is not None:
        import trimesh

        v, f = np.asarray(mesh.vertices), np.asarray(mesh.faces)
        # Two-sided shading with back-face culling: the front copy and a reversed copy, each lit with its
        # own outward normal; back sides get a warm colour so inverted or open sheets are easy to read.
        for faces, colour in ((f, _MESH_COLOUR), (f[:, ::-1], _BACK_COLOUR)):
            material = pr.MetallicRoughnessMaterial(baseColorFactor=colour, metallicFactor=0.0,
                                                    roughnessFactor=0.85, doubleSided=False)
            scene.add(pr.Mesh.from_trimesh(trimesh.Trimesh(v, faces, process=False), material=material,
                                           smooth=False))
    if points is not None:
        pts = np.asarray(points, dtype=np.float32)
        colours = np.tile(np.array(_POINT_COLOUR, np.uint8), (len(pts), 1))
        scene.add(pr.Mesh.from_points(pts, colors=colours))
    pose = _look_at(_EYE)
    scene.add(pr.PerspectiveCamera(yfov=np.deg2rad(46.0), znear=0.05, zfar=20.0), pose=pose)
    scene.add(pr.DirectionalLight(intensity=1.2), pose=pose)                  # fill: headlight
    scene.add(pr.DirectionalLight(intensity=2.8), pose=_look_at(_KEY_LIGHT))  # key: upper left
    colour, _ = _renderer(size).render(scene)
    return np.ascontiguousarray(colour[..., :3])


def _placeholder(text: str, size: int = RENDER_SIZE) -> np.ndarray:
    img = np.full((size, size, 3), 235, np.uint8)
    img[::16, :, :] = 220
    return img


def cached_render(path: str | Path, cache: str | Path, kind: str = "mesh", size: int = RENDER_SIZE) -> np.ndarray:
    """Render of the mesh file (kind "mesh") or point-cloud .npz (kind "points") at `path`, cached by content."""
    from PIL import Image

    path = Path(path)
    digest = hashlib.sha256(path.read_bytes() if path.is_file() else str(path).encode()).hexdigest()[:24]
    out = Path(cache) / f"{kind}-{size}-{digest}.png"
    if out.is_file():
        return np.asarray(Image.open(out).convert("RGB"))
    if kind == "points":
        with np.load(path) as z:
            pts = z["points"]
        rng = np.random.default_rng(0)
        pts = pts[rng.choice(len(pts), size=min(len(pts), 30_000), replace=False)]
        img = render(points=pts, size=size)
    else:
        import trimesh

        img = render(mesh=trimesh.load(path, process=False, force="mesh"), size=size)
    with atomic_path(out) as tmp:
        Image.fromarray(img).save(tmp, format="PNG")
    return img


def multiview_thumbnail(folder: str | Path, size: int = RENDER_SIZE) -> np.ndarray | None:
    """One captured view of a multi-view input folder (the first diffuse image found), or None."""
    from PIL import Image

    folder = Path(folder)
    images = sorted(p for p in folder.rglob("*.png") if "diffuse" in p.name or "rgb" in p.name or "color" in p.name)
    images = images or sorted(folder.rglob("*.png"))
    if not images:
        return None
    # Prefer a view from the middle of the list (an oblique elevation rather than the first ring).
    img = Image.open(images[len(images) // 2]).convert("RGB").resize((size, size))
    return np.asarray(img)


def side_by_side(panels: list[tuple[str, np.ndarray]], out: str | Path, title: str,
                 cache: str | Path | None = None) -> Path:
    """Writes one PNG with the labelled panels in a row (at most 8 per row); with `cache`, a figure drawn
    before from the same title, labels and images is copied from there instead of drawn again."""
    out = Path(out)
    cached = None
    if cache is not None:
        h = hashlib.sha256(title.encode())
        for label, img in panels:
            h.update(label.encode() + b"\0" + np.ascontiguousarray(img).tobytes())
        cached = Path(cache) / f"figure-{h.hexdigest()[:24]}.png"
        if cached.is_file():
            with atomic_path(out) as tmp:
                shutil.copyfile(cached, tmp)
            return out
    _draw_side_by_side(panels, out, title)
    if cached is not None:
        with atomic_path(cached) as tmp:
            shutil.copyfile(out, tmp)
    return out


def _draw_side_by_side(panels, out: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cols = min(len(panels), 8)
    rows = (len(panels) + cols - 1) // cols
    fig, axes = plt.subplots(rows, cols, figsize=(2.3 * cols, 2.3 * rows + 0.7), squeeze=False)
    for ax in axes.ravel():
        ax.axis("off")
    for ax, (label, img) in zip(axes.ravel(), panels):
        ax.imshow(img)
        ax.set_title(label, fontsize=8.5)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    with atomic_path(out) as tmp:
        fig.savefig(tmp, format="png", dpi=100)
    plt.close(fig)


def bar_plots(rows: list[dict], out: str | Path, title: str) -> Path | None:
    """Per-class grouped bars of CD p2s (x1e-3) and time (s), one bar per method; `rows` from
    `eval.reports.tables.table2`. Failure counts are written above the bars ("n=2, 1 failed")."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if not rows:
        return None
    methods = sorted({r["method"] for r in rows})
    cats = [c for c in ("closed", "open", "mixed") if any(r["category"] == c for r in rows)]
    cats += sorted({r["category"] for r in rows} - set(cats))
    by = {(r["method"], r["category"]): r for r in rows}
    fig, axes = plt.subplots(1, 2, figsize=(11, 3.8))
    width = 0.8 / max(1, len(methods))
    cmap = plt.get_cmap("tab10")
    for ax, (key, label, scale) in zip(axes, (("cd_p2s", "CD point-to-surface (x1e-3, log)", 1e3),
                                               ("time_s", "method time (s, log)", 1.0))):
        vals = [r[key] * scale for r in rows if r.get(key) is not None and r[key] > 0]
        use_log = bool(vals) and max(vals) / min(vals) > 30  # log only when values span decades
        floor = min(vals) if (use_log and vals) else 0.0     # where a class without any done run is noted
        for i, m in enumerate(methods):
            xs, ys, notes = [], [], []
            for j, c in enumerate(cats):
                r = by.get((m, c))
                if r is None:
                    continue
                x = j + (i - (len(methods) - 1) / 2) * width
                v = r.get(key) * scale if r.get(key) is not None else None
                xs.append(x)
                ys.append(v if v is not None else np.nan)
                notes.append((x, v if v is not None and v > 0 else floor, r["n"], r["failed"]))
            ax.bar(xs, ys, width=width * 0.95, color=cmap(i % 10), label=m)
            for x, y, n, f in notes:
                txt = f"n={n}" + (f"\n{f} failed" if f else "")
                ax.annotate(txt, (x, y), ha="center", va="bottom", fontsize=6.5,
                            color="firebrick" if f else "dimgray", xytext=(0, 2), textcoords="offset points")
        ax.set_xticks(range(len(cats)), cats)
        if use_log:
            ax.set_yscale("log")
        else:
            label = label.replace(", log", "")
            ax.set_ylim(0, (max(vals) if vals else 1.0) * 1.2)
        ax.set_ylabel(label)
        ax.grid(axis="y", alpha=0.3, which="both")
    axes[0].legend(fontsize=8, loc="best")
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    out = Path(out)
    with atomic_path(out) as tmp:
        fig.savefig(tmp, format="png", dpi=110)
    plt.close(fig)
    return out


def render_figures(df, db: Path, work: Path, figdir: Path, progress=None) -> list[tuple[str, Path]]:
    """One side-by-side figure per (input kind, shape): GT, input, then each method's mesh with its CD."""
    from eval.execute import resolve_mesh_path
    from eval.inputs import input_path, shape_dir
    from eval.reports import tables
    from eval.shapes import ShapeRef

    if progress is None:
        from eval.progress import progress
    cache = work / "renders"
    out = []
    groups = list(df.groupby(["input_kind", "category", "shape"], sort=True))
    order = {"pointcloud": 0, "multiview": 1}
    groups.sort(key=lambda g: (order.get(g[0][0], 9), ("closed", "open", "mixed").index(g[0][1])
                               if g[0][1] in ("closed", "open", "mixed") else 9, g[0][2]))
    for (kind, category, shape), g in progress(groups, desc="renders", unit="figure", leave=False):
        try:
            first = g.sort_values("seed").iloc[0]
            settings = first["inputs_json"] if isinstance(first["inputs_json"], dict) else {}
            ref = ShapeRef(id=shape, kind="file", source="", gt_hash=first["gt_hash"] or "")
            radius = float(settings.get("radius", 1.0))
            gt = shape_dir(work, ref, radius) / "gt.ply"
            missing = not gt.is_file()  # GT or a done run's mesh absent (e.g. a clone with the store export only)
            panels = []
            panels.append(("ground truth", cached_render(gt, cache) if gt.is_file()
                           else _placeholder("GT missing")))
            if kind == "pointcloud" and "n_points" in settings:
                p = input_path(work, ref, kind, settings, int(first["seed"]))
                if p.is_file():
                    panels.append((f"input: {settings['n_points']} points", cached_render(p, cache, "points")))
            elif kind == "multiview" and "views" in settings:
                p = input_path(work, ref, kind, settings, int(first["seed"]))
                thumb = multiview_thumbnail(p) if p.exists() else None
                if thumb is not None:
                    panels.append((f"input: {settings['views']} views (one shown)", thumb))
            seed0 = g[g["seed"] == first["seed"]]
            for _, r in seed0.sort_values(["method", "config_label"]).iterrows():
                label = tables.method_label(r["method"], r["config_label"], kind)
                mp = resolve_mesh_path(r.to_dict(), db)
                if r["status"] == "done" and mp is not None and mp.is_file():
                    cd = r.get("cd_p2s")
                    cap = f"{label}\nCD p2s {tables.fmt(float(cd) * 1e3)}e-3" if cd is not None and cd == cd else label
                    panels.append((cap, cached_render(mp, cache)))
                else:
                    missing = missing or r["status"] == "done"
                    err = (tables.text(r.get("error")) or r["status"])[:34]
                    panels.append((f"{label}\n{r['status']}: {err}", _placeholder(r["status"])))
            name = f"renders_{kind}_{safe_name(shape)}.png"
            title = f"{shape} ({category}), {kind} input, seed {int(first['seed'])}"
            if missing and (figdir / name).is_file():  # keep the figure drawn from the meshes, not placeholders
                out.append((title, figdir / name))
                continue
            out.append((title, side_by_side(panels, figdir / name, title, cache=cache)))
        except Exception as exc:  # noqa: BLE001 - a figure that cannot be drawn must not lose the tables
            log.warning("renders for %s / %s skipped: %s", kind, shape, exc)
    return out


def safe_name(name: str) -> str:
    """`name` as a file name: characters other than letters, digits and -_@. become _."""
    return "".join(c if c.isalnum() or c in "-_@." else "_" for c in name)
