"""Where each tendon runs: the one description of a robot's tendon routing (docs/design.md
§1) that kinematics, the actuation model, the tendon groups, the Cosserat layout and the
drawings read.

``per_segment``: segment k's m tendons end at segment k and run through segments 0…k; the
tendon order is ``[segment 0's m, segment 1's m, …]``, and a tendon sits at its own
segment's angle in every segment it crosses. ``shared``: m tendons run through every
segment and end at the tip; inside segment i a tendon sits at segment i's angle (its
slot's angle plus segment i's offset). Slot j of m is at 2πj/m rad before the offsets.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from ..runtime import cached


class _Tendons(Protocol):
    per_segment: int
    offsets: tuple[float, ...]
    routing: str


class Robot(Protocol):
    """What routing reads of a ``model.robot.Robot`` (this module sits below it)."""

    @property
    def n_segments(self) -> int: ...

    @property
    def tendons(self) -> _Tendons: ...


def tendon_count(per_segment: int, n_segments: int, routing: str) -> int:
    """How many tendons a robot has: m for shared routing, m per segment otherwise."""
    return per_segment if routing == "shared" else per_segment * n_segments


@dataclass(frozen=True)
class TendonRouting:
    """Per tendon t of T (the robot file's order) and segment i of n."""

    through: np.ndarray   # (T, n) bool: the segments tendon t runs through (and bends)
    anchor: np.ndarray    # (T,) the segment where tendon t ends (its stiffness group)
    slot: np.ndarray      # (T,) its place among the m tendons around the disks
    owner: np.ndarray     # (T, n) the segment whose offset sets its angle inside segment i
    # (int32: it indexes offsets a program traces; under ``jax.enable_x64``, which the
    # float64 stages enter and leave, an int64 index made JAX's gather mix int64 and int32
    # in a program traced later without it: TypeError in lax.add)
    slot_angle: np.ndarray  # (T,) 2π slot / m, rad, before any offset
    shared: bool          # every tendon runs to the tip (``shared``), else per segment

    @property
    def first(self) -> np.ndarray:
        """(T,) the first segment each tendon runs through (0: every tendon starts at the
        base)."""
        return np.argmax(self.through, axis=1)

    def names(self) -> list[str]:
        """Each tendon's name in tables and CSV columns: ``tendon_<j>`` (shared) or
        ``tendon_<segment>_<j>`` (per segment), counted from 1."""
        if self.shared:
            return [f"tendon_{j + 1}" for j in self.slot]
        return [f"tendon_{k + 1}_{j + 1}" for k, j in zip(self.anchor, self.slot, strict=True)]

    def angles(self, offsets: Any, xp: Any = np) -> Any:
        """(T, n) angle α of tendon t inside segment i, rad, for per-segment ``offsets``
        (n,) rad (defined, but unused, where the tendon does not run). ``xp``: numpy
        (float64), or ``jax.numpy`` for offsets a compiled program takes as data."""
        return self.slot_angle[:, None] + xp.asarray(offsets, dtype=float)[self.owner]


def routing_of(robot: Robot) -> TendonRouting:
    """The routing of ``robot``'s tendons (see the module), derived once per robot shape
    (segments, tendons per segment, routing; the arrays are read-only, shared by every
    caller)."""
    return _routing(robot.n_segments, robot.tendons.per_segment, robot.tendons.routing)


@cached(maxsize=64)
def _routing(n: int, m: int, routing: str) -> TendonRouting:
    count = tendon_count(m, n, routing)
    tendon = np.arange(count)
    slot = tendon % m
    segment = np.arange(n)
    shared = routing == "shared"
    if shared:
        anchor = np.full(count, n - 1)
        owner = np.tile(segment, (count, 1))
    else:
        anchor = tendon // m
        owner = np.repeat(anchor[:, None], n, axis=1)
    arrays = {"through": segment[None, :] <= anchor[:, None], "anchor": anchor,
              "slot": slot, "owner": owner.astype(np.int32), "slot_angle": slot * 2.0 * np.pi / m}
    for value in arrays.values():
        value.flags.writeable = False
    return TendonRouting(**arrays, shared=shared)


def tendon_names(robot: Robot) -> list[str]:
    """The tendons' names in the robot file's order (``tendon_lengths``' columns, the CSV
    headers of every tendon series)."""
    return routing_of(robot).names()


def tendon_angles(robot: Robot) -> np.ndarray:
    """(T, n) angle α of each tendon inside each segment, rad (the robot's offsets)."""
    return routing_of(robot).angles(robot.tendons.offsets)
