"""A numpy backend for the model's entry code: float64 kinematics for the verdict and
the figures, independent of JAX's precision setting."""

from __future__ import annotations

from typing import Any

import numpy as np

from ..model._ops import Ops


def _stack_points(per_segment: list[tuple[Any, Any, Any]]) -> np.ndarray:
    return np.concatenate([np.stack(np.broadcast_arrays(*xyz), axis=-1) for xyz in per_segment],
                          axis=-2)


NUMPY = Ops(
    name="numpy",
    sin=np.sin,
    cos=np.cos,
    sqrt=np.sqrt,
    atan2=np.arctan2,
    where=np.where,
    fmax=np.maximum,
    fmin=np.minimum,
    entry=lambda x, i: x[..., i],
    stack=lambda xs: np.stack(np.broadcast_arrays(*xs), axis=-1),
    along=lambda x: np.asarray(x)[..., None],
    fractions=lambda s: np.asarray(s, dtype=float),
    stack_points=_stack_points,
    materialize=lambda x: x,
)
