"""Calibration: fit a robot file's parameters to measured commands and tip positions.

The problem: minimise Σ‖tip(commands; p) − tip_measured‖² over the parameters p that a
real robot gets wrong (base pose in the measurement frame, per-segment and per-tendon
angle offsets, tendon radius and segment lengths within bounds, tendon zero offsets and
gains, segment, tendon and axial stiffness ratios, the measured point's offset from the
tip),
each within bounds and pulled towards its nominal value by a prior (so parameters that the
data cannot tell apart stay physical). It is a bilevel fit: every prediction is the
equilibrium of ``model.actuation`` (the inner solve), differentiated implicitly; the
outer solve is scipy's bounded trust-region least squares with JAX Jacobians.

Before that, the base's rotation about its own axis (often unknown in a motion-capture
frame) is searched on a coarse grid, since a local fit cannot turn it by half a circle.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from scipy.optimize import least_squares
from scipy.spatial import cKDTree

from ...model import Robot
from ...model.actuation import (
    NOMINAL_AXIAL_STIFFNESS_RATIO,
    actuation_of,
    measured_point,
    params_of,
    predict_tip,
    robot_with_params,
    zero_sensitivity,
)
from ...runtime import configure
from .measurements import Measurements


@dataclass(frozen=True)
class Prior:
    """How one parameter group may move: ``scale`` is the prior's standard deviation (the
    parameter's own units, times the robot's length, its tendon radius or the nominal value
    when ``relative_to`` is "length", "radius" or "value"), ``bound`` the largest change
    allowed, in units of ``scale``; ``fit=False`` keeps the group at its nominal value."""

    scale: float
    bound: float = 5.0
    fit: bool = True
    relative_to: str = ""


def _default_priors() -> dict[str, Prior]:
    return {
        # the measurement frame is unknown: a quarter of the robot's length, 2.5 lengths
        "base_position": Prior(0.25, 10.0, relative_to="length"),
        "base_rotvec": Prior(0.2, 3.0),                              # rad, after the yaw grid
        "segment_offsets": Prior(0.2, 3.0),                          # rad
        "angle_deltas": Prior(0.05, 4.0),                            # rad, per tendon
        "radius": Prior(0.1, 2.0, relative_to="value"),              # ±20 %
        "lengths": Prior(0.05, 2.0, relative_to="value"),            # ±10 %
        "zero_offsets": Prior(0.5, 5.0, relative_to="radius"),       # m, θ-equivalent 0.5
        "gains": Prior(0.15, 3.0),                                   # 1
        "log_stiffness": Prior(0.7, 3.0),          # log EI ratios (the first is the unit)
        "log_kappa": Prior(1.5, 3.0),              # log of the tendon stiffness ratio
        "log_axial": Prior(1.5, 3.0),              # log of the axial stiffness ratio
        "marker": Prior(0.03, 3.0, relative_to="length"),            # m
    }


@dataclass(frozen=True)
class CalibrationConfig:
    """Settings of ``calibrate``."""

    priors: dict[str, Prior] = field(default_factory=_default_priors)
    """Per parameter group: prior scale, bound and whether it is fitted."""
    noise: float = 1e-3
    """Expected tip error of a good fit, m: weighs the data against the priors."""
    repeat_tolerance: float = 5e-5
    """Rows whose commands agree within this on every tendon count as the same command
    for ``Repeatability``, m."""
    yaw_grid: int = 12
    """Base rotations about the base axis tried before the fit (0: no search)."""
    max_evaluations: int = 60
    """Most Jacobian evaluations of the outer least-squares solve."""
    inner_iterations: int = 12
    """Newton steps of the equilibrium solve."""
    robust_loss: str = "linear"
    """scipy ``loss`` of the outer fit ("linear", "soft_l1", "huber", …)."""
    axial_compression: bool = False
    """Also fit the segments' axial compression under tendon load (``model.actuation``),
    from the robot file's ``axial_stiffness_ratio`` or, without one, from
    ``NOMINAL_AXIAL_STIFFNESS_RATIO``. Off by default: plans keep fixed segment lengths, so
    with shortening segments the commands of a plan reproduce its tip only to about 1 mm
    (FTDCR v6), about what the fit gains there (validation 10.2 → 9.5 mm mean; the
    take-up alone, ``axial_shortens_segments`` False, 9.6 mm and exact plans). False:
    incompressible segments unless the file already gives them an axial stiffness."""
    axial_shortens_segments: bool = True
    """With ``axial_compression``: True, the compression also shortens the segments' arcs;
    False, it only takes up the tendons' length (``Actuation.axial_shortens_segments``),
    so plans' commands reproduce their shapes exactly. On the FTDCR v6 training folds
    (docs/design.md §1b) the take-up alone fits as well (8.15 mm against 8.34)."""


@dataclass
class ErrorStats:
    """Tip errors of a model on some rows, m and % of the robot's length."""

    rows: int
    mean: float
    median: float
    p95: float
    max: float
    robot_length: float
    rmse: float
    """Root mean square of the tip errors, m."""
    rmse_aligned: float
    """The same after removing the rows' mean error vector (the metric that OpenCR-MuJoCo's
    system identification reports), m."""

    @classmethod
    def of(cls, residuals: np.ndarray, robot_length: float) -> ErrorStats:
        """From (N, 3) predicted − measured tip vectors, m."""
        r = np.asarray(residuals, float)
        e = np.linalg.norm(r, axis=1)
        aligned = r - r.mean(axis=0)
        return cls(len(e), float(e.mean()), float(np.median(e)),
                   float(np.percentile(e, 95)), float(e.max()), robot_length,
                   float(np.sqrt(np.mean(e * e))),
                   float(np.sqrt(np.mean(np.sum(aligned * aligned, axis=1)))))

    def to_dict(self) -> dict[str, Any]:
        keys = ("mean", "median", "p95", "max", "rmse", "rmse_aligned")
        mm = {k: 1e3 * getattr(self, k) for k in keys}
        pct = {k: 100.0 * getattr(self, k) / self.robot_length for k in keys}
        return {"rows": self.rows, "mm": mm, "percent_of_length": pct,
                "robot_length_m": self.robot_length}


@dataclass
class Repeatability:
    """Pairs of rows whose commands agree within ``tolerance`` on every tendon, and how far
    apart their measured tips are. A prediction from the commands alone gives both rows of
    such a pair about the same tip, so on one of them it errs by at least half their gap
    (less the tip motion that ``tolerance`` allows, ``tolerance`` times the zero
    sensitivity): hysteresis, drift and measurement noise set this floor under any model
    without memory, whatever its parameters."""

    tolerance: float
    """Largest command difference per tendon within a pair, m."""
    gaps: np.ndarray
    """(pairs,) distances between the pairs' measured tips, m."""
    rows: int
    """Rows that belong to at least one pair."""

    @classmethod
    def of(cls, data: Measurements, tolerance: float) -> Repeatability:
        if data.tip is None:
            raise ValueError(f"{data.source}: repeatability needs the measured tip columns")
        pairs = cKDTree(data.commands).query_pairs(tolerance, p=np.inf, output_type="ndarray")
        gaps = np.linalg.norm(data.tip[pairs[:, 0]] - data.tip[pairs[:, 1]], axis=1)
        return cls(float(tolerance), gaps, int(np.unique(pairs).size))

    def to_dict(self) -> dict[str, Any]:
        gap = None
        if self.gaps.size:
            mm = 1e3 * self.gaps
            gap = {"mean": float(mm.mean()), "median": float(np.median(mm)),
                   "p95": float(np.percentile(mm, 95)), "max": float(mm.max())}
        return {"tolerance_mm": 1e3 * self.tolerance, "pairs": int(self.gaps.size),
                "rows": self.rows, "tip_gap_mm": gap}


@dataclass
class FitResult:
    """What every calibration returns: the calibrated robot with its errors on the training
    (and validation) rows, m.

    Outside ``tasks._result.ResultIO`` on purpose: a fit gives one robot file and error
    statistics, not an answer per input with a verdict; it is saved as that robot file."""

    robot: Robot
    """The calibrated robot (geometry, base pose, ``actuation`` and, for the rod,
    ``mechanics`` blocks)."""
    nominal: Robot
    """The robot the fit started from."""
    train: ErrorStats
    validation: ErrorStats | None
    nominal_train: ErrorStats
    """Errors of the starting robot (after the yaw search) on the training rows."""
    parameters: dict[str, Any]
    """Fitted values by group (JSON-ready), with their nominal values."""
    repeatability: Repeatability
    """Rows of the training and validation data with the same commands and their tips'
    gaps: the floor under any model of the commands alone."""
    seconds: float
    evaluations: int
    status: str

    def report(self) -> dict[str, Any]:
        """The JSON report (``cr-nlp calibrate --report``)."""
        return {
            "robot": self.robot.name,
            "train": self.train.to_dict(),
            "validation": self.validation.to_dict() if self.validation else None,
            "nominal_train": self.nominal_train.to_dict(),
            "parameters": self.parameters,
            "repeatability": self.repeatability.to_dict(),
            "seconds": self.seconds,
            "evaluations": self.evaluations,
            "status": self.status,
        }


@dataclass
class CalibrationResult(FitResult):
    """The geometric (PCC) calibration's ``FitResult``."""

    zero_sensitivity: np.ndarray = field(default_factory=lambda: np.zeros(0))
    """(training rows,) the calibrated tip's motion per unit tendon zero error, m/m
    (``model.actuation.zero_sensitivity``)."""

    def report(self) -> dict[str, Any]:
        """The JSON report (``cr-nlp calibrate --report``)."""
        return {**super().report(), "zero_sensitivity_mm_per_mm": {
            "median": float(np.median(self.zero_sensitivity)),
            "p90": float(np.percentile(self.zero_sensitivity, 90))}}


def tip_residuals(robot: Robot, data: Measurements) -> np.ndarray:
    """(N, 3) predicted minus measured tip, m."""
    if data.tip is None:
        raise ValueError(f"{data.source}: no measured tip columns")
    return predict_tip(robot, data.commands) - data.tip


def tip_errors(robot: Robot, data: Measurements) -> np.ndarray:
    """(N,) distance between predicted and measured tip, m."""
    return np.linalg.norm(tip_residuals(robot, data), axis=1)


def robot_length(robot: Robot) -> float:
    """The backbone length used for "% of the robot's length", m."""
    return float(sum(s.length_min for s in robot.segments))


class _Packing:
    """The fitted parameters as one vector x, x = (p − p_nominal) / prior scale."""

    def __init__(self, robot: Robot, nominal: dict[str, np.ndarray],
                 priors: dict[str, Prior]) -> None:
        self.nominal = nominal
        self.groups: list[tuple[str, slice, np.ndarray]] = []
        self._masks: dict[str, np.ndarray] = {}
        start = 0
        for name, prior in priors.items():
            if not prior.fit or name not in nominal:
                continue
            value = nominal[name]
            mask = np.ones(value.size, bool)
            if name == "log_stiffness":
                mask[0] = False  # only ratios matter: the first segment is the unit
            unit = {"": 1.0, "length": robot_length(robot),
                    "radius": robot.tendons.radius}.get(prior.relative_to)
            if prior.relative_to == "value":
                scale = prior.scale * np.abs(value.ravel()[mask])
            else:
                scale = np.full(int(mask.sum()), prior.scale * unit)
            size = int(mask.sum())
            if size == 0:
                continue
            self.groups.append((name, slice(start, start + size), scale))
            start += size
            self._masks[name] = mask
        self.size = start
        self.bounds = np.concatenate([np.full(sl.stop - sl.start, priors[name].bound)
                                      for name, sl, _ in self.groups])

    def unpack(self, x: jax.Array) -> dict[str, jax.Array]:
        params = {k: jnp.asarray(v) for k, v in self.nominal.items()}
        for name, sl, scale in self.groups:
            mask = self._masks[name]
            delta = jnp.zeros(self.nominal[name].size, x.dtype)
            delta = delta.at[np.flatnonzero(mask)].set(x[sl] * scale)
            params[name] = params[name] + delta.reshape(self.nominal[name].shape)
        return params


def calibrate(robot: Robot, train: Measurements, validation: Measurements | None = None,
              config: CalibrationConfig | None = None) -> CalibrationResult:
    """Fit ``robot``'s parameters to the ``train`` rows (commands → measured tip), and
    measure the calibrated model on ``validation`` (never used by the fit).

    Returns the calibrated robot (its ``actuation`` block records the validation errors,
    or the training errors without validation) and the error statistics in m.
    """
    configure()
    config = config or CalibrationConfig()
    if train.tip is None:
        raise ValueError(f"{train.source}: calibration needs the measured tip columns")
    t0 = time.perf_counter()
    nominal_robot = robot
    act = actuation_of(robot)
    if config.axial_compression and act.axial_shortens_segments != config.axial_shortens_segments:
        robot = replace(robot, actuation=replace(
            act, axial_shortens_segments=config.axial_shortens_segments))
    with jax.enable_x64(True):
        nominal = {k: np.asarray(v, np.float64) for k, v in params_of(robot).items()}
        nominal["base_rotvec"] = np.zeros(3)
        if config.axial_compression and "log_axial" not in nominal:
            nominal["log_axial"] = np.full(robot.n_segments,
                                           np.log(NOMINAL_AXIAL_STIFFNESS_RATIO))
        commands = jnp.asarray(train.commands, jnp.float64)
        measured = jnp.asarray(train.tip, jnp.float64)
        iterations = config.inner_iterations

        @jax.jit
        def tips(params: dict[str, Any]) -> jax.Array:
            return measured_point(robot, params, commands, iterations)

        if config.yaw_grid > 0:
            nominal["base_rotation"], shift = _best_yaw(nominal, tips, measured,
                                                        config.yaw_grid)
            nominal["base_position"] = nominal["base_position"] - shift
        pack = _Packing(robot, nominal, config.priors)
        weight = 1.0 / config.noise

        @jax.jit
        def residuals(x: jax.Array) -> jax.Array:
            return jnp.concatenate([((tips(pack.unpack(x)) - measured) * weight).ravel(), x])

        jacobian = jax.jit(jax.jacfwd(residuals))
        x0 = np.zeros(pack.size)
        nominal_residuals = np.asarray(tips(pack.unpack(jnp.asarray(x0)))) - train.tip
        evaluations = {"jac": 0}

        def jac(x: np.ndarray) -> np.ndarray:
            evaluations["jac"] += 1
            return np.asarray(jacobian(jnp.asarray(x)))

        solution = least_squares(
            lambda x: np.asarray(residuals(jnp.asarray(x))), x0, jac=jac,
            bounds=(-pack.bounds, pack.bounds), method="trf", loss=config.robust_loss,
            f_scale=3.0, x_scale=1.0, max_nfev=config.max_evaluations, xtol=1e-10,
            ftol=1e-10, gtol=1e-10)
        fitted = {k: np.asarray(v) for k, v in pack.unpack(jnp.asarray(solution.x)).items()}
        fitted["base_rotation"] = np.asarray(_rotation_of(fitted))
        del fitted["base_rotvec"]
    length = robot_length(robot)
    calibrated = robot_with_params(robot, fitted)
    train_stats = ErrorStats.of(tip_residuals(calibrated, train), length)
    val_stats = (ErrorStats.of(tip_residuals(calibrated, validation), length)
                 if validation is not None else None)
    recorded = val_stats or train_stats
    calibrated = robot_with_params(robot, fitted, (recorded.mean, recorded.p95))
    parameters = {name: {"nominal": np.asarray(nominal[name]).tolist(),
                         "fitted": np.asarray(fitted[name]).tolist()}
                  for name, _, _ in pack.groups if name in fitted}
    rows = train if validation is None else Measurements(   # both files' tips were read above
        np.vstack([train.commands, validation.commands]),
        np.vstack([train.tip, validation.tip]), train.source)
    return CalibrationResult(
        robot=calibrated, nominal=nominal_robot, train=train_stats, validation=val_stats,
        nominal_train=ErrorStats.of(nominal_residuals, length), parameters=parameters,
        repeatability=Repeatability.of(rows, config.repeat_tolerance),
        zero_sensitivity=zero_sensitivity(calibrated, train.commands),
        seconds=time.perf_counter() - t0, evaluations=int(solution.nfev),
        status=str(solution.message))


def _rotation_of(params: dict[str, Any]) -> jax.Array:
    from ...model.actuation import base_rotation

    return base_rotation({k: jnp.asarray(v) for k, v in params.items()})


def _best_yaw(nominal: dict[str, np.ndarray], tips: Any, measured: jax.Array,
              grid: int) -> tuple[np.ndarray, np.ndarray]:
    """The base rotation, turned about the base's own z axis by the grid angle whose
    prediction has the least squared tip error after centring (the base position is not
    fitted yet, so the mean offset is taken out), and that mean offset (m)."""
    best, best_cost, best_shift = nominal["base_rotation"], np.inf, np.zeros(3)
    for k in range(grid):
        angle = 2.0 * np.pi * k / grid
        c, s = np.cos(angle), np.sin(angle)
        rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        trial = dict(nominal, base_rotation=nominal["base_rotation"] @ rz)
        pred = np.asarray(tips({k2: jnp.asarray(v) for k2, v in trial.items()}))
        diff = pred - np.asarray(measured)
        cost = float(np.sum((diff - diff.mean(axis=0)) ** 2))
        if cost < best_cost:
            best, best_cost, best_shift = trial["base_rotation"], cost, diff.mean(axis=0)
    return best, best_shift
