"""Headless OpenGL for the capture (`datasets.capture`): the platform (OSMesa first, EGL if OSMesa cannot be
loaded; PYOPENGL_PLATFORM forces one) through pyrender's platform layer, and `Rasterizer`, the small shader
pipeline that writes, per pixel centre, the camera-space depth and the id of the front-most face (no
multisampling, no culling, a float32 depth buffer). What the images are made of: `datasets.capture`.
"""
from __future__ import annotations

import logging
import os
import sys
import threading

import numpy as np

log = logging.getLogger(__name__)

__all__ = ["GLUnavailableError", "GL_LOCK", "gl_problem", "gl_platform", "Rasterizer"]


class GLUnavailableError(RuntimeError):
    """No headless OpenGL platform (OSMesa or EGL) could be started."""


_PLATFORM: str | None = None
#: One GL context renders at a time in a process (contexts and PyOpenGL state are not shared safely).
GL_LOCK = threading.RLock()

_VERT = """#version 330 core
layout(location = 0) in vec3 position;
uniform mat4 world_to_camera;
uniform mat4 projection;
out float v_depth;
void main() {
    vec4 cam = world_to_camera * vec4(position, 1.0);
    v_depth = -cam.z;
    gl_Position = projection * cam;
}
"""

_FRAG = """#version 330 core
in float v_depth;
layout(location = 0) out vec4 out_value;
void main() {
    out_value = vec4(v_depth, float(gl_PrimitiveID + 1), 0.0, 1.0);
}
"""


def gl_problem() -> str | None:
    """None when headless OpenGL works here (`gl_platform`), else the one-line reason it does not."""
    try:
        gl_platform()
        return None
    except RuntimeError as exc:
        return str(exc)


def gl_platform() -> str:
    """Import PyOpenGL on a headless platform and return its name ("osmesa" or "egl").

    PYOPENGL_PLATFORM is honoured when set; otherwise OSMesa is tried first and EGL second (Mesa's
    software EGL device works without a GPU). Raises GLUnavailableError naming each failure.
    """
    global _PLATFORM
    if _PLATFORM is not None:
        return _PLATFORM
    forced = os.environ.get("PYOPENGL_PLATFORM")
    candidates = [forced] if forced else ["osmesa", "egl"]
    errors = []
    for name in candidates:
        os.environ["PYOPENGL_PLATFORM"] = name
        try:
            _make_platform(name, 8, 8).delete_context()
            _PLATFORM = name
            log.debug("OpenGL platform: %s", name)
            return name
        except Exception as exc:  # a missing library shows up as ImportError, OSError or others
            errors.append(f"{name}: {type(exc).__name__}: {' '.join(str(exc).split())}")
            # PyOpenGL binds its platform on first import: forget it so the next candidate can load.
            for mod in [m for m in sys.modules if m == "OpenGL" or m.startswith("OpenGL.")
                        or m == "pyrender" or m.startswith("pyrender.")]:
                del sys.modules[mod]
    if not forced:
        os.environ.pop("PYOPENGL_PLATFORM", None)
    raise GLUnavailableError("no headless OpenGL platform works (install libosmesa6 or libegl1): " + "; ".join(errors))


def _make_platform(name: str, width: int, height: int):
    """A current pyrender platform (OpenGL 3.3 core context) of the given name."""
    if name == "osmesa":
        from pyrender.platforms.osmesa import OSMesaPlatform
        plat = OSMesaPlatform(width, height)
    elif name == "egl":
        from pyrender.platforms.egl import EGLPlatform
        plat = EGLPlatform(width, height)
    else:
        raise RuntimeError(f"unsupported PYOPENGL_PLATFORM {name!r} (use osmesa or egl)")
    plat.init_context()
    plat.make_current()
    return plat


class Rasterizer:
    """Face-id and depth rasteriser in an offscreen framebuffer (one context per instance)."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, resolution: int):
        platform = gl_platform()
        self.resolution = resolution
        self.plat = _make_platform(platform, resolution, resolution)
        from OpenGL import GL as gl
        self.gl = gl
        try:
            self._setup(vertices, faces)
        except BaseException:
            self.close()
            raise

    def _setup(self, vertices, faces):
        gl, r = self.gl, self.resolution
        self.program = gl.glCreateProgram()
        for kind, src in ((gl.GL_VERTEX_SHADER, _VERT), (gl.GL_FRAGMENT_SHADER, _FRAG)):
            sh = gl.glCreateShader(kind)
            gl.glShaderSource(sh, src)
            gl.glCompileShader(sh)
            if not gl.glGetShaderiv(sh, gl.GL_COMPILE_STATUS):
                raise RuntimeError(f"shader compile failed: {gl.glGetShaderInfoLog(sh)!r}")
            gl.glAttachShader(self.program, sh)
        gl.glLinkProgram(self.program)
        if not gl.glGetProgramiv(self.program, gl.GL_LINK_STATUS):
            raise RuntimeError(f"shader link failed: {gl.glGetProgramInfoLog(self.program)!r}")

        self.fbo = gl.glGenFramebuffers(1)
        gl.glBindFramebuffer(gl.GL_FRAMEBUFFER, self.fbo)
        self.color = gl.glGenRenderbuffers(1)
        gl.glBindRenderbuffer(gl.GL_RENDERBUFFER, self.color)
        gl.glRenderbufferStorage(gl.GL_RENDERBUFFER, gl.GL_RGBA32F, r, r)
        gl.glFramebufferRenderbuffer(gl.GL_FRAMEBUFFER, gl.GL_COLOR_ATTACHMENT0, gl.GL_RENDERBUFFER, self.color)
        self.depth_rb = gl.glGenRenderbuffers(1)
        gl.glBindRenderbuffer(gl.GL_RENDERBUFFER, self.depth_rb)
        gl.glRenderbufferStorage(gl.GL_RENDERBUFFER, gl.GL_DEPTH_COMPONENT32F, r, r)
        gl.glFramebufferRenderbuffer(gl.GL_FRAMEBUFFER, gl.GL_DEPTH_ATTACHMENT, gl.GL_RENDERBUFFER,
                                     self.depth_rb)
        status = gl.glCheckFramebufferStatus(gl.GL_FRAMEBUFFER)
        if status != gl.GL_FRAMEBUFFER_COMPLETE:
            raise RuntimeError(f"offscreen framebuffer incomplete (status {status})")

        self.vao = gl.glGenVertexArrays(1)
        gl.glBindVertexArray(self.vao)
        self.vbo, self.ebo = gl.glGenBuffers(2)
        v = np.ascontiguousarray(vertices, np.float32)
        f = np.ascontiguousarray(faces, np.uint32)
        gl.glBindBuffer(gl.GL_ARRAY_BUFFER, self.vbo)
        gl.glBufferData(gl.GL_ARRAY_BUFFER, v.nbytes, v, gl.GL_STATIC_DRAW)
        gl.glEnableVertexAttribArray(0)
        gl.glVertexAttribPointer(0, 3, gl.GL_FLOAT, gl.GL_FALSE, 0, None)
        gl.glBindBuffer(gl.GL_ELEMENT_ARRAY_BUFFER, self.ebo)
        gl.glBufferData(gl.GL_ELEMENT_ARRAY_BUFFER, f.nbytes, f, gl.GL_STATIC_DRAW)
        self.count = int(f.size)

        gl.glViewport(0, 0, self.resolution, self.resolution)
        gl.glDisable(gl.GL_CULL_FACE)
        gl.glDisable(gl.GL_MULTISAMPLE)
        gl.glDisable(gl.GL_BLEND)
        gl.glDisable(gl.GL_DITHER)
        gl.glEnable(gl.GL_DEPTH_TEST)
        gl.glDepthFunc(gl.GL_LESS)
        gl.glUseProgram(self.program)
        self.loc_w2c = gl.glGetUniformLocation(self.program, "world_to_camera")
        self.loc_proj = gl.glGetUniformLocation(self.program, "projection")

    def render(self, world_to_camera: np.ndarray, projection: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rasterise one view: (H, W) float32 depth (-z_cam, 0 = none) and (H, W) int64 face id (-1 = none)."""
        gl, r = self.gl, self.resolution
        gl.glBindFramebuffer(gl.GL_FRAMEBUFFER, self.fbo)
        gl.glClearColor(0.0, 0.0, 0.0, 0.0)
        gl.glClearDepth(1.0)
        gl.glClear(gl.GL_COLOR_BUFFER_BIT | gl.GL_DEPTH_BUFFER_BIT)
        # GL matrices are column-major: upload the transpose flag so rows stay rows.
        gl.glUniformMatrix4fv(self.loc_w2c, 1, gl.GL_TRUE, np.ascontiguousarray(world_to_camera, np.float32))
        gl.glUniformMatrix4fv(self.loc_proj, 1, gl.GL_TRUE, np.ascontiguousarray(projection, np.float32))
        gl.glDrawElements(gl.GL_TRIANGLES, self.count, gl.GL_UNSIGNED_INT, None)
        gl.glFinish()
        gl.glReadBuffer(gl.GL_COLOR_ATTACHMENT0)
        buf = gl.glReadPixels(0, 0, r, r, gl.GL_RGBA, gl.GL_FLOAT)
        img = np.frombuffer(buf, np.float32).reshape(r, r, 4)[::-1]  # GL rows start at the bottom
        depth = np.ascontiguousarray(img[..., 0])
        face = img[..., 1].astype(np.int64) - 1
        depth[face < 0] = 0.0
        return depth, face

    def close(self):
        plat, self.plat = getattr(self, "plat", None), None
        if plat is None:
            return
        try:
            gl = self.gl
            for name, fn in (("vbo", lambda x: gl.glDeleteBuffers(1, [x])),
                             ("ebo", lambda x: gl.glDeleteBuffers(1, [x])),
                             ("vao", lambda x: gl.glDeleteVertexArrays(1, [x])),
                             ("color", lambda x: gl.glDeleteRenderbuffers(1, [x])),
                             ("depth_rb", lambda x: gl.glDeleteRenderbuffers(1, [x])),
                             ("fbo", lambda x: gl.glDeleteFramebuffers(1, [x]))):
                if hasattr(self, name):
                    fn(getattr(self, name))
            if hasattr(self, "program"):
                gl.glDeleteProgram(self.program)
        finally:
            plat.delete_context()
