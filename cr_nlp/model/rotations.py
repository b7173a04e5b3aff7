"""Float64 numpy conversions between unit quaternions (w, x, y, z) and rotation matrices."""

from __future__ import annotations

import numpy as np

from ._ops import NUMPY
from .lie import quat_from_rot, rot_from_quat


def wxyz_from_matrix(rotation: np.ndarray) -> np.ndarray:
    """(…, 3, 3) rotation matrices → (…, 4) unit quaternions (w, x, y, z) with w ≥ 0,
    float64 numpy (evaluated in numpy, whatever JAX's precision setting)."""
    r = np.asarray(rotation, dtype=np.float64)
    entries = tuple(r[..., i, j] for i in range(3) for j in range(3))
    # Float64 numpy: JAX op by op was float32 and compiled every operation anew for each
    # new batch shape (about 1 s of a one-shot ``cr-nlp ik`` call's verification).
    with np.errstate(invalid="ignore", divide="ignore"):  # the branches not selected
        quat = quat_from_rot(NUMPY, entries)
    return np.stack(np.broadcast_arrays(*quat), axis=-1)


def matrix_from_wxyz(wxyz: np.ndarray) -> np.ndarray:
    """(…, 4) unit quaternions (w, x, y, z) → (…, 3, 3) rotation matrices."""
    q = np.asarray(wxyz, dtype=float)
    # Every entry is a product of the components, so already of the batch's shape (no
    # ``np.broadcast_to``: 20 µs each, most of a single quaternion's 0.2 ms).
    entries = rot_from_quat(tuple(q[..., i] for i in range(4)))
    return np.stack(entries, axis=-1).reshape(q.shape[:-1] + (3, 3))
