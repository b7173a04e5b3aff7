"""External loads of the Cosserat statics: what a case may carry, checked (numpy).

A load case of ``model.statics.solve_statics`` (and of the tension-space IK) may hold,
all in the world frame:

- ``tip_force`` (N) and ``tip_moment`` (N·m) on the tip;
- ``gravity`` (m/s²) acting on the backbone's mass per metre and on the disks;
- ``distributed_force`` (N/m): a force per unit length along the whole backbone (a
  flow's drag, a sheath's weight);
- ``point_loads``: wrenches at given arc lengths, each ``{"s": m from the base,
  "force": [N], "moment": [N·m]}`` (a payload held mid-body, a contact, an instrument).
  A point load at s = L is the same as ``tip_force`` / ``tip_moment``.

Every value is checked here, once, and a bad one raises a ``ValueError`` that names the
case and the key (``case 3: point_loads[0].s: ...``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

POINT_LOAD_KEYS = ("s", "force", "moment")
"""The keys of one point load (``s`` required, ``force`` and ``moment`` default zero)."""
LOAD_KEYS = ("tip_force", "tip_moment", "gravity", "distributed_force", "point_loads")
"""The loads of one case: the keyword arguments of ``static_loads`` and the keys of a
loads file (``--loads``)."""


@dataclass(frozen=True)
class StaticLoads:
    """The external loads of a batch of B cases (float64 numpy; world frame unless
    ``in_base_frame`` made a copy in the robot's base frame)."""

    tip_force: np.ndarray
    """(B, 3) force on the tip, N."""
    tip_moment: np.ndarray
    """(B, 3) moment on the tip, N·m."""
    gravity: np.ndarray
    """(B, 3) gravitational acceleration, m/s²."""
    distributed_force: np.ndarray
    """(B, 3) force per unit length along the whole backbone, N/m."""
    point_s: np.ndarray
    """(B, K) arc length of each point load from the base, m (padding: 0 with no load)."""
    point_force: np.ndarray
    """(B, K, 3) force of each point load, N."""
    point_moment: np.ndarray
    """(B, K, 3) moment of each point load, N·m."""

    def in_base_frame(self, base_rotation: np.ndarray) -> StaticLoads:
        """The same loads with every vector in the frame of ``base_rotation`` (3, 3)."""
        r = np.asarray(base_rotation, dtype=float)
        return StaticLoads(self.tip_force @ r, self.tip_moment @ r, self.gravity @ r,
                           self.distributed_force @ r, self.point_s,
                           self.point_force @ r, self.point_moment @ r)

    def rows(self, index: Any) -> StaticLoads:
        """The cases ``index`` (an index array or a boolean mask)."""
        return StaticLoads(*(np.asarray(getattr(self, f))[index] for f in _FIELDS))

    def arrays(self) -> tuple[np.ndarray, ...]:
        """The seven arrays in field order."""
        return tuple(getattr(self, f) for f in _FIELDS)

    def point_load_lists(self) -> list[list[dict]]:
        """The point loads of every case in ``solve_statics``' form, ``[{"s": m, "force":
        [N], "moment": [N·m]}, …]`` per case (padding dropped)."""
        return [[{"s": float(s), "force": f.tolist(), "moment": m.tolist()}
                 for s, f, m in zip(ss, fs, ms, strict=True) if np.any(f) or np.any(m)]
                for ss, fs, ms in zip(self.point_s, self.point_force, self.point_moment,
                                      strict=True)]

    def has_force(self) -> np.ndarray:
        """(B,) True where some external force acts (then the cut's force N is not zero and
        the statics must shoot for M(0))."""
        return (np.any(self.tip_force != 0, axis=1) | np.any(self.gravity != 0, axis=1)
                | np.any(self.distributed_force != 0, axis=1)
                | np.any(self.point_force != 0, axis=(1, 2)))


_FIELDS = ("tip_force", "tip_moment", "gravity", "distributed_force", "point_s",
           "point_force", "point_moment")


def load_cases(value: Any, batch: int, size: int, name: str) -> np.ndarray:
    """A load input as (batch, size) float64: None → zeros, one row → broadcast to every
    case; a wrong shape or a non-finite entry is a ValueError naming ``name`` (and the
    case)."""
    if value is None:
        return np.zeros((batch, size))
    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: expected {size} numbers or ({batch}, {size}), got "
                         f"{value!r:.60}") from None
    if arr.ndim == 1:
        arr = np.broadcast_to(arr, (batch, arr.shape[0]))
    if arr.shape != (batch, size):
        raise ValueError(f"{name}: expected {size} numbers or ({batch}, {size}), got shape "
                         f"{np.shape(value)}")
    if not np.all(np.isfinite(arr)):
        case = int(np.argwhere(~np.isfinite(arr))[0, 0])
        raise ValueError(f"case {case}: {name}: non-finite entries")
    return np.array(arr)


def finite_number(value: Any, where: str) -> float:
    """``value`` as a finite float; a bool, a non-number or a non-finite value raises a
    ValueError naming ``where`` (an integer past float's range counts as infinite)."""
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise ValueError(f"{where}: expected a number, got {value!r:.40}")
    try:
        x = float(value)
    except OverflowError:  # an integer past float's range
        x = math.inf
    if not math.isfinite(x):
        raise ValueError(f"{where}: must be finite, got {value!r:.40}")
    return x


def _vector(value: Any, where: str) -> list[float]:
    if isinstance(value, np.ndarray):
        value = value.tolist()
    if not isinstance(value, (list, tuple)) or len(value) != 3:
        raise ValueError(f"{where}: expected 3 numbers, got {value!r:.60}")
    return [finite_number(v, f"{where}[{j}]") for j, v in enumerate(value)]


def parse_point_loads(value: Any, length: float, where: str) -> list[tuple[float, list, list]]:
    """One case's point loads as [(s, force, moment)], checked: a list of
    ``{"s": m, "force": [N], "moment": [N·m]}`` with 0 ≤ s ≤ ``length`` (m). ``where``
    names the list in errors (``"case 3: point_loads"``)."""
    if value is None:
        return []
    if not isinstance(value, (list, tuple)):
        raise ValueError(f"{where}: expected a list of {{\"s\", \"force\", \"moment\"}} "
                         f"objects, got {value!r:.60}")
    out = []
    for k, load in enumerate(value):
        here = f"{where}[{k}]"
        if not isinstance(load, dict):
            raise ValueError(f"{here}: expected an object with keys 's', 'force', 'moment'")
        unknown = sorted(set(load) - set(POINT_LOAD_KEYS))
        if unknown:
            raise ValueError(f"{here}.{unknown[0]}: unknown key (a point load has 's', "
                             "'force', 'moment')")
        if "s" not in load:
            raise ValueError(f"{here}.s: missing (the arc length from the base, m)")
        s = finite_number(load["s"], f"{here}.s")
        if s < 0.0 or s > length * (1 + 1e-12):
            raise ValueError(f"{here}.s: {s} m lies outside the robot (0 to its length "
                             f"{length:g} m)")
        force = _vector(load.get("force", [0.0, 0.0, 0.0]), f"{here}.force")
        moment = _vector(load.get("moment", [0.0, 0.0, 0.0]), f"{here}.moment")
        out.append((min(s, length), force, moment))
    return out


def _per_case(point_loads: Any, batch: int) -> list[Any]:
    """The point-load input as one list per case: a list of load objects applies to every
    case, a list of ``batch`` lists gives each case its own."""
    if point_loads is None or len(point_loads) == 0:
        return [None] * batch
    if isinstance(point_loads[0], dict):
        return [point_loads] * batch
    if len(point_loads) != batch:
        raise ValueError(f"point_loads: expected a list of point loads or one list per case "
                         f"({batch}), got {len(point_loads)} entries")
    return list(point_loads)


def static_loads(batch: int, length: float, tip_force: Any = None, tip_moment: Any = None,
                 gravity: Any = None, distributed_force: Any = None,
                 point_loads: Any = None) -> StaticLoads:
    """The loads of ``batch`` cases, checked (see the module's docstring for the keys).

    Args:
        batch: number of cases B.
        length: the robot's length, m (point loads must lie on it).
        tip_force, tip_moment, gravity, distributed_force: (3,) or (B, 3) in N, N·m,
            m/s² and N/m, world frame; None is zero.
        point_loads: None, a list of ``{"s": m, "force": [N], "moment": [N·m]}`` for every
            case, or a list of B such lists.

    Raises:
        ValueError: a wrong shape, a non-finite number, an unknown key or an ``s`` off the
            robot, naming the case and the key.
    """
    vectors = [load_cases(v, batch, 3, n) for v, n in (
        (tip_force, "tip_force"), (tip_moment, "tip_moment"), (gravity, "gravity"),
        (distributed_force, "distributed_force"))]
    parsed = [parse_point_loads(p, length, f"case {i}: point_loads")
              for i, p in enumerate(_per_case(point_loads, batch))]
    most = max((len(p) for p in parsed), default=0)
    # Padded to a power of two (zero loads at the base) so that few programs serve all.
    width = 0 if most == 0 else 1 << (most - 1).bit_length()
    point_s = np.zeros((batch, width))
    point_force, point_moment = np.zeros((batch, width, 3)), np.zeros((batch, width, 3))
    for i, loads in enumerate(parsed):
        for k, (s, force, moment) in enumerate(loads):
            point_s[i, k], point_force[i, k], point_moment[i, k] = s, force, moment
    return StaticLoads(*vectors, point_s, point_force, point_moment)
