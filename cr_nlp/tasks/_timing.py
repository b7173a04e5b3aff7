"""Wall-clock seconds per solver stage, the same stage names for every task."""

from __future__ import annotations

import threading
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass, fields
from typing import Any

import jax.monitoring


@dataclass
class StageTiming(Mapping):
    """Seconds per stage (docs/design.md §2's stages; compile time kept apart from the work).

    Read as attributes (``timing.refine``) or as a read-only mapping stage → seconds
    (``timing["refine"]``, ``dict(timing)``; ``"total"`` included), written as
    ``as_dict()`` in every RESULT.json."""

    compile: float = 0.0
    """Tracing and compiling JAX programs (first call of a shape; 0 from the cache)."""
    explore: float = 0.0
    """Stage 1: seeds, beam, roadmap, per-waypoint IK."""
    refine: float = 0.0
    """Stage 2: the batched LM."""
    polish: float = 0.0
    """Stage 3: Ipopt (exact mode only)."""
    verify: float = 0.0
    """The independent float64 / python-fcl verdict."""

    @property
    def total(self) -> float:
        return float(sum(getattr(self, f.name) for f in fields(self)))

    def __getitem__(self, stage: str) -> float:
        if stage == "total":
            return self.total
        if stage not in self.stages():
            raise KeyError(f"no timing stage {stage!r}: the stages are {', '.join(self.stages())}")
        return float(getattr(self, stage))

    def __iter__(self) -> Iterator[str]:
        return iter((*self.stages(), "total"))

    def __len__(self) -> int:
        return len(self.stages()) + 1

    @classmethod
    def stages(cls) -> tuple[str, ...]:
        """The stage names, in order."""
        return tuple(f.name for f in fields(cls))

    def as_dict(self) -> dict[str, float]:
        out = {name: float(getattr(self, name)) for name in self.stages()}
        out["total"] = self.total
        return out

    @classmethod
    def from_dict(cls, data: dict[str, Any] | None) -> StageTiming:
        """The timing of ``as_dict``'s form ("total" is derived; unknown stages raise)."""
        data = {k: v for k, v in (data or {}).items() if k != "total"}
        unknown = sorted(set(data) - set(cls.stages()))
        if unknown:
            raise ValueError(f"timing: unknown stage(s) {unknown}; the stages are "
                             f"{', '.join(cls.stages())}")
        return cls(**{k: float(v) for k, v in data.items()})


# ================================================================ compile-time accounting

_COMPILE = threading.local()


def _on_duration(event: str, duration: float, **_: Any) -> None:
    if event.startswith("/jax/core/compile/") and getattr(_COMPILE, "active", False):
        _COMPILE.seconds += duration


jax.monitoring.register_event_duration_secs_listener(_on_duration)


@contextmanager
def compile_seconds() -> Any:
    """Collects JAX's tracing/lowering/compile durations inside the block (this thread):
    yields a one-element list that holds the total once the block ends."""
    out = [0.0]
    previous = (getattr(_COMPILE, "active", False), getattr(_COMPILE, "seconds", 0.0))
    _COMPILE.active, _COMPILE.seconds = True, 0.0
    try:
        yield out
    finally:
        out[0] = _COMPILE.seconds
        _COMPILE.active, _COMPILE.seconds = previous[0], previous[1] + out[0]
