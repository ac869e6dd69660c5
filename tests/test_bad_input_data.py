"""Bad input data, one case a row: loaders check what they read, and outputs lose nothing (issue 15).

Three tables. MESHES: mesh files that must load with the right counts at any coordinate scale (the vertex
merge once overflowed at 1e12 and over-merged at 1e11). BAD_MESHES: mesh files that must fail as one line on
stderr with exit status 2, through `dmesh metrics` (which reads both meshes with `datasets.meshes.load_mesh`).
BAD_POINTS: point clouds that must fail the same way through `dmesh reconstruct pointcloud` before any work.
Then full-precision mesh outputs (`eval.io.write_mesh`) and outputs that honour the umask.
"""
from __future__ import annotations

import ast
import dataclasses
import os
import stat
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import trimesh

from datasets.meshes import check_off, check_ply, load_mesh, merge_vertices
from eval.io import atomic_path, honour_umask, write_mesh, write_text

ROOT = Path(__file__).resolve().parents[1]
ICO = trimesh.creation.icosphere(3)  # 642 vertices, 1280 faces
assert (len(ICO.vertices), len(ICO.faces)) == (642, 1280)

PLY_XYZ = "ply\nformat {fmt} 1.0\nelement vertex {nv}\nproperty {t} x\nproperty {t} y\nproperty {t} z\n"
PLY_FACE = "element face {nf}\nproperty list uchar int vertex_indices\n"


def _ply_ascii(verts, faces=None, nv=None, nf=None, extra_rows="") -> bytes:
    """An ASCII PLY whose header may declare other counts (nv, nf) than it holds."""
    head = PLY_XYZ.format(fmt="ascii", nv=len(verts) if nv is None else nv, t="double")
    if faces is not None:
        head += PLY_FACE.format(nf=len(faces) if nf is None else nf)
    rows = [" ".join(repr(float(x)) for x in v) for v in np.asarray(verts)]
    rows += [" ".join(str(int(i)) for i in [3, *f]) for f in np.asarray(faces if faces is not None else [])]
    return (head + "end_header\n" + "\n".join(rows) + "\n" + extra_rows).encode()


def _ply_binary(verts, faces=None, nv=None, nf=None, tail=b"") -> bytes:
    head = PLY_XYZ.format(fmt="binary_little_endian", nv=len(verts) if nv is None else nv, t="float")
    body = np.asarray(verts, "<f4").tobytes()
    if faces is not None:
        head += PLY_FACE.format(nf=len(faces) if nf is None else nf)
        packed = np.zeros(len(faces), dtype=[("n", "u1"), ("i", "<i4", (3,))])
        packed["n"], packed["i"] = 3, faces
        body += packed.tobytes()
    return (head + "end_header\n").encode() + body + tail


def _obj(verts, faces) -> bytes:
    return ("".join(f"v {x!r} {y!r} {z!r}\n" for x, y, z in np.asarray(verts, float).tolist())
            + "".join(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in np.asarray(faces).tolist())).encode()


def _off(verts, faces, nv=None, nf=None, extra="") -> bytes:
    head = f"OFF\n{len(verts) if nv is None else nv} {len(faces) if nf is None else nf} 0\n"
    return (head + "".join(f"{x!r} {y!r} {z!r}\n" for x, y, z in np.asarray(verts, float).tolist())
            + "".join(f"3 {a} {b} {c}\n" for a, b, c in np.asarray(faces).tolist()) + extra).encode()


def _scaled(scale=1.0, shift=0.0) -> trimesh.Trimesh:
    return trimesh.Trimesh(ICO.vertices * scale + shift, ICO.faces, process=False)


# --------------------------------------------------------------------------- meshes that must load intact

def _written(suffix, scale=1.0, shift=0.0):
    def make(folder: Path) -> Path:
        path = folder / f"mesh{suffix}"
        write_mesh(_scaled(scale, shift), path)
        return path
    return make


def _trimesh_export(suffix, scale):
    """Through trimesh's own writer (8-digit OBJ, float32 PLY), as files from elsewhere come."""
    def make(folder: Path) -> Path:
        path = folder / f"mesh{suffix}"
        _scaled(scale).export(path)
        return path
    return make


def _relative(folder: Path) -> Path:
    """Each face written as its own three `v` lines then `f -3 -2 -1` (OBJ's relative indices), with texture
    and normal indices counting back over their own lists: the sphere's 642 vertices and 1280 faces, once
    merged."""
    rows = []
    for a, b, c in ICO.faces.tolist():
        rows += [f"v {x!r} {y!r} {z!r}" for x, y, z in ICO.vertices[[a, b, c]].tolist()]
        rows += ["vt 0 0", "vt 1 0", "vt 0 1", "vn 0 0 1"]
        rows.append("f -3/-3/-1 -2/-2/-1 -1/-1/-1")
    path = folder / "relative.obj"
    path.write_text("\n".join(rows) + "\n")
    return path


def _seams(folder: Path) -> Path:
    """Every face with its own three corners (as OBJ UV seams or STL split them): merged back to 642."""
    tri = ICO.vertices[ICO.faces].reshape(-1, 3) * 1e12
    path = folder / "split.obj"
    path.write_bytes(_obj(tri, np.arange(len(tri)).reshape(-1, 3)))
    return path


MESHES = [  # (id, builder, vertices, faces)
    ("obj-scale-1e12", _written(".obj", 1e12), 642, 1280),
    ("ply-scale-1e12", _written(".ply", 1e12), 642, 1280),
    ("obj-scale-1e11", _written(".obj", 1e11), 642, 1280),
    ("ply-scale-1e11", _written(".ply", 1e11), 642, 1280),
    ("obj-scale-1e-12", _written(".obj", 1e-12), 642, 1280),
    ("ply-scale-1e-12", _written(".ply", 1e-12), 642, 1280),
    ("off-scale-1e-12", _written(".off", 1e-12), 642, 1280),
    ("stl-scale-1e12", _written(".stl", 1e12), 642, 1280),
    ("obj-shift-1e9", _written(".obj", 1.0, 1e9), 642, 1280),
    ("ply-shift-1e9", _written(".ply", 1.0, 1e9), 642, 1280),
    ("obj-scale-0.9e75-below-the-limit", _written(".obj", 0.9e75), 642, 1280),
    ("stl-scale-1e-300", _written(".stl", 1e-300), 642, 1280),
    ("trimesh-obj-scale-1e12", _trimesh_export(".obj", 1e12), 642, 1280),
    ("trimesh-ply-scale-1e11", _trimesh_export(".ply", 1e11), 642, 1280),
    ("split-corners-merged-1e12", _seams, 642, 1280),
    ("obj-relative-face-indices", _relative, 642, 1280),
]


@pytest.mark.parametrize("build,nv,nf", [m[1:] for m in MESHES], ids=[m[0] for m in MESHES])
def test_mesh_loads_intact(tmp_path, build, nv, nf):
    mesh = load_mesh(build(tmp_path))
    assert (len(mesh.vertices), len(mesh.faces)) == (nv, nf)


def test_relative_indices_give_the_same_surface(tmp_path):
    """The relative-index sphere is the sphere: every face the same triangle (a copy scores 0 Chamfer)."""
    mesh = load_mesh(_relative(tmp_path))
    got = np.sort(mesh.vertices[mesh.faces].round(12).reshape(-1, 9), axis=0)
    want = np.sort(ICO.vertices[ICO.faces].round(12).reshape(-1, 9), axis=0)
    assert np.array_equal(got, want)


def test_metrics_near_the_coordinate_limit_are_finite_and_silent(tmp_path, capsys, recwarn):
    """A mesh just below `MAX_COORDINATE` measures against itself without overflow: a copy at CD 0."""
    import json

    path = _written(".obj", 0.9e75)(tmp_path)
    code, err = _cli(["-q", "metrics", str(path), str(path), "--samples", "500", "--json",
                      "--no-self-intersections"], capsys)
    assert code == 0 and err == "", err
    assert not [str(w.message) for w in recwarn.list]


def test_merge_vertices_relative_tolerance():
    # Two copies of the sphere, the second moved by 1e-10 of its size: one sphere at every scale.
    for scale in (1e-12, 1.0, 1e12):
        v = np.r_[ICO.vertices, ICO.vertices + 1e-10] * scale
        f = np.r_[ICO.faces, ICO.faces + len(ICO.vertices)]
        mv, mf = merge_vertices(v, f)
        assert len(mv) == 642 and np.array_equal(mf, np.r_[ICO.faces, ICO.faces])
        assert np.array_equal(mv, v[:642])  # first occurrence, input order


# ---------------------------------------------------------------- mesh files that must fail as one line

V3 = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], float)
F2 = np.array([[0, 1, 2], [0, 2, 3]])
HALF = np.random.default_rng(0).random((2500, 3))

BAD_MESHES = [  # (id, file name, content, fragment of the message)
    ("empty-file", "m.obj", b"", "no faces (empty file)"),
    ("garbage-bytes-ply", "m.ply", bytes(range(256)) * 4, "not a PLY file"),
    ("garbage-bytes-obj", "m.obj", bytes(range(256)) * 4, "no faces"),
    ("garbage-bytes-off", "m.off", bytes(range(128, 256)) * 4, "not an OFF file"),
    ("obj-without-faces", "m.obj", b"v 0 0 0\nv 1 0 0\nv 0 1 0\n", "no faces"),
    ("obj-nan-vertex", "m.obj", b"v 0 0 0\nv nan 0 0\nv 0 1 0\nf 1 2 3\n", "NaN or infinite"),
    ("obj-inf-vertex", "m.obj", b"v 0 0 0\nv inf 0 0\nv 0 1 0\nf 1 2 3\n", "NaN or infinite"),
    ("obj-face-missing-vertex", "m.obj", b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n", "out of bounds"),
    ("obj-all-faces-collapse", "m.obj", b"v 0 0 0\nv 0 0 0\nv 0 0 0\nf 1 2 3\n", "no faces left"),
    ("ply-face-missing-vertex", "m.ply", _ply_ascii(V3, [[0, 1, 9]]), "out of range"),
    ("ply-negative-face-index", "m.ply", _ply_ascii(V3, [[0, 1, -1]]), "out of range"),
    ("ply-nan-vertex", "m.ply", _ply_ascii(np.r_[V3[:3], [[np.nan, 0, 0]]], F2), "NaN or infinite"),
    ("ply-no-vertex-element", "m.ply",
     b"ply\nformat ascii 1.0\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n3 0 1 2\n",
     "no 'vertex' element"),
    ("ply-no-end-header", "m.ply", b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\n",
     "no 'end_header'"),
    ("ply-no-format", "m.ply", b"ply\nelement vertex 0\nend_header\n", "no 'format'"),
    ("ply-bad-property-type", "m.ply",
     b"ply\nformat ascii 1.0\nelement vertex 1\nproperty quaternion x\nend_header\n1\n", "malformed PLY header"),
    ("ply-ascii-fewer-vertices-than-header", "m.ply", _ply_ascii(V3, F2, nv=5000),
     "declares 5000 'vertex' elements"),
    ("ply-ascii-fewer-faces-than-header", "m.ply", _ply_ascii(V3, F2, nf=3), "declares 3 'face' elements"),
    ("ply-ascii-more-rows-than-header", "m.ply", _ply_ascii(V3, F2, extra_rows="3 0 1 3\n"),
     "more than its header"),
    ("ply-ascii-face-row-too-short", "m.ply", _ply_ascii(V3, F2).replace(b"3 0 2 3", b"3 0 2"),
     "does not match"),
    ("ply-ascii-vertex-row-too-long", "m.ply", _ply_ascii(V3, F2).replace(b"1.0 0.0 0.0", b"1.0 0.0 0.0 7"),
     "has 4 values"),
    ("ply-binary-fewer-vertices-than-header", "m.ply", _ply_binary(V3, F2, nv=5000),
     "declares 5000 'vertex' elements"),
    ("ply-binary-fewer-faces-than-header", "m.ply", _ply_binary(V3, F2, nf=5), "declares 5 'face' elements"),
    ("ply-binary-trailing-bytes", "m.ply", _ply_binary(V3, F2, tail=b"\0" * 7), "7 bytes more"),
    ("off-fewer-vertices-than-header", "m.off", _off(V3, F2, nv=9), "declares 9 vertices"),
    ("off-fewer-faces-than-header", "m.off", _off(V3, F2, nf=5), "declares 5 faces"),
    ("off-more-lines-than-header", "m.off", _off(V3, F2, extra="3 0 1 3\n"), "more than its header"),
    ("off-face-missing-vertex", "m.off", _off(V3, [[0, 1, 9]]), "outside the range"),
    ("off-no-header", "m.off", b"4 2 0\n0 0 0\n", "not an OFF file"),
    ("unsupported-suffix", "m.xyz", b"0 0 0\n", "unsupported mesh format"),
    ("obj-scale-1e300", "m.obj", _obj(ICO.vertices * 1e300, ICO.faces), "coordinates up to 1e+300"),
    ("ply-span-3e308-wider-than-float", "m.ply", _ply_ascii(ICO.vertices * 1.5e308, ICO.faces),
     "at most 1e+75 are supported"),
    ("obj-one-coordinate-past-the-limit", "m.obj", b"v 0 0 0\nv 1 0 0\nv 0 2e75 0\nf 1 2 3\n", "coordinates up to 2e+75"),
    ("obj-relative-index-before-the-first-vertex", "m.obj", b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf -4 -2 -1\n",
     "line 4: face index -4 reaches before the first v line"),
]


def _cli(argv, capsys):
    from eval.cli import main

    code = main(argv)
    return code, capsys.readouterr().err


@pytest.mark.parametrize("name,content,match", [c[1:] for c in BAD_MESHES], ids=[c[0] for c in BAD_MESHES])
def test_bad_mesh_is_one_line_error(tmp_path, capsys, recwarn, name, content, match):
    good = tmp_path / "good.ply"
    write_mesh(ICO, good)
    bad = tmp_path / name
    bad.write_bytes(content)
    code, err = _cli(["-q", "metrics", str(bad), str(good), "--samples", "100"], capsys)
    assert code == 2, err
    assert err.strip().count("\n") == 0 and err.startswith("dmesh metrics: error:") and match in err, err
    assert not [str(w.message) for w in recwarn.list]  # a warning would be a second line on a terminal


def test_a_ground_truth_of_no_area_is_one_line(tmp_path, capsys, recwarn):
    """As the GT (oriented at load), a mesh whose faces all have zero area is refused before its winding is
    judged (it once warned about the winding first); as a prediction it scores as empty."""
    flat = tmp_path / "flat.obj"
    flat.write_bytes(b"v 0 0 0\nv 1 0 0\nv 2 0 0\nv 3 0 0\nf 1 2 3\nf 2 3 4\n")
    good = tmp_path / "good.ply"
    write_mesh(ICO, good)
    code, err = _cli(["-q", "metrics", str(good), str(flat), "--samples", "100"], capsys)
    assert code == 2 and err.count("\n") == 1 and "no face has a positive area" in err, err
    assert not [str(w.message) for w in recwarn.list]


def test_header_checks_pass_the_shared_formats(tmp_path):
    """What the project writes, and trimesh's own binary/ASCII PLY, pass the header checks."""
    for i, data in enumerate([ICO.export(file_type="ply"), ICO.export(file_type="ply", encoding="ascii")]):
        (tmp_path / f"t{i}.ply").write_bytes(data)
        assert check_ply(tmp_path / f"t{i}.ply") == {"vertex": 642, "face": 1280}
    write_mesh(ICO, tmp_path / "w.ply")
    write_mesh(ICO, tmp_path / "w.off")
    assert check_ply(tmp_path / "w.ply") == {"vertex": 642, "face": 1280}
    assert check_off(tmp_path / "w.off") == (642, 1280)


# ------------------------------------------------------------ point clouds that must fail as one line

def _npy(arr):
    def make(path: Path) -> None:
        np.save(path, arr, allow_pickle=True)
    return make


def _bytes(data: bytes):
    return lambda path: path.write_bytes(data)


PTS = np.random.default_rng(1).random((50, 3))
NAN_PTS = PTS.copy()
NAN_PTS[7, 1] = np.nan
INF_NORMALS = np.c_[PTS, PTS]
INF_NORMALS[3, 4] = np.inf
STRUCT = np.zeros(50, dtype=[("x", "f8"), ("y", "f8"), ("z", "f8")])

BAD_POINTS = [  # (id, suffix, builder, fragment of the message)
    ("npy-complex", ".npy", _npy(PTS + 1j), "complex numbers"),
    ("npy-complex-zero-imaginary", ".npy", _npy(PTS.astype(complex)), "complex numbers"),
    ("npy-boolean", ".npy", _npy(PTS > 0.5), "booleans"),
    ("npy-strings", ".npy", _npy(PTS.astype(str)), "text"),
    ("npy-bytes", ".npy", _npy(PTS.astype("S8")), "text"),
    ("npy-objects", ".npy", _npy(PTS.astype(object)), "cannot read"),
    ("npy-records", ".npy", _npy(STRUCT), "records"),
    ("npy-nan", ".npy", _npy(NAN_PTS), "1 points have NaN or infinite"),
    ("npy-inf-normals", ".npy", _npy(INF_NORMALS), "1 normals have NaN or infinite"),
    ("npy-two-columns", ".npy", _npy(PTS[:, :2]), "rows of 3"),
    ("npy-no-points", ".npy", _npy(np.zeros((0, 3))), "no points"),
    ("npy-garbage-bytes", ".npy", _bytes(bytes(range(256))), "cannot read"),
    ("xyz-nan", ".xyz", _bytes(b"0 0 0\nnan 1 0\n0 1 1\n"), "NaN or infinite"),
    ("xyz-inf", ".xyz", _bytes(b"0 0 0\n1 -inf 0\n0 1 1\n"), "NaN or infinite"),
    ("xyz-complex-text", ".xyz", _bytes(b"0 0 0\n1+2j 0 0\n"), "cannot read"),
    ("empty-file", ".xyz", _bytes(b""), "empty file"),
    ("ply-ascii-header-5000-holds-2500", ".ply", _bytes(_ply_ascii(HALF, nv=5000)),
     "declares 5000 'vertex' elements but the file holds only 2500"),
    ("ply-binary-header-5000-holds-2500", ".ply", _bytes(_ply_binary(HALF, nv=5000)),
     "declares 5000 'vertex' elements but the binary data holds only 2500"),
    ("ply-points-nan", ".ply", _bytes(_ply_ascii(NAN_PTS)), "NaN or infinite"),
    ("ply-points-no-vertex-element", ".ply", _bytes(b"ply\nformat ascii 1.0\nend_header\n"),
     "no 'vertex' element"),
    ("ply-points-garbage", ".ply", _bytes(b"\x00ply" + bytes(range(256))), "not a PLY file"),
    ("xyz-comments-only", ".xyz", _bytes(b"# a header and nothing else\n"), "no points"),
    ("npy-coordinates-1e300", ".npy", _npy(PTS * 1e300), "coordinates up to"),
    ("npy-points-on-a-line", ".npy", _npy(np.c_[np.linspace(0, 1, 3000), np.zeros((3000, 2))]),
     "all 3000 points lie on one line"),
    ("npy-points-on-a-slanted-line", ".npy", _npy(np.linspace(0, 1, 500)[:, None] * [[1.0, 2.0, -3.0]] + 7),
     "lie on one line"),
    ("npy-zero-length-normals", ".npy", _npy(np.c_[PTS, np.r_[np.zeros((2, 3)), PTS[2:]]]),
     "2 normals have zero length"),
]


@pytest.mark.parametrize("suffix,build,match", [c[1:] for c in BAD_POINTS], ids=[c[0] for c in BAD_POINTS])
def test_bad_points_is_one_line_error(tmp_path, capsys, recwarn, suffix, build, match):
    src = tmp_path / f"in{suffix}"
    build(src)
    out = tmp_path / "out.obj"
    code, err = _cli(["-q", "reconstruct", "pointcloud", str(src), "-o", str(out), "--preset", "tiny"], capsys)
    assert code == 2, err
    assert err.strip().count("\n") == 0 and match in err, err
    assert not out.exists() and not list(tmp_path.glob("*.json"))
    assert not [str(w.message) for w in recwarn.list]  # a warning would be a second line on a terminal


# ------------------------------------------------------------------------------ full-precision outputs

@pytest.mark.parametrize("suffix", [".obj", ".ply", ".off", ".stl"])
@pytest.mark.parametrize("scale,shift", [(1e-12, 0.0), (1.0, 1e9), (1e12, 0.0)],
                         ids=["scale-1e-12", "shift-1e9", "scale-1e12"])
def test_write_mesh_keeps_every_bit(tmp_path, suffix, scale, shift):
    # A sphere with random float64 noise in every last bit: 8 decimals (.obj) or float32 (.ply) lose it.
    rng = np.random.default_rng(2)
    mesh = _scaled(scale, shift)
    mesh.vertices = mesh.vertices * (1 + rng.uniform(-1e-12, 1e-12, mesh.vertices.shape))
    write_mesh(mesh, tmp_path / f"m{suffix}")
    back = load_mesh(tmp_path / f"m{suffix}")
    if suffix == ".stl":  # STL stores each triangle's corners: compare the triangles
        assert np.array_equal(back.vertices[back.faces], mesh.vertices[mesh.faces])
    else:
        assert np.array_equal(back.vertices, mesh.vertices) and np.array_equal(back.faces, mesh.faces)
    assert not list(tmp_path.glob(".*tmp"))


def test_write_mesh_point_cloud_and_bad_suffix(tmp_path):
    pts = np.random.default_rng(3).random((40, 3)) * 1e-12
    write_mesh(trimesh.PointCloud(pts), tmp_path / "p.ply")
    back = trimesh.load(tmp_path / "p.ply", process=False)
    assert np.array_equal(np.asarray(back.vertices), pts)
    with pytest.raises(ValueError, match="cannot write mesh format '.glb'"):
        write_mesh(ICO, tmp_path / "m.glb")
    assert not (tmp_path / "m.glb").exists()


def test_reconstruct_output_keeps_a_1e_minus_12_cloud(tmp_path):
    """`dmesh reconstruct` writes its mesh with `write_mesh` (8-decimal OBJ once gave all zeros at 1e-12)."""
    from eval.commands.reconstruct import write_outputs

    @dataclasses.dataclass
    class Cfg:
        seed: int = 0

    mesh = _scaled(1e-12)
    res = SimpleNamespace(mesh=mesh, timings={"total": 0.0}, info={}, history=[])
    out = tmp_path / "out.obj"
    write_outputs(out, res, Cfg(), {})
    back = trimesh.load(out, process=False)
    assert np.array_equal(np.asarray(back.vertices), mesh.vertices)


# ------------------------------------------------------------------------------------------------ umask

@pytest.fixture
def umask_027():
    old = os.umask(0o027)
    yield 0o027
    os.umask(old)


def _mode(path) -> int:
    return stat.S_IMODE(os.stat(path).st_mode)


def test_outputs_honour_the_umask(tmp_path, umask_027):
    write_text(tmp_path / "a.txt", "x")
    write_mesh(ICO, tmp_path / "m.ply")
    with atomic_path(tmp_path / "b.npz") as tmp, open(tmp, "wb") as fh:  # opens mkstemp's file: keeps its mode
        np.savez(fh, a=np.zeros(3))
    import tempfile

    folder = Path(tempfile.mkdtemp(dir=tmp_path))
    honour_umask(folder)
    assert _mode(tmp_path / "a.txt") == _mode(tmp_path / "m.ply") == _mode(tmp_path / "b.npz") == 0o640
    assert _mode(folder) == 0o750


def test_every_temporary_name_honours_the_umask():
    """Each mkstemp / mkdtemp / NamedTemporaryFile that makes an *output* is followed by `honour_umask` (or is
    `atomic_path`, which calls it); listed exceptions are private scratch files deleted at once."""
    scratch = {("baselines/alpha_wrap.py", "mkstemp"),  # CGAL's OFF written and read back in one call
               ("eval/ray_executor.py", "mkdtemp")}    # a Ray task's private scratch folder, removed after it
    missing = []
    for folder in ("eval", "datasets", "baselines", "dmesh"):
        for path in sorted((ROOT / folder).rglob("*.py")):
            rel = path.relative_to(ROOT).as_posix()
            lines = path.read_text().splitlines()
            for node in ast.walk(ast.parse("\n".join(lines))):
                if not (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)
                        and node.func.attr in ("mkstemp", "mkdtemp", "NamedTemporaryFile")):
                    continue
                after = "\n".join(lines[node.lineno - 1:node.lineno + 6])
                if (rel, node.func.attr) not in scratch and "honour_umask" not in after:
                    if '".old"' in lines[node.lineno - 1]:
                        continue  # a name reserved then removed at once (capture's swap of folders)
                    missing.append(f"{rel}:{node.lineno}")
    assert not missing, f"temporary outputs made without honour_umask: {missing}"
