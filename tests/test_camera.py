"""Camera maths (`dmesh.camera`): the look-at point of a rig, the projection against pyrender's."""
from __future__ import annotations

import numpy as np
import pytest

from datasets import capture as cap
from dmesh.camera import perspective


def test_look_at_point_of_the_capture_rig():
    from dmesh.camera import look_at_point

    w2c, _ = cap.camera_rig(64)
    shifted = w2c.copy()
    shifted[:, :3, 3] -= np.einsum("vij,j->vi", w2c[:, :3, :3], [0.3, -0.2, 0.1])  # rig moved to (0.3, -0.2, 0.1)
    assert np.allclose(look_at_point(w2c), 0.0, atol=1e-9)
    assert np.allclose(look_at_point(shifted), [0.3, -0.2, 0.1], atol=1e-9)
    assert look_at_point(np.repeat(w2c[:1], 3, axis=0)) is None  # one axis: no single nearest point


def test_projection_matches_pyrender_convention():
    pyrender = pytest.importorskip("pyrender", reason="pyrender not installed")
    ours = perspective(65.0, 1.0, 0.1, 100.0)
    theirs = pyrender.PerspectiveCamera(yfov=np.radians(65.0), aspectRatio=1.0, znear=0.1, zfar=100.0)
    assert np.allclose(ours, theirs.get_projection_matrix(64, 64))
