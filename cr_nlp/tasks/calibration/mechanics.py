"""Calibration of the mechanics model: fit a robot's Cosserat rod to measured commands.

The model of a row: the commanded displacements d (m) pull each tendon by ``p = g (d −
d0)``; the rod takes the displacement-driven equilibrium
(``model.cosserat.solve_displacement_statics``: tensions k·max(0, p − s), s with the
take-up, the rod's own weight under the fitted gravity), and the measured point is the tip
plus a marker offset, seen from a fitted base pose. The fitted parameters
(``MechanicsCalibrationConfig.priors``): the base pose in the measurement frame, the
marker, zero offsets d0 and gains g per tendon, each segment's stiffness factor relative
to the first (the unit: with commands alone only ratios of stiffnesses, tendon stiffnesses
and weights are seen), the tendon stiffness k of each segment's tendons, each segment's
take-up compliance (m/N: the length every tendon through it loses per newton it carries),
and the gravity vector in the measurement frame (its size stands for the masses' scale:
only m·g acts).

The fit is scipy's bounded trust-region least squares over the tip errors of the training
rows plus prior rows, as the geometric calibration's (``tasks.calibrate``). Every
residual evaluation solves the rods of all rows (warm-started from the last answers); the
Jacobian comes from the implicit function theorem: one vectorised set of forward
differences per row over the equilibrium's unknowns and the row's inputs (pulls, tendon
stiffnesses, segment stiffnesses, gravity in the base frame) gives dtip/dinputs, and JAX
chains it to the fitted parameters. Units: metres, radians, newtons, N/m, m/s².
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from ...model import Robot
from ...model.actuation import Actuation, actuation_of, base_rotation
from ...model.cosserat import (
    StaticsConfig,
    case_loads,
    displacement_pass,
    displacement_solver,
    predict_marker,
)
from ...model.mechanics import Mechanics
from ...model.rotations import wxyz_from_matrix
from ...model.routing import routing_of
from ...runtime import cached, configure
from .calibrate import (
    CalibrationConfig,
    ErrorStats,
    FitResult,
    Prior,
    Repeatability,
    _Packing,
    calibrate,
    robot_length,
)
from .measurements import Measurements

STANDARD_GRAVITY = 9.81
"""m/s²: the size of the starting gravity vector."""
TAKE_UP_START = 1e-4
"""m/N: the segments' take-up compliance the fit starts from where the robot file gives
none (0.1 mm of every tendon through a segment per newton it carries)."""


def default_mechanics(robot: Robot) -> Mechanics:
    """The mechanics a robot file without a ``mechanics`` block starts from (stated
    defaults, the fit corrects the ratios that act): a solid NiTi backbone of 1 mm
    diameter (E = 54 GPa, ν = 0.3, 6450 kg/m³), a 0.5 g spacer disk every 10 mm, tendons
    whose stiffness k = 100 · E I / (r² L) (the geometric model's nominal tendon stiffness
    ratio κ = 100), tensions up to 20 N."""
    radius = 0.0005
    total = robot_length(robot)
    ei = 54e9 * np.pi / 4 * radius ** 4
    k = 100.0 * ei / (robot.tendons.radius ** 2 * total)
    disks = tuple(max(1, round(s.length_min / 0.01)) for s in robot.segments)
    return Mechanics(54e9, 0.3, radius, 0.0, 6450.0 * np.pi * radius ** 2, disks, 0.0005,
                     20.0, (), (float(k),) * robot.n_segments)


def _default_priors() -> dict[str, Prior]:
    return {
        "base_position": Prior(0.05, 5.0, relative_to="length"),
        "base_rotvec": Prior(0.1, 3.0),                               # rad
        "marker": Prior(0.03, 3.0, relative_to="length"),             # m
        "zero_offsets": Prior(0.5, 5.0, relative_to="radius"),        # m
        "gains": Prior(0.15, 3.0),
        "log_stiffness": Prior(0.7, 4.0),       # segment factors; the first is the unit
        "log_tendon_stiffness": Prior(1.5, 3.0),
        "log_take_up": Prior(2.0, 3.0),         # log m/N per segment, from TAKE_UP_START
        "gravity": Prior(STANDARD_GRAVITY, 3.0),                      # m/s², per axis
    }


@dataclass(frozen=True)
class MechanicsCalibrationConfig:
    """Settings of ``calibrate_mechanics``."""

    priors: dict[str, Prior] = field(default_factory=_default_priors)
    """Per parameter group: prior scale, bound and whether it is fitted (as
    ``tasks.calibrate.Prior``)."""
    noise: float = 1e-3
    """Expected tip error of a good fit, m: weighs the data against the priors."""
    max_evaluations: int = 40
    """Most residual evaluations of the outer least-squares solve."""
    start: str = "pcc"
    """"pcc": the base pose, marker, zero offsets and gains start from a geometric
    calibration (``tasks.calibrate``) of the same training rows; "nominal": from the
    robot file (its base pose must then be close)."""
    pcc_geometry: bool = False
    """With ``start="pcc"``: also keep the geometric calibration's segment lengths, tendon
    radius and segment angle offsets (the rod's grid and routing are not fitted here);
    False: the robot file's."""
    statics: StaticsConfig = StaticsConfig()
    """The rod's discretisation (float64)."""
    repeat_tolerance: float = 5e-5
    """As ``CalibrationConfig.repeat_tolerance``, m."""
    progress: bool = False
    """Print a line per residual evaluation (its mean tip error and the time so far)."""


@dataclass
class MechanicsCalibrationResult(FitResult):
    """The Cosserat rod's ``FitResult`` (``mechanics`` and ``actuation`` blocks)."""

    unconverged: int = 0
    """Rows (training and validation) whose equilibrium did not converge."""

    def report(self) -> dict[str, Any]:
        """The JSON report (``cr-nlp calibrate --model cosserat --report``)."""
        return {**super().report(), "model": "cosserat", "unconverged_rows": self.unconverged}


@cached(maxsize=8)
def _programs(robot: Robot, config: StaticsConfig) -> tuple[Any, Any]:
    """(solve, sensitivity), jitted and vmapped over rows, for rows' inputs q = (pull (T)
    m, log k (T), log stiffness factor (n), take-up (n) m/N, gravity in the base frame (3)
    m/s²)."""
    solver = displacement_solver(robot, config)
    one_pass = displacement_pass(robot, config)
    t, n = robot.n_tendons, robot.n_segments

    def split(q: jax.Array) -> tuple[jax.Array, ...]:
        return (q[:t], jnp.exp(q[t:2 * t]), jnp.exp(q[2 * t:2 * t + n]),
                q[2 * t + n:2 * t + 2 * n], q[2 * t + 2 * n:])

    def loads(gravity: jax.Array) -> Any:
        zero = jnp.zeros(3, gravity.dtype)
        return case_loads(zero, zero, gravity)

    def solve(q: jax.Array, y0: jax.Array, lam0: jax.Array) -> tuple[jax.Array, ...]:
        pull, k, stiffness, take_up, gravity = split(q)
        y, ok, _, _, _ = solver(pull, k, stiffness, take_up, loads(gravity), y0, lam0)
        _, tip, frame = one_pass(y, pull, k, stiffness, take_up, loads(gravity))
        return y, ok, jnp.concatenate([tip, frame.ravel()])

    def sensitivity(y: jax.Array, q: jax.Array) -> tuple[jax.Array, jax.Array]:
        """(tip (12,), dtip/dq (12, Q)) at the equilibrium y: forward differences over
        (y, q) of one pass, then the implicit function theorem (dy/dq = −A⁻¹ B)."""
        ny = y.shape[0]
        z = jnp.concatenate([y, q])
        typical = jnp.concatenate([jnp.ones_like(y), jnp.full(t, robot.tendons.radius),
                                   jnp.ones(t + n, q.dtype), jnp.full(n, TAKE_UP_START),
                                   jnp.ones(3, q.dtype)])
        h = 1e-7 * jnp.maximum(jnp.abs(z), typical)

        def evaluate(zz: jax.Array) -> tuple[jax.Array, jax.Array]:
            pull, k, stiffness, take_up, gravity = split(zz[ny:])
            rows, tip, frame = one_pass(zz[:ny], pull, k, stiffness, take_up, loads(gravity))
            return rows, jnp.concatenate([tip, frame.ravel()])

        rows, out = jax.vmap(evaluate)(jnp.concatenate([z[None], z[None] + jnp.diag(h)]))
        d_rows = ((rows[1:] - rows[0]) / h[:, None]).T     # (ny, ny + nq)
        d_out = ((out[1:] - out[0]) / h[:, None]).T        # (12, ny + nq)
        dy_dq = -jnp.linalg.solve(d_rows[:, :ny], d_rows[:, ny:])
        return out[0], d_out[:, ny:] + d_out[:, :ny] @ dy_dq

    return jax.jit(jax.vmap(solve)), jax.jit(jax.vmap(sensitivity))


class _Model:
    """The rows' model for one robot: the rows' inputs q of the parameters, the batched
    equilibrium solve and its sensitivities (``_programs``)."""

    def __init__(self, robot: Robot, config: StaticsConfig, commands: np.ndarray) -> None:
        self.robot, self.commands = robot, jnp.asarray(commands, jnp.float64)
        self.anchor = np.asarray(routing_of(robot).anchor)
        self.n, self.t = robot.n_segments, robot.n_tendons
        self.solve, self.sensitivity = _programs(robot, config)

    def inputs(self, params: dict[str, jax.Array]) -> jax.Array:
        """(N, Q) the rows' inputs q of the parameters (see ``sensitivity``)."""
        pull = params["gains"] * (self.commands - params["zero_offsets"])
        rows = pull.shape[0]
        log_k = jnp.broadcast_to(params["log_tendon_stiffness"][self.anchor], (rows, self.t))
        stiff = params["log_stiffness"] - params["log_stiffness"][0]
        take_up = jnp.exp(params["log_take_up"])
        rotation = base_rotation(params)
        gravity_base = rotation.T @ params["gravity"]
        return jnp.concatenate([pull, log_k, jnp.broadcast_to(stiff, (rows, self.n)),
                                jnp.broadcast_to(take_up, (rows, self.n)),
                                jnp.broadcast_to(gravity_base, (rows, 3))], axis=1)

    @staticmethod
    def marker(params: dict[str, jax.Array], tip: jax.Array) -> jax.Array:
        """(N, 3) measured points of tip vectors (N, 12) (position, rotation row-major)."""
        rotation = base_rotation(params)
        local = tip[:, :3] + tip[:, 3:].reshape(-1, 3, 3) @ params["marker"]
        return local @ rotation.T + params["base_position"]


_BUCKETS = (16, 64, 256, 1024)


def _bucket(count: int) -> int:
    """The padded batch size of ``count`` rows (a few compiled programs serve them all)."""
    return next((b for b in _BUCKETS if b >= count), -(-count // 1024) * 1024)


def _solve_rows(model: _Model, q: jax.Array, y0: np.ndarray, lam0: float,
                rows: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(y, converged, tip (12,)) of the ``rows`` of q, padded to a few batch sizes (with
    copies of the first) so that a few compiled programs serve every subset."""
    count = len(rows)
    size = _bucket(count)
    pick = np.concatenate([rows, np.full(size - count, rows[0])])
    y, ok, tip = model.solve(q[pick], jnp.asarray(y0[pick]),
                             jnp.full(size, lam0, jnp.float64))
    return np.array(y)[:count], np.array(ok)[:count], np.array(tip)[:count]


class _Fit:
    """The outer problem: residuals and Jacobians of the packed parameters x, with the
    rows' equilibria of the last x kept as the next warm start."""

    def __init__(self, model: _Model, pack: _Packing, measured: np.ndarray,
                 noise: float, progress: bool = False) -> None:
        self.model, self.pack, self.measured = model, pack, measured
        self.progress, self.started, self.evaluations = progress, time.perf_counter(), 0
        self.weight = 1.0 / noise
        rows = len(measured)
        self.y = np.zeros((rows, 3 + model.t))
        self.x: np.ndarray | None = None
        self.tip = np.zeros((rows, 12))
        self.ok = np.zeros(rows, bool)
        self.q = jnp.zeros((rows, 0))
        self._inputs = jax.jit(lambda x: model.inputs(pack.unpack(x)))
        self._marker = jax.jit(lambda x, tip: model.marker(pack.unpack(x), tip))

        def linear(x: jax.Array, tip: jax.Array, d_tip: jax.Array, q0: jax.Array) -> jax.Array:
            params = pack.unpack(x)
            moved = tip + jnp.einsum("nij,nj->ni", d_tip, model.inputs(params) - q0)
            return model.marker(params, moved).ravel()

        self._jacobian = jax.jit(jax.jacfwd(linear))

    def solve(self, x: np.ndarray) -> None:
        """The rows' equilibria at x (warm from the last, else from rest)."""
        if self.x is not None and np.array_equal(x, self.x):
            return
        q = self._inputs(jnp.asarray(x))
        everything = np.arange(len(self.y))
        warm = self.x is not None
        y, ok, tip = _solve_rows(self.model, q, self.y, 1.0 if warm else 0.0, everything)
        again = np.flatnonzero(~ok | ~np.isfinite(tip).all(axis=1))
        if warm and again.size:
            y[again], ok[again], tip[again] = _solve_rows(self.model, q, np.zeros_like(y),
                                                          0.0, again)
        good = ok & np.isfinite(tip).all(axis=1) & np.isfinite(y).all(axis=1)
        self.y = np.where(good[:, None], y, self.y)
        self.tip, self.ok, self.q, self.x = tip, good, q, np.array(x)

    def residuals(self, x: np.ndarray) -> np.ndarray:
        self.solve(x)
        error = np.asarray(self._marker(jnp.asarray(x), jnp.asarray(self.tip))) - self.measured
        error[~self.ok] = 0.0  # an unconverged row (counted in the result) adds nothing
        self.evaluations += 1
        if self.progress:
            print(f"  evaluation {self.evaluations}: train mean "
                  f"{1e3 * np.linalg.norm(error, axis=1).mean():.2f} mm, "
                  f"{int((~self.ok).sum())} unconverged, "
                  f"{time.perf_counter() - self.started:.0f} s", flush=True)
        return np.concatenate([(error * self.weight).ravel(), x])

    def jacobian(self, x: np.ndarray) -> np.ndarray:
        self.solve(x)
        rows = len(self.y)
        pick = np.concatenate([np.arange(rows), np.zeros(_bucket(rows) - rows, int)])
        tip, d_tip = self.model.sensitivity(jnp.asarray(self.y[pick]), self.q[pick])
        tip, d_tip = tip[:rows], d_tip[:rows]
        jac = np.array(self._jacobian(jnp.asarray(x), tip, d_tip, self.q))
        jac = jac.reshape(len(self.y), 3, -1)
        jac[~self.ok] = 0.0
        return np.concatenate([jac.reshape(-1, x.size) * self.weight, np.eye(x.size)])


def _start(robot: Robot, train: Measurements, config: MechanicsCalibrationConfig
           ) -> tuple[Robot, dict[str, np.ndarray], str]:
    """The robot the fit starts from (its mechanics block, or the defaults) and the
    starting parameters; with ``start="pcc"`` the base pose, marker, zero offsets and gains
    of a geometric calibration of the training rows."""
    mech = robot.mechanics or default_mechanics(robot)
    if not mech.tendon_stiffness:
        mech = replace(mech, tendon_stiffness=default_mechanics(robot).tendon_stiffness)
    start = replace(robot, mechanics=mech)
    source = robot
    note = "nominal"
    if config.start == "pcc":
        source = calibrate(robot, train, None, CalibrationConfig()).robot
        note = "pcc"
        if config.pcc_geometry:
            start = replace(start, segments=source.segments, tendons=source.tendons)
            note = "pcc with its geometry"
    elif config.start != "nominal":
        raise ValueError(f"start: 'pcc' or 'nominal', got {config.start!r}")
    act = actuation_of(source)
    factors = np.asarray(mech.stiffness_factors(robot.n_segments), float)
    gravity = (np.asarray(mech.calibration_gravity, float) if mech.calibration_gravity
               else np.array([0.0, 0.0, -STANDARD_GRAVITY]))
    nominal = {
        "base_position": np.asarray(source.base_position, float),
        "base_rotation": np.array(source.base_rotation),
        "base_rotvec": np.zeros(3),
        "marker": np.asarray(act.tip_marker, float),
        "zero_offsets": np.asarray(act.zero_offsets, float),
        "gains": np.asarray(act.gains, float),
        "log_stiffness": np.log(factors),
        "log_tendon_stiffness": np.log(np.asarray(mech.tendon_stiffness, float)),
        "log_take_up": np.log(np.asarray(mech.tendon_take_up or
                                         (TAKE_UP_START,) * robot.n_segments, float)),
        "gravity": gravity,
    }
    return start, nominal, note


def _robot_with(robot: Robot, params: dict[str, np.ndarray],
                error: tuple[float | None, float | None] = (None, None)) -> Robot:
    """``robot`` carrying the fitted parameters in its mechanics and actuation blocks."""
    turn = Rotation.from_rotvec(np.array(params["base_rotvec"], float)).as_matrix()
    rotation = params["base_rotation"] @ turn
    wxyz = wxyz_from_matrix(rotation)
    stiff = np.exp(params["log_stiffness"] - params["log_stiffness"][0])
    mech = replace(robot.mechanics, segment_stiffness=tuple(float(v) for v in stiff),
                   tendon_stiffness=tuple(float(v) for v in
                                          np.exp(params["log_tendon_stiffness"])),
                   calibration_gravity=tuple(float(v) for v in params["gravity"]),
                   tendon_take_up=tuple(float(v) for v in np.exp(params["log_take_up"])))
    act = replace(Actuation.nominal(robot.n_tendons, robot.n_segments),
                  zero_offsets=tuple(float(v) for v in params["zero_offsets"]),
                  gains=tuple(float(v) for v in params["gains"]),
                  tip_marker=tuple(float(v) for v in params["marker"]),  # type: ignore
                  model_error_mean=error[0], model_error_p95=error[1])
    return replace(robot, mechanics=mech, actuation=act,
                   base_position=tuple(float(v) for v in params["base_position"]),
                   base_wxyz=tuple(float(v) for v in wxyz / np.linalg.norm(wxyz)))


def mechanics_residuals(robot: Robot, data: Measurements,
                        config: StaticsConfig | None = None) -> tuple[np.ndarray, int]:
    """((N, 3) predicted minus measured points, m; rows that did not converge) of a robot
    with a mechanics block on ``data`` (``model.cosserat.predict_marker``)."""
    if data.tip is None:
        raise ValueError(f"{data.source}: no measured tip columns")
    marker, converged = predict_marker(robot, data.commands,
                                       config=config or StaticsConfig())
    return marker - data.tip, int(np.sum(~converged))


def calibrate_mechanics(robot: Robot, train: Measurements,
                        validation: Measurements | None = None,
                        config: MechanicsCalibrationConfig | None = None
                        ) -> MechanicsCalibrationResult:
    """Fit the mechanics model of ``robot`` to the ``train`` rows (commands → measured
    point) and measure it on ``validation`` (never used by the fit); see the module.

    Returns the calibrated robot (``mechanics``: segment stiffness factors, tendon
    stiffness N/m, the calibration's gravity; ``actuation``: zero offsets, gains, marker
    and the validation errors, or the training errors without validation) with its error
    statistics in m.

    Raises:
        ValueError: no measured tip columns, extendable segments, an unknown ``start``.
    """
    configure()
    config = config or MechanicsCalibrationConfig()
    if train.tip is None:
        raise ValueError(f"{train.source}: calibration needs the measured tip columns")
    if any(s.extendable for s in robot.segments):
        raise ValueError(f"{robot.name}: the mechanics model needs fixed segment lengths")
    t0 = time.perf_counter()
    start, nominal, note = _start(robot, train, config)
    with jax.enable_x64(True):
        model = _Model(start, config.statics, train.commands)
        pack = _Packing(start, nominal, config.priors)
        fit = _Fit(model, pack, np.asarray(train.tip), config.noise, config.progress)
        x0 = np.zeros(pack.size)
        nominal_error = fit.residuals(x0)[:3 * len(train)].reshape(-1, 3) * config.noise
        solution = least_squares(fit.residuals, x0, jac=fit.jacobian,
                                 bounds=(-pack.bounds, pack.bounds), method="trf",
                                 x_scale=1.0, max_nfev=config.max_evaluations, xtol=1e-8,
                                 ftol=1e-8, gtol=1e-8)
        fitted = {k: np.asarray(v) for k, v in pack.unpack(jnp.asarray(solution.x)).items()}
    length = robot_length(robot)
    calibrated = _robot_with(start, fitted)
    train_res, bad_train = mechanics_residuals(calibrated, train, config.statics)
    train_stats = ErrorStats.of(train_res, length)
    val_stats, bad_val = None, 0
    if validation is not None:
        val_res, bad_val = mechanics_residuals(calibrated, validation, config.statics)
        val_stats = ErrorStats.of(val_res, length)
    recorded = val_stats or train_stats
    calibrated = _robot_with(start, fitted, (recorded.mean, recorded.p95))
    parameters = {name: {"nominal": np.asarray(nominal[name]).tolist(),
                         "fitted": np.asarray(fitted[name]).tolist()}
                  for name, _, _ in pack.groups}
    parameters["start"] = note
    rows = train if validation is None else Measurements(
        np.vstack([train.commands, validation.commands]),
        np.vstack([train.tip, validation.tip]), train.source)
    return MechanicsCalibrationResult(
        robot=calibrated, nominal=robot, train=train_stats, validation=val_stats,
        nominal_train=ErrorStats.of(nominal_error, length), parameters=parameters,
        repeatability=Repeatability.of(rows, config.repeat_tolerance),
        seconds=time.perf_counter() - t0, evaluations=int(solution.nfev),
        status=str(solution.message), unconverged=bad_train + bad_val)
