"""The reconstruction methods by name.

`METHODS` is a plain dict from name to a `baselines.base.Method` instance; other packages (DMesh) register
themselves by adding to it: `METHODS["dmesh"] = DMeshMethod()`.
"""
from __future__ import annotations

from baselines.alpha_wrap import AlphaWrap
from baselines.base import Method
from baselines.bpa import BallPivoting
from baselines.psr import ScreenedPoisson
from baselines.sdf_mc import SignedDistanceMC
from baselines.tsdf import TSDFFusion
from baselines.udf_mc import UnsignedDistanceMC

METHODS: dict[str, Method] = {m.name: m for m in (
    ScreenedPoisson(), SignedDistanceMC(), BallPivoting(), AlphaWrap(), UnsignedDistanceMC(), TSDFFusion())}


def get_method(name: str) -> Method:
    """The registered method `name`; raises ValueError listing the known names."""
    try:
        return METHODS[name]
    except KeyError:
        raise ValueError(f"unknown method {name!r}; choose from {', '.join(sorted(METHODS))}") from None

from baselines.dmesh_pointcloud import DMeshPointCloud  # noqa: E402  (DMesh itself, behind the same interface)

METHODS[DMeshPointCloud.name] = DMeshPointCloud()

from baselines.dmesh_fit import DMeshFromMesh  # noqa: E402  (DMesh from a mesh, Exp. 1 / Table 1)

METHODS[DMeshFromMesh.name] = DMeshFromMesh()

from baselines.dmesh_multiview import DMeshMultiView  # noqa: E402  (DMesh on multi-view images, Exp. 3)

METHODS[DMeshMultiView.name] = DMeshMultiView()

from baselines.flexicubes import FlexiCubes  # noqa: E402  (the paper's Table 2 baselines, re-implemented)
from baselines.nie import NIE  # noqa: E402
from baselines.voromesh import VoroMesh  # noqa: E402

for _paper_baseline in (VoroMesh(), FlexiCubes(), NIE()):
    METHODS[_paper_baseline.name] = _paper_baseline

from baselines.decimate import DecimatedGT, bpa_qem, psr_qem, sdf_mc_qem  # noqa: E402  (reconstruct, then QEM)

for _decimated in (psr_qem(), bpa_qem(), sdf_mc_qem(), DecimatedGT()):
    METHODS[_decimated.name] = _decimated

from baselines.alpha_budget import AlphaWrapBudget  # noqa: E402  (alpha wrapping at a face budget)

METHODS[AlphaWrapBudget.name] = AlphaWrapBudget()
