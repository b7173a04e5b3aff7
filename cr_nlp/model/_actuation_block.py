"""The robot file's ``actuation`` block: the calibrated parameters of the motor-command
model (``model.actuation``), its schema and validation. Imports nothing of the model, so
that ``robot.py`` can parse the block while loading a file."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

NOMINAL_TENDON_STIFFNESS_RATIO = 100.0
"""κ without a calibration: tendons 100× stiffer than the backbone in bending."""

HISTORY_VERSION = 1
"""Version of the ``actuation.history`` block this code writes and reads."""

NOMINAL_AXIAL_STIFFNESS_RATIO = 30.0
"""a where a calibration starts fitting axial compression (``calibrate``); a robot file
without ``axial_stiffness_ratio`` has incompressible segments."""


@dataclass(frozen=True)
class History:
    """The history-aware part of the actuation model (the ``actuation.history`` block,
    ``model.history``): each tendon's command passes through K play (backlash)
    operators of widths r_k before the static model, as a Prandtl–Ishlinskii sum

        d_eff_j(t) = d_j(t) + Σ_k w_jk · (play_{r_k}(d_j)(t) − d_j(t)),

    with w_jk ≥ 0 and Σ_k w_jk < 1, so d_eff rises strictly with d (the operator is
    invertible: ``model.history.compensate_commands``)."""

    widths: tuple[float, ...]
    """Play widths r_k shared by every tendon, m (> 0, increasing)."""
    weights: tuple[tuple[float, ...], ...]
    """(n_tendons, K) weight of each play operator for each tendon (≥ 0, each row's sum
    < 1; dimensionless)."""
    kind: str = "play"
    """The operator family; "play" is the only one."""
    model_error_mean: float | None = None
    """Mean tip error (m) of the history-aware model on the calibration's validation rows
    (or its training rows)."""
    model_error_p95: float | None = None
    """95th-percentile tip error (m) of the history-aware model on the same rows."""
    fold_score: float | None = None
    """Mean held-out tip error (m) over the leave-one-family-out folds of the training rows
    that chose this model (``tasks.calibration.history``), None when it was not chosen by folds."""

    def to_dict(self) -> dict[str, Any]:
        """The JSON form of the ``history`` block (round-trips through ``parse_history``)."""
        out: dict[str, Any] = {"version": HISTORY_VERSION, "kind": self.kind,
                               "widths": list(self.widths),
                               "weights": [list(row) for row in self.weights]}
        for key in ("model_error_mean", "model_error_p95", "fold_score"):
            if getattr(self, key) is not None:
                out[key] = getattr(self, key)
        return out


def _steps(values: tuple[float, ...]) -> list[float]:
    """Differences of consecutive values."""
    return [b - a for a, b in zip(values[:-1], values[1:], strict=True)]


_HISTORY_KEYS = {"version", "kind", "widths", "weights", "model_error_mean",
                 "model_error_p95", "fold_score", "description"}


def parse_history(checker: Any, raw: Any, n_tendons: int) -> History:
    """The ``actuation.history`` block, checked field by field (``ModelFileError`` naming
    the field)."""
    h = checker.obj(raw, "actuation.history", _HISTORY_KEYS, {"version", "widths", "weights"})
    version = checker.integer(h["version"], "actuation.history.version", 1, 10 ** 6)
    if version != HISTORY_VERSION:
        raise checker.fail("actuation.history.version",
                           f"this cr_nlp reads version {HISTORY_VERSION}, got {version}")
    kind = h.get("kind", "play")
    if kind != "play":
        raise checker.fail("actuation.history.kind", f"must be 'play', got {kind!r}")
    raw_widths = h["widths"]
    if not isinstance(raw_widths, list) or not raw_widths:
        raise checker.fail("actuation.history.widths", "expected a non-empty list of metres")
    widths = checker.vector(raw_widths, "actuation.history.widths", len(raw_widths))
    if any(w <= 0 for w in widths) or any(step <= 0 for step in _steps(widths)):
        raise checker.fail("actuation.history.widths",
                           f"must be positive and increasing, got {list(widths)}")
    rows = h["weights"]
    if not isinstance(rows, list) or len(rows) != n_tendons:
        raise checker.fail("actuation.history.weights",
                           f"expected {n_tendons} rows (one per tendon) of {len(widths)} numbers")
    weights = tuple(checker.vector(row, f"actuation.history.weights[{j}]", len(widths))
                    for j, row in enumerate(rows))
    for j, row in enumerate(weights):
        if min(row) < 0 or sum(row) >= 1:
            raise checker.fail(f"actuation.history.weights[{j}]",
                               f"must be ≥ 0 with a sum below 1, got {list(row)}")
    errors = {key: checker.number(h[key], f"actuation.history.{key}", nonnegative=True)
              for key in ("model_error_mean", "model_error_p95", "fold_score") if key in h}
    return History(widths, weights, kind, **errors)


@dataclass(frozen=True)
class Actuation:
    """The calibrated actuation of a robot (the robot file's ``actuation`` block).

    Per-tendon tuples follow the robot file's tendon order (segment by segment).
    """

    zero_offsets: tuple[float, ...]
    """Command (m) at which each tendon is just taut with the backbone straight."""
    gains: tuple[float, ...]
    """Effective pull per commanded metre (dimensionless, > 0)."""
    tendon_angle_deltas: tuple[float, ...]
    """Per-tendon correction of its angle α (rad), added to the nominal routing."""
    segment_stiffness: tuple[float, ...]
    """Bending stiffness EI of each segment relative to the first (dimensionless)."""
    tendon_stiffness_ratio: tuple[float, ...] = ()
    """κ = k_t·r²·L_total / EI_1 per segment (its tendons' axial stiffness against backbone
    bending; shared routing uses the last); empty: 100 for every segment."""
    axial_stiffness_ratio: tuple[float, ...] = ()
    """a_i = EA_i·r²·L_total / (L_i·EI_1) per segment: its axial stiffness against backbone
    bending (dimensionless), so the tendons' tension shortens it; empty: incompressible
    segments (each keeps its length)."""
    axial_shortens_segments: bool = True
    """With ``axial_stiffness_ratio``: True, the compression shortens the segments' arcs as
    well as taking up the length of the tendons through them; False, only the take-up (the
    taut tendons through segment i give up r·δ_i of their pull together, the arcs keep
    their lengths, so the commands of a plan reproduce its shape exactly)."""
    tip_marker: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """Position of the measured point (e.g. a motion-capture marker) in the tip frame, m."""
    model_error_mean: float | None = None
    """Mean tip error (m) of this model on the calibration's validation rows (or train)."""
    model_error_p95: float | None = None
    """95th percentile tip error (m), the figure ``--model-margin auto`` adds."""
    history: History | None = None
    """The history-aware correction (``cr-nlp calibrate --history``); None: the static
    model alone (the model errors above are the static model's)."""

    @classmethod
    def nominal(cls, n_tendons: int, n_segments: int) -> Actuation:
        """Zero offsets 0, gains 1, no angle corrections, equal stiffness, κ = 100."""
        t, n = n_tendons, n_segments
        return cls((0.0,) * t, (1.0,) * t, (0.0,) * t, (1.0,) * n,
                   (NOMINAL_TENDON_STIFFNESS_RATIO,) * n)

    def to_dict(self) -> dict[str, Any]:
        """The JSON form of the ``actuation`` block (round-trips through ``parse_actuation``)."""
        out: dict[str, Any] = {
            "zero_offsets": list(self.zero_offsets),
            "gains": list(self.gains),
            "tendon_angle_deltas": list(self.tendon_angle_deltas),
            "segment_stiffness": list(self.segment_stiffness),
            "tendon_stiffness_ratio": list(self.tendon_stiffness_ratio),
            "tip_marker": list(self.tip_marker),
        }
        if self.axial_stiffness_ratio:
            out["axial_stiffness_ratio"] = list(self.axial_stiffness_ratio)
            if not self.axial_shortens_segments:
                out["axial_shortens_segments"] = False
        if self.model_error_mean is not None:
            out["model_error_mean"] = self.model_error_mean
        if self.model_error_p95 is not None:
            out["model_error_p95"] = self.model_error_p95
        if self.history is not None:
            out["history"] = self.history.to_dict()
        return out


_ACTUATION_KEYS = {"zero_offsets", "gains", "tendon_angle_deltas", "segment_stiffness",
                   "tendon_stiffness_ratio", "axial_stiffness_ratio", "axial_shortens_segments",
                   "tip_marker",
                   "model_error_mean", "model_error_p95", "history", "description"}


def parse_actuation(checker: Any, raw: Any, n_tendons: int, n_segments: int) -> Actuation:
    """The ``actuation`` block of a robot file, checked field by field (``ModelFileError``
    naming the field). ``checker`` is robot.py's field checker."""
    a = checker.obj(raw, "actuation", _ACTUATION_KEYS, set())

    def vec(key: str, size: int, default: float, positive: bool = False) -> tuple[float, ...]:
        values = checker.vector(a.get(key, [default] * size), f"actuation.{key}", size)
        if positive and any(v <= 0 for v in values):
            raise checker.fail(f"actuation.{key}", f"must all be positive, got {list(values)}")
        return values

    def per_segment_ratio(key: str, default: float) -> tuple[float, ...]:
        # One number stands for every segment.
        raw_ratio = a.get(key, default)
        if isinstance(raw_ratio, (int, float)) and not isinstance(raw_ratio, bool):
            raw_ratio = [raw_ratio] * n_segments
        values = checker.vector(raw_ratio, f"actuation.{key}", n_segments)
        if any(v <= 0 for v in values):
            raise checker.fail(f"actuation.{key}", f"must be positive, got {list(values)}")
        return values

    kappa = per_segment_ratio("tendon_stiffness_ratio", NOMINAL_TENDON_STIFFNESS_RATIO)
    axial = (per_segment_ratio("axial_stiffness_ratio", 0.0)
             if "axial_stiffness_ratio" in a else ())
    shortens = a.get("axial_shortens_segments", True)
    if not isinstance(shortens, bool):
        raise checker.fail("actuation.axial_shortens_segments",
                           f"must be true or false, got {shortens!r}")
    if not shortens and not axial:
        raise checker.fail("actuation.axial_shortens_segments",
                           "false needs actuation.axial_stiffness_ratio")
    errors = {}
    for key in ("model_error_mean", "model_error_p95"):
        errors[key] = (checker.number(a[key], f"actuation.{key}", nonnegative=True)
                       if key in a else None)
    return Actuation(
        zero_offsets=vec("zero_offsets", n_tendons, 0.0),
        gains=vec("gains", n_tendons, 1.0, positive=True),
        tendon_angle_deltas=vec("tendon_angle_deltas", n_tendons, 0.0),
        segment_stiffness=vec("segment_stiffness", n_segments, 1.0, positive=True),
        tendon_stiffness_ratio=kappa,
        axial_stiffness_ratio=axial,
        axial_shortens_segments=shortens,
        tip_marker=vec("tip_marker", 3, 0.0),  # type: ignore[arg-type]
        history=parse_history(checker, a["history"], n_tendons) if "history" in a else None,
        **errors,
    )
