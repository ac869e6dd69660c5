"""Array type aliases shared by the library's signatures.

Letters used in shapes across `dmesh`: N points, T tetrahedra, F faces (triangles), E edges,
C candidate faces, H x W pixels, B batch.
"""
from __future__ import annotations

from typing import Union

import numpy as np
import numpy.typing as npt
import torch

FloatArray = npt.NDArray[np.floating]
IndexArray = npt.NDArray[np.integer]
ArrayLike = Union[npt.ArrayLike, torch.Tensor]

#: dtype of every index array crossing the native boundary (see native/src/types.h).
INDEX_DTYPE = np.int32
#: dtype of geometry that decides combinatorics (positions, weights, orthocentres).
GEOMETRY_DTYPE = np.float64
