"""Calibration of the history-aware actuation model (issue 42; ``model.history``).

The static model (``tasks.calibration.calibrate``) is fitted first and kept; the history fit then
finds the play widths r_k (shared by the tendons) and the per-tendon weights w_jk that
make the static model of the effective commands match the measured tips. The static
model is linearised in the commands around the current effective commands (the
corrections are a fraction of a millimetre of command) and re-linearised a few times; the
inner problem is scipy's bounded least squares with JAX Jacobians through the operators'
``lax.scan``. Weights are pulled towards zero by a prior, so a recording without
hysteresis leaves them there.

The model's size (how many operators, or none) is chosen by folds of the training rows:
each family of patterns is left out in turn, the history fitted on the others (the play
states still run over every row in time order: commands are inputs) and the mean tip
error measured on the family left out. The validation rows are never read here.
"""

from __future__ import annotations

import re
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from functools import partial
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from scipy.optimize import least_squares

from ...model import Robot
from ...model.actuation import actuation_of, measured_point, params_of
from ...model.history import History, effective_commands_jax, predict_tip_series
from ...runtime import configure
from .calibrate import ErrorStats, robot_length
from .measurements import Measurements

VARIANTS: dict[str, int] = {"play1": 1, "play2": 2, "play3": 3}
"""Named history models (``--history NAME``) and their number of play operators."""


@dataclass(frozen=True)
class HistoryConfig:
    """Settings of ``fit_history``."""

    operators: int = 2
    """K, the number of play operators (widths) per tendon."""
    width_bounds: tuple[float, float] = (5e-5, 8e-3)
    """Smallest and largest play width, m."""
    initial_widths: tuple[float, ...] = ()
    """Starting widths, m (K of them); empty: spread geometrically over 0.2 … 2 mm."""
    weight_scale: float = 0.3
    """Prior standard deviation of each weight about zero (dimensionless)."""
    noise: float = 1e-3
    """Expected tip error of a good fit, m: weighs the data against the prior."""
    relinearisations: int = 3
    """Times the static model is linearised again around the new effective commands."""
    max_evaluations: int = 30
    """Most Jacobian evaluations of each inner least-squares solve."""


def _start_widths(config: HistoryConfig) -> np.ndarray:
    if config.initial_widths:
        return np.asarray(config.initial_widths, float)
    k = config.operators
    return np.geomspace(2e-4, 2e-3, k) if k > 1 else np.array([6e-4])


@partial(jax.jit, static_argnums=0)
def _linearised(robot: Robot, params: dict[str, jax.Array],
                commands: jax.Array) -> tuple[jax.Array, jax.Array]:
    def tip(row: jax.Array) -> jax.Array:
        return measured_point(robot, params, row)

    return jax.vmap(tip)(commands), jax.vmap(jax.jacfwd(tip))(commands)


def _static_jacobian(robot: Robot, commands: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The static model's tips (T, 3) m and their Jacobian (T, 3, n) m/m at commands."""
    params = {k: jnp.asarray(v, jnp.float64) for k, v in params_of(robot).items()}
    tips, jac = _linearised(with_history(robot, None), params,
                            jnp.asarray(commands, jnp.float64))
    return np.asarray(tips, np.float64), np.asarray(jac, np.float64)


@partial(jax.jit, static_argnums=(0,))
def _residuals(k: int, x: jax.Array, fit: dict[str, jax.Array]) -> jax.Array:
    """The linearised problem's residuals: (predicted − measured tip) / noise on the fitted
    rows (zero elsewhere), then the weights / their prior scale."""
    commands = fit["commands"]
    n = commands.shape[1]
    shift = effective_commands_jax(commands, jnp.exp(x[:k]), x[k:].reshape(n, k)) \
        - fit["around"]
    predicted = fit["tips"] + jnp.einsum("tij,tj->ti", fit["jac"], shift)
    data = (predicted - fit["measured"]) * fit["row_weight"][:, None]
    return jnp.concatenate([data.ravel(), x[k:] / fit["weight_scale"]])


_residual_jacobian = jax.jit(jax.jacfwd(_residuals, argnums=1), static_argnums=(0,))


def _solve(k: int, x0: np.ndarray, fit: dict[str, jax.Array],
           bounds: tuple[np.ndarray, np.ndarray], evaluations: int) -> np.ndarray:
    """One bounded least-squares solve of the linearised problem from x0."""
    solution = least_squares(
        lambda x: np.asarray(_residuals(k, jnp.asarray(x), fit)), x0,
        jac=lambda x: np.asarray(_residual_jacobian(k, jnp.asarray(x), fit)),
        bounds=bounds, method="trf", max_nfev=evaluations, xtol=1e-10, ftol=1e-10,
        gtol=1e-10)
    return np.clip(np.asarray(solution.x, float), *bounds)


def fit_history(robot: Robot, data: Measurements, config: HistoryConfig | None = None,
                rows: np.ndarray | None = None) -> History:
    """The play widths and weights that best explain ``data``'s measured tips (rows in time
    order) through ``robot``'s static model, fitted on ``rows`` (a boolean mask; default
    all). Returns the ``History`` block (widths m, weights dimensionless), without errors."""
    configure()
    config = config or HistoryConfig()
    if data.tip is None:
        raise ValueError(f"{data.source}: the history fit needs the measured tip columns")
    k, n = config.operators, robot.n_tendons
    mask = np.ones(len(data), bool) if rows is None else np.asarray(rows, bool)
    low, high = np.log(config.width_bounds[0]), np.log(config.width_bounds[1])
    cap = 0.98 / k
    x = np.concatenate([np.clip(np.log(_start_widths(config)), low, high),
                        np.full(n * k, min(0.05, 0.5 * cap))])
    lower = np.concatenate([np.full(k, low), np.zeros(n * k)])
    upper = np.concatenate([np.full(k, high), np.full(n * k, cap)])
    with jax.enable_x64(True):
        fit = {"commands": jnp.asarray(data.commands, jnp.float64),
               "measured": jnp.asarray(data.tip, jnp.float64),
               "row_weight": jnp.asarray(mask / config.noise, jnp.float64),
               "weight_scale": jnp.asarray(config.weight_scale, jnp.float64)}
        for _ in range(config.relinearisations):
            widths, weights = jnp.exp(jnp.asarray(x[:k])), jnp.asarray(x[k:]).reshape(n, k)
            around = np.asarray(effective_commands_jax(fit["commands"], widths, weights))
            tips, jac = _static_jacobian(robot, around)
            fit |= {"around": jnp.asarray(around), "tips": jnp.asarray(tips),
                    "jac": jnp.asarray(jac)}
            x = _solve(k, x, dict(fit), (lower, upper), config.max_evaluations)
    widths, weights = np.exp(x[:k]), x[k:].reshape(n, k)
    order = np.argsort(widths)
    widths, weights = widths[order], weights[:, order]
    widths = np.maximum.accumulate(widths * (1.0 + 1e-9 * np.arange(k)))  # strictly rising
    return History(tuple(float(v) for v in widths),
                   tuple(tuple(float(v) for v in row) for row in weights))


def with_history(robot: Robot, history: History | None) -> Robot:
    """A copy of ``robot`` whose ``actuation`` block carries ``history`` (None: removed)."""
    return replace(robot, actuation=replace(actuation_of(robot), history=history))


def families_of(labels: np.ndarray, pattern: str | None = None,
                max_folds: int = 10, folds: int = 5) -> np.ndarray:
    """(N,) the fold family of each row: the first group of regular expression ``pattern``
    found in its label (the label itself without one). More than ``max_folds`` families:
    consecutive families (in order of first appearance) are merged into ``folds`` groups
    of about equal rows. A label that the pattern does not match raises ValueError."""
    labels = np.asarray(labels, dtype=str)
    if pattern:
        compiled = re.compile(pattern)
        found = []
        for label in labels:
            match = compiled.search(label)
            if match is None:
                raise ValueError(f"fold pattern {pattern!r} matches no part of the label "
                                 f"{label!r}")
            found.append(match.group(1) if compiled.groups else match.group(0))
        labels = np.array(found)
    names = list(dict.fromkeys(labels.tolist()))
    if len(names) <= max_folds:
        return labels
    rank = {name: i for i, name in enumerate(names)}
    order = np.array([rank[v] for v in labels])
    counts = np.bincount(order, minlength=len(names))
    edges = np.cumsum(counts) / len(labels)
    group = np.minimum((edges - counts / (2 * len(labels))) * folds, folds - 1).astype(int)
    return np.array([f"block{group[i] + 1}" for i in order])


def time_blocks(rows: int, folds: int = 5) -> np.ndarray:
    """(rows,) ``folds`` contiguous blocks of rows in time order, as fold families (for a
    recording without pattern labels)."""
    return np.array([f"block{1 + (i * folds) // rows}" for i in range(rows)])


@dataclass
class FoldReport:
    """Held-out tip errors of each candidate model on each left-out family."""

    families: list[str]
    errors: dict[str, list[float]] = field(default_factory=dict)
    """Model name ("none" = static) → mean tip error on each family left out, m."""
    chosen: str = "none"
    seconds: float = 0.0

    def score(self, name: str) -> float:
        """The model's fold score: the mean over the families of the held-out mean, m."""
        return float(np.mean(self.errors[name]))

    def to_dict(self) -> dict[str, Any]:
        return {"protocol": "leave one family of the training rows out; fit the history on "
                            "the rest; mean tip error on the family left out",
                "families": self.families, "chosen": self.chosen, "seconds": self.seconds,
                "held_out_mm": {name: {"per_family": [1e3 * e for e in errs],
                                       "score": 1e3 * self.score(name)}
                                for name, errs in self.errors.items()}}


def fold_errors(static: Robot | Callable[[np.ndarray], Robot], data: Measurements,
                families: np.ndarray, names: tuple[str, ...] = ("none", *VARIANTS),
                config: HistoryConfig | None = None) -> FoldReport:
    """Leave-one-family-out errors of the named models ("none" = the static model alone)
    on ``data``'s rows. ``static`` is the static robot, or a function of the fitted rows'
    mask that returns the static robot fitted on them (the honest protocol, one static
    calibration per fold). The model with the lowest score wins, "none" unless a history
    model beats it by 1 %."""
    t0 = time.perf_counter()
    config = config or HistoryConfig()
    families = np.asarray(families, dtype=str)
    report = FoldReport(list(dict.fromkeys(families.tolist())))
    report.errors = {name: [] for name in names}
    for family in report.families:
        held_out = families == family
        robot = static(~held_out) if callable(static) else static
        for name in names:
            model = None if name == "none" else fit_history(
                robot, data, replace(config, operators=VARIANTS[name]), ~held_out)
            tips = predict_tip_series(with_history(robot, model), data.commands)
            error = np.linalg.norm(tips[held_out] - data.tip[held_out], axis=1).mean()
            report.errors[name].append(float(error))
    best = min(names, key=report.score)
    if "none" in names and report.score(best) > 0.99 * report.score("none"):
        best = "none"
    report.chosen, report.seconds = best, time.perf_counter() - t0
    return report


@dataclass
class HistoryCalibration:
    """The history-aware model fitted on the training rows, with its errors."""

    robot: Robot
    """The static robot with the chosen ``actuation.history`` (none: unchanged)."""
    history: History | None
    folds: FoldReport | None
    train: ErrorStats
    validation: ErrorStats | None
    seconds: float

    def report(self) -> dict[str, Any]:
        """The ``history`` section of ``cr-nlp calibrate --report``."""
        return {"model": None if self.history is None else self.history.to_dict(),
                "folds": None if self.folds is None else self.folds.to_dict(),
                "train": self.train.to_dict(),
                "validation": self.validation.to_dict() if self.validation else None,
                "seconds": self.seconds}


def calibrate_history(static: Robot, train: Measurements,
                      validation: Measurements | None = None, name: str = "auto",
                      families: np.ndarray | None = None,
                      config: HistoryConfig | None = None) -> HistoryCalibration:
    """Fit the history model ``name`` ("auto": chosen by ``fold_errors`` on ``families``
    of the training rows; "none"; or a ``VARIANTS`` name) on the ``train`` rows (in time
    order) through the calibrated ``static`` robot, and measure it on ``validation`` (its
    own series from rest; never used by the fit). Errors in m."""
    t0 = time.perf_counter()
    config = config or HistoryConfig()
    folds = None
    if name == "auto":
        if families is None:
            families = time_blocks(len(train))
        folds = fold_errors(static, train, families, config=config)
        name = folds.chosen
    elif name != "none" and name not in VARIANTS:
        raise ValueError(f"history model must be auto, none or one of {sorted(VARIANTS)}, "
                         f"got {name!r}")
    model = None
    if name != "none":
        model = fit_history(static, train, replace(config, operators=VARIANTS[name]))
    robot = with_history(static, model)
    length = robot_length(robot)
    train_stats = ErrorStats.of(predict_tip_series(robot, train.commands) - train.tip, length)
    val_stats = None
    if validation is not None:
        val_stats = ErrorStats.of(
            predict_tip_series(robot, validation.commands) - validation.tip, length)
    if model is not None:
        recorded = val_stats or train_stats
        model = replace(model, model_error_mean=recorded.mean, model_error_p95=recorded.p95,
                        fold_score=folds.score(name) if folds else None)
        robot = with_history(static, model)
    return HistoryCalibration(robot, model, folds, train_stats, val_stats,
                              time.perf_counter() - t0)


@dataclass
class Compensation:
    """Motor commands for a planned shape sequence, without and with the history
    compensation, and the tip error of each replayed through the history-aware model."""

    planned_tip: np.ndarray
    """(T, 3) the plan's measured point (tip marker) in the measurement frame, m."""
    uncompensated: np.ndarray
    """(T, n_tendons) the static model's commands for the plan, m (positive = pulled)."""
    compensated: np.ndarray
    """(T, n_tendons) the commands whose effective commands are the uncompensated ones, m."""
    error_uncompensated: np.ndarray
    """(T,) tip error of the uncompensated series through the history-aware model, m."""
    error_compensated: np.ndarray
    """(T,) tip error of the compensated series through the history-aware model, m."""


def compensate_plan(robot: Robot, q: Any) -> Compensation:
    """The command series that makes ``robot``'s history-aware model (its
    ``actuation.history``) take the planned configurations q (T, 3n) (rad, rad, m) in
    order, beside the static model's commands for them (``commands_for_configuration``),
    with the predicted tip error of both (m). Raises ValueError without a history block or
    with rows of q that are not finite (an IK target without an answer)."""
    from ...model.actuation import commands_for_configuration, predict_tip
    from ...model.history import compensate_commands, history_of

    history = history_of(robot)
    if history is None:
        raise ValueError(f"{robot.name} has no actuation.history block: run cr-nlp "
                         f"calibrate --history first")
    q = np.atleast_2d(np.asarray(q, np.float64))
    if not np.all(np.isfinite(q)):
        raise ValueError("the plan has rows without a configuration (not finite)")
    static = with_history(robot, None)
    uncompensated = commands_for_configuration(static, q)
    planned = predict_tip(static, uncompensated)
    compensated = compensate_commands(history, uncompensated)
    errors = [np.linalg.norm(predict_tip_series(robot, cmd) - planned, axis=1)
              for cmd in (uncompensated, compensated)]
    return Compensation(planned, uncompensated, compensated, *errors)
