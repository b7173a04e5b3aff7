"""Wall-clock seconds per solver stage: the fields of a subclass are its stages."""

from __future__ import annotations

from dataclasses import dataclass, fields


@dataclass
class StageTiming:
    """Seconds per stage; compile time is one of the stages, kept apart from the work."""

    @property
    def total(self) -> float:
        return float(sum(getattr(self, f.name) for f in fields(self)))

    def as_dict(self) -> dict[str, float]:
        out = {f.name: float(getattr(self, f.name)) for f in fields(self)}
        out["total"] = self.total
        return out
