"""Image-loss gradients of the soft renderer against finite differences of a hard render.

First table: small scenes (one triangle, opaque or at opacity 0.6; two opaque triangles sharing an edge, the
edge's vertex moved in the image plane or in depth), 32 x 32 pixels. For each image channel (alpha, depth,
diffuse) the sum over the pixels is differentiated along one direction u: autograd against central differences
at h = 1e-2, 3e-3 and 1e-3. There the soft render is smooth and the differences converge to the gradient.

Second table: the multi-view procedure moves points with the soft renderer's analytic gradients
(`dmesh.render.soft_render`: triangles with a soft band of `edge_width` pixels outside them). The images it
fits come from a hard rasteriser. This bench checks, for an opaque sphere (an icosphere of radius 0.5, seen
from distance 2 at R x R pixels), the derivative of the procedure's image loss (L1 of the diffuse channel + L1
of the depth channel, `dmesh.recon.views.depth_channel`) against target images of the sphere scaled by 1.03,
along random unit directions u that move only

- the silhouette vertices (those with both front- and back-facing faces around them in some view), or
- the interior vertices (on no view's silhouette),

three ways:

- autograd: g . u of the soft render's loss, the gradient the procedure uses;
- fd_soft: (L(x + h u) - L(x - h u)) / 2h of the same soft render: checks the kernel's backward;
- fd_hard: the same central difference of the loss of an antialiased hard render (the soft renderer at 8R x 8R
  with a band of 0.05 of its pixels, box-averaged to R x R, so 64 hard samples per pixel): the derivative
  that the true images' loss has, which a silhouette term should follow.

rel_soft = |autograd - fd_soft| / |fd_soft|; rel_hard = |autograd - fd_hard| / |fd_hard|. The step h moves the
vertices by about 0.05 pixel (the kernel runs in float32). Two kinds of targets for the soft loss (the hard
loss always compares with the hard targets, the true images):

- hard: hard renders of the target sphere, without the soft band that the procedure's phase-1 targets carry
  (`dmesh.recon.views.soft_band_targets`): the soft silhouette lies about half a band outside the hard one;
- band: soft renders of the target sphere, the ideal band targets (what the band would look like on the true
  shape): the soft loss's minimum is then at the target.

Regenerate: `python -m eval.bench render_gradients`.
"""
from __future__ import annotations

import numpy as np
import torch

from eval.bench.common import markdown_table, write_report

#: Supersampling of the hard render (per axis) and its band width in its own pixels.
SUPERSAMPLE = 8
HARD_BAND = 0.05
#: Scale of the target sphere.
TARGET_SCALE = 1.03


def _scene(resolution: int, views: int):
    import trimesh

    from dmesh.camera import look_at
    from dmesh.render import Camera

    mesh = trimesh.creation.icosphere(subdivisions=3, radius=0.5)
    rng = np.random.default_rng(0)
    dirs = rng.normal(size=(views, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    cams = [Camera(look_at(2.0 * d), height=resolution, width=resolution) for d in dirs]
    return mesh, cams, dirs


def _render(verts: torch.Tensor, faces: torch.Tensor, cam, hard: bool) -> dict[str, torch.Tensor]:
    import dataclasses

    from dmesh.render import soft_render

    opacity = torch.ones(len(faces))
    if not hard:
        return soft_render(verts, faces, opacity, cam)
    big = dataclasses.replace(cam, height=cam.height * SUPERSAMPLE, width=cam.width * SUPERSAMPLE)
    out = soft_render(verts, faces, opacity, big, edge_width=HARD_BAND)
    pool = torch.nn.functional.avg_pool2d
    return {k: pool(v[None, None].double(), SUPERSAMPLE)[0, 0] for k, v in out.items()}


def _channels(out: dict) -> tuple[torch.Tensor, torch.Tensor]:
    """(diffuse, depth channel) in float64; the depth channel as the procedure's, with far = 3 (beyond the
    sphere from distance 2)."""
    from dmesh.recon.views import depth_channel

    far = torch.tensor([3.0], dtype=out["depth"].dtype)
    return out["diffuse"].double(), depth_channel(out["depth"][None], out["alpha"][None], far)[0].double()


#: Which channels the loss takes: the procedure's ("both"), or one of them.
CHANNELS = {"both": (1.0, 1.0), "diffuse": (1.0, 0.0), "depth": (0.0, 1.0)}


def _loss(verts, faces, cams, targets, hard: bool, channels: str) -> torch.Tensor:
    w_d, w_z = CHANNELS[channels]
    total = torch.zeros((), dtype=torch.float64)
    for cam, (t_d, t_z) in zip(cams, targets):
        d, z = _channels(_render(verts, faces, cam, hard))
        total = total + w_d * (d - t_d).abs().mean() + w_z * (z - t_z).abs().mean()
    return total / len(cams)


def _groups(mesh, dirs) -> dict[str, np.ndarray]:
    """(N,) bool silhouette vertices (faces facing both ways around them in some view) and interior vertices
    (on no view's silhouette)."""
    normals = mesh.face_normals
    centres = mesh.triangles_center
    sil = np.zeros(len(mesh.vertices), bool)
    for d in dirs:
        facing = ((2.0 * d - centres) * normals).sum(1) > 0
        pos = np.zeros(len(mesh.vertices), bool)
        neg = np.zeros(len(mesh.vertices), bool)
        np.logical_or.at(pos, mesh.faces.ravel(), np.repeat(facing, 3))
        np.logical_or.at(neg, mesh.faces.ravel(), np.repeat(~facing, 3))
        sil |= pos & neg
    return {"silhouette": sil, "interior": ~sil}


def check(resolution: int, views: int, directions: int, h: float) -> list[dict]:
    mesh, cams, dirs = _scene(resolution, views)
    faces = torch.from_numpy(np.asarray(mesh.faces, dtype=np.int64))
    x0 = torch.tensor(np.asarray(mesh.vertices), dtype=torch.float32)
    with torch.no_grad():
        hard_targets = [_channels(_render(x0 * TARGET_SCALE, faces, cam, hard=True)) for cam in cams]
        band_targets = [_channels(_render(x0 * TARGET_SCALE, faces, cam, hard=False)) for cam in cams]
    rows = []
    groups = _groups(mesh, dirs)
    for target_kind, targets in (("hard", hard_targets), ("band", band_targets)):
        for channels in CHANNELS:
            x = x0.clone().requires_grad_(True)
            (grad,) = torch.autograd.grad(_loss(x, faces, cams, targets, False, channels), x)
            rng = np.random.default_rng(1)  # the same directions for every channel set
            for group, mask in groups.items():
                for k in range(directions):
                    u = np.zeros((len(mesh.vertices), 3))
                    u[mask] = rng.normal(size=(int(mask.sum()), 3))
                    ut = torch.from_numpy(u / np.linalg.norm(u)).float()
                    auto = float((grad.double() * ut.double()).sum())
                    with torch.no_grad():  # the soft loss on these targets; the hard loss on the hard targets
                        fd = {hard: (float(_loss(x0 + h * ut, faces, cams, hard_targets if hard else targets, hard,
                                                 channels))
                                     - float(_loss(x0 - h * ut, faces, cams, hard_targets if hard else targets, hard,
                                                   channels))) / (2 * h)
                              for hard in (False, True)}
                    rows.append({"resolution": resolution, "targets": target_kind, "channels": channels,
                                 "group": group, "vertices": int(mask.sum()), "direction": k, "autograd": auto,
                                 "fd_soft": fd[False], "fd_hard": fd[True],
                                 "rel_soft": abs(auto - fd[False]) / max(abs(fd[False]), 1e-12),
                                 "rel_hard": abs(auto - fd[True]) / max(abs(fd[True]), 1e-12)})
                    print(f"  {resolution} px {target_kind} {channels} {group} u{k}: autograd {auto:.4g} "
                          f"fd_soft {fd[False]:.4g} fd_hard {fd[True]:.4g}", flush=True)
    return rows


SCENES = {
    "triangle": ([[-.5, -.4, 0.], [.5, -.3, .1], [.1, .5, -.1]], [[0, 1, 2]], [1.0],
                 [[.3, .2, .5], [0, 0, 0], [0, 0, 0]]),
    "triangle, opacity 0.6": ([[-.5, -.4, 0.], [.5, -.3, .1], [.1, .5, -.1]], [[0, 1, 2]], [0.6],
                              [[.3, .2, .5], [0, 0, 0], [0, 0, 0]]),
    "two triangles, edge vertex in the image plane": (
        [[-.5, -.5, 0.], [.5, -.5, .1], [.5, .5, 0.], [-.5, .5, -.1]], [[0, 1, 2], [0, 2, 3]], [1.0, 1.0],
        [[.3, .1, .2], [0, 0, 0], [0, 0, 0], [0, 0, 0]]),
    "two triangles, corner vertex in depth": (
        [[-.5, -.5, 0.], [.5, -.5, .1], [.5, .5, 0.], [-.5, .5, -.1]], [[0, 1, 2], [0, 2, 3]], [1.0, 1.0],
        [[0, 0, 0], [0, 0, .4], [0, 0, 0], [0, 0, 0]]),
}


def small_scenes() -> list[dict]:
    from dmesh.camera import look_at
    from dmesh.render import Camera, soft_render

    cam = Camera(look_at((0.0, 0.0, 2.0)), height=32, width=32)
    rows = []
    for scene, (v, f, op, u) in SCENES.items():
        v, f = torch.tensor(v, dtype=torch.float32), torch.tensor(f)
        op, u = torch.tensor(op, dtype=torch.float32), torch.tensor(u, dtype=torch.float32)
        u = u / u.norm()
        for key in ("alpha", "depth", "diffuse"):
            def total(x):
                return soft_render(x, f, op, cam)[key].double().sum()

            x = v.clone().requires_grad_(True)
            (g,) = torch.autograd.grad(total(x), x)
            row = {"scene": scene, "channel": key, "autograd": float((g.double() * u.double()).sum())}
            with torch.no_grad():
                for h in (1e-2, 3e-3, 1e-3):
                    row[f"fd_h{h:g}"] = (float(total(v + h * u)) - float(total(v - h * u))) / (2 * h)
            row["rel_err"] = abs(row["autograd"] - row["fd_h0.001"]) / max(abs(row["fd_h0.001"]), 1e-12)
            rows.append(row)
    return rows


def main(out: str = "reports", quick: bool = False) -> None:
    small = small_scenes()
    rows = []
    for resolution in ((32,) if quick else (64, 128)):
        # h: about 0.05 pixel at the object (focal length ~ 0.78 R pixels per unit at distance 2)
        h = 0.05 / (0.78 * resolution / 2.0)
        rows += check(resolution, views=2 if quick else 4, directions=2 if quick else 4, h=h)
    cols = ["resolution", "targets", "channels", "group", "vertices", "direction", "autograd", "fd_soft", "fd_hard",
            "rel_soft", "rel_hard"]
    fmt = {c: ".3g" for c in cols[6:]}
    summary = []
    for key in sorted({(r["resolution"], r["targets"], r["channels"], r["group"]) for r in rows}, key=str):
        sel = [r for r in rows if (r["resolution"], r["targets"], r["channels"], r["group"]) == key]
        same = {f: float(np.mean([np.sign(r["autograd"]) == np.sign(r[f]) for r in sel]))
                for f in ("fd_soft", "fd_hard")}
        summary.append({"resolution": key[0], "targets": key[1], "channels": key[2], "group": key[3],
                        "directions": len(sel),
                        "sign_as_fd_soft": same["fd_soft"], "sign_as_fd_hard": same["fd_hard"],
                        "median_rel_soft": float(np.median([r["rel_soft"] for r in sel])),
                        "median_rel_hard": float(np.median([r["rel_hard"] for r in sel]))})
    small_cols = ["scene", "channel", "autograd", "fd_h0.01", "fd_h0.003", "fd_h0.001", "rel_err"]
    intro = __doc__.split("\n\n", 1)[1].rsplit("Regenerate", 1)[0].strip()
    sum_cols = ["resolution", "targets", "channels", "group", "directions", "sign_as_fd_soft", "sign_as_fd_hard",
                "median_rel_soft", "median_rel_hard"]
    table = (markdown_table(small, small_cols, {c: ".5g" for c in small_cols[2:]}) + "\n\n"
             + "Sphere, per group: the fraction of directions where autograd has the sign of each difference, and the"
             " median relative errors.\n\n" + markdown_table(summary, sum_cols, {c: ".2f" for c in sum_cols[5:]})
             + "\n\nSphere, every direction:\n\n" + markdown_table(rows, cols, fmt))
    write_report(out, "bench_render_gradients", "Soft-render gradients against a hard render", intro, table,
                 rows)


if __name__ == "__main__":
    main()
