"""Classic IK baselines for the benchmark: numpy in, numpy out, obstacles ignored.

- ``damped_newton_ik``: damped least squares (Levenberg's fixed damping, no trust
  region) on the model's pose-error residual with ``jax.jacfwd`` Jacobians, batched over
  every (target, start) pair, from ``starts`` random configurations per target; the
  start with the smallest final pose error wins.
- ``scipy_ik``: a derivative-free ``scipy.optimize.minimize`` method (Nelder–Mead by
  default; Powell also works) on the squared pose error of one target at a time,
  from one random start, bounded where the method allows.

Both work on the same variables as cr_nlp where that is the fair choice: the damped
Newton iteration moves the singularity-free bending vector ``z = [ux, uy, L, …]``
(rad, rad, m) and projects onto the limits after every step (the same projection as
cr_nlp's LM), so it is not handicapped by the azimuth singularity at θ = 0; the scipy
method moves θ, φ, L directly (bounds θ ∈ [0, θmax], L in its range, φ free and
periodic). Fixed lengths are not variables in either. Neither sees obstacles: in a
scene their answers are judged by python-fcl like everyone else's, nothing more.
Every answer is clipped into the limits before it is returned.
"""

from __future__ import annotations

import functools
import math
import time
from dataclasses import dataclass
from functools import partial
from typing import Any, NamedTuple

import casadi as ca
import jax
import jax.numpy as jnp
import numpy as np
import scipy.optimize

from ..model import CasadiModel, Robot, load_robot, q_to_z, z_to_q
from ..model._ops import JAX
from ..model.kinematics import model_pose_error, model_segment_frames
from ..model.limits import clip_to_limits, project_z
from ..model.rotations import matrix_from_wxyz
from ..runtime import split_over_devices
from ..stages.refine._lm import solve_spd


class BaselineSolve(NamedTuple):
    """What a baseline returns."""

    q: np.ndarray
    """(T, 3n) θ, φ, L per target (rad, rad, m), inside the limits."""
    seconds: float
    """Wall-clock seconds of the solve (device work finished before the clock stops)."""


def random_configurations(robot: Robot, count: int, seed: int) -> np.ndarray:
    """(count, 3n) configurations drawn uniformly inside the limits: θ, φ and L of every
    segment independently (rad, rad, m)."""
    lo, hi = robot.q_bounds()
    return np.random.default_rng(seed).uniform(lo, hi, (count, robot.dof))


# ================================================================ damped Newton–Raphson


@dataclass(frozen=True)
class DampedNewtonConfig:
    """Settings of the damped least-squares (damped Newton–Raphson) baseline.

    The defaults were chosen on 500 tdcr3 targets apart from the benchmark's (seed 123)
    over λ ∈ {0.01, 0.05, 0.2}, iterations ∈ {50, 100, 200}, starts ∈ {4, 8, 16}:
    λ = 0.05 with 50 iterations and 16 starts reached 99.8 % in about 1.7 s, as well as
    any setting that took longer.
    """

    damping: float = 0.05
    """λ of the step Δz = −Jᵀ(JJᵀ + λ²I)⁻¹r, fixed for every iteration (mixed m/rad)."""
    iterations: int = 50
    """Iterations per start, always all of them (no early stop)."""
    starts: int = 16
    """Random starts per target (uniform inside the limits); the best answer wins."""
    dtype: str = "float32"
    """JAX dtype of the iteration ("float64" needs jax_enable_x64), as cr_nlp's default."""


def _pose_residual(robot: Robot, z: jax.Array, target_position: jax.Array,
                   target_rotation: jax.Array) -> jax.Array:
    """log(T_tip(z)⁻¹·T_target) (6,): translation part (m), rotation part (rad)."""
    tip = model_segment_frames(JAX, robot, [z[i] for i in range(robot.dof)])[-1]
    goal = (tuple(target_rotation[i] for i in range(9)),
            tuple(target_position[i] for i in range(3)))
    return jnp.stack(model_pose_error(JAX, tip, goal))


def _damped_newton(robot: Robot, iterations: int, z0: jax.Array, target_position: jax.Array,
                   target_rotation: jax.Array, free: jax.Array,
                   damping: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Fixed-damping least squares on a batch (B, n); returns the best iterate z (B, n) of
    each problem and its squared pose error (B,)."""
    residual = partial(_pose_residual, robot)
    jac = jax.vmap(jax.jacfwd(residual))
    res = jax.vmap(residual)
    eye = jnp.eye(6, dtype=z0.dtype)

    def step(_: int, state: tuple) -> tuple:
        z, best_z, best_cost = state
        r = res(z, target_position, target_rotation)
        j = jac(z, target_position, target_rotation) * free
        cost = jnp.sum(r * r, axis=-1)
        better = cost < best_cost
        best_z = jnp.where(better[:, None], z, best_z)
        best_cost = jnp.where(better, cost, best_cost)
        # Δz = −Jᵀ(JJᵀ + λ²I)⁻¹ r: a 6×6 solve whatever the number of segments.
        a = jnp.einsum("bmi,bki->bmk", j, j) + damping * damping * eye
        y = solve_spd(a, r)  # unrolled Cholesky, as cr_nlp's LM (faster than LAPACK here)
        z = project_z(robot, z - jnp.einsum("bmi,bm->bi", j, y))
        return z, best_z, best_cost

    z0 = project_z(robot, z0)
    # Derived from z0 (not jnp.full) so that under shard_map it varies per shard as z does.
    init = (z0, z0, jnp.inf + 0.0 * z0[:, 0])
    z, best_z, best_cost = jax.lax.fori_loop(0, iterations, step, init)
    r = res(z, target_position, target_rotation)
    cost = jnp.sum(r * r, axis=-1)
    better = cost < best_cost
    return (jnp.where(better[:, None], z, best_z), jnp.where(better, cost, best_cost))


@functools.cache
def _compiled_newton(robot: Robot, iterations: int, batch_size: int) -> Any:
    """The jitted batch iteration, split over the JAX devices (one per CPU core with
    ``use_host_devices``) as cr_nlp's LM is, so the baseline uses every core too."""
    solve = partial(_damped_newton, robot, iterations)
    return split_over_devices(solve, (True, True, True, False, False), batch_size, outputs=2)


def damped_newton_ik(robot: Robot | str, positions: Any, wxyz: Any,
                     config: DampedNewtonConfig = DampedNewtonConfig(), seed: int = 0,
                     starts: Any = None) -> BaselineSolve:
    """Damped Newton–Raphson IK from ``config.starts`` random starts per target.

    Args:
        robot: a ``Robot`` or a robot file.
        positions: (T, 3) target tip positions, metres.
        wxyz: (T, 4) target tip orientations, unit quaternions (w, x, y, z).
        config: damping, iterations, starts, dtype.
        seed: seed of the random starts.
        starts: optional start configurations θ, φ, L (rad, rad, m), (T, 3n) or
            (T, K, 3n), instead of the random ones.

    Returns ``BaselineSolve(q (T, 3n), seconds)``; the time covers the whole call, from
    numpy in (start sampling included) to numpy out, and compilation on the first call
    for a batch size (batches are padded to powers of two from 256 up).
    """
    start = time.perf_counter()
    robot = load_robot(robot)
    positions = np.asarray(positions, dtype=float).reshape(-1, 3)
    rotations = matrix_from_wxyz(np.asarray(wxyz, dtype=float).reshape(-1, 4))
    t, k, n = len(positions), config.starts, robot.dof
    if starts is None:
        q0 = random_configurations(robot, t * k, seed)
    else:
        q0 = np.asarray(starts, dtype=float).reshape(t, -1, n)
        k = q0.shape[1]
        q0 = q0.reshape(-1, n)
    dtype = jnp.dtype(config.dtype)
    z0 = np.asarray(q_to_z(robot, q0))
    free = np.ones(n)
    free[2::3] = ~robot.lengths_fixed()
    target_position = np.repeat(positions, k, 0)
    target_rotation = np.repeat(rotations.reshape(-1, 9), k, 0)
    devices = len(jax.devices())
    # Power-of-two batches from 256 up: few compiled shapes, equal shards, little padding.
    padded = 256
    while padded < len(z0):
        padded *= 2
    pad = padded - len(z0) + (-padded % devices)  # padding repeats the first problem
    if pad:
        z0, target_position, target_rotation = (
            np.concatenate([x, np.repeat(x[:1], pad, 0)])
            for x in (z0, target_position, target_rotation))
    solve = _compiled_newton(robot, config.iterations, len(z0))
    z, cost = solve(jnp.asarray(z0, dtype), jnp.asarray(target_position, dtype),
                    jnp.asarray(target_rotation, dtype), jnp.asarray(free, dtype),
                    jnp.asarray(config.damping, dtype))
    z, cost = np.asarray(jax.block_until_ready(z))[: t * k], np.asarray(cost)[: t * k]
    best = np.argmin(np.where(np.isfinite(cost), cost, np.inf).reshape(t, k), axis=1)
    z_best = z.reshape(t, k, n)[np.arange(t), best]
    q = clip_to_limits(robot, np.asarray(z_to_q(robot, z_best), dtype=float))
    return BaselineSolve(q, time.perf_counter() - start)


# ================================================================ scipy, derivative-free


@dataclass(frozen=True)
class ScipyConfig:
    """Settings of the derivative-free scipy baseline."""

    method: str = "Nelder-Mead"
    """``scipy.optimize.minimize`` method: "Nelder-Mead" (bounded since scipy 1.7) or
    "Powell" (bounded). On 60 targets each (seed 7) Nelder–Mead reached 35 % (tdcr3) and
    100 % (tdcr6_ext) in 0.10–0.16 s per target, Powell 18 % and 95 % in 0.14–0.38 s."""
    max_evaluations: int = 20_000
    """Most pose-error evaluations per target."""
    xtol: float = 1e-8
    """Stopping tolerance on the variables (rad, m)."""
    ftol: float = 1e-12
    """Stopping tolerance on the squared pose error."""


def _squared_pose_error_function(robot: Robot, free_index: np.ndarray) -> ca.Function:
    """CasADi f(x, p) = ‖log(T_tip⁻¹·T_target)‖² (mixed m²/rad²), built from the model's
    CasADi backend: x the free entries of q (rad, rad, m), p = [target position (3, m),
    target rotation (9, row-major)]. A compiled-graph call costs a few tens of µs, about
    4× less than the same model evaluated with numpy scalars."""
    model = CasadiModel(robot)
    x = ca.SX.sym("x", len(free_index))
    p = ca.SX.sym("p", 12)
    lo, _ = robot.q_bounds()
    entries = [ca.SX(float(lo[i])) for i in range(robot.dof)]  # fixed lengths: L = L_min
    for k, i in enumerate(free_index):
        entries[i] = x[k]
    rotation = ca.reshape(p[3:], 3, 3).T  # row-major entries → matrix
    err = model.functions_q["pose_error"](ca.vertcat(*entries), p[:3], rotation)
    return ca.Function("squared_pose_error", [x, p], [ca.dot(err, err)])


def scipy_ik(robot: Robot | str, positions: Any, wxyz: Any,
             config: ScipyConfig = ScipyConfig(), seed: int = 0, starts: Any = None,
             progress: bool = False) -> BaselineSolve:
    """Derivative-free IK, one target at a time, from one random start each.

    Args:
        robot: a ``Robot`` or a robot file.
        positions: (T, 3) target tip positions, metres.
        wxyz: (T, 4) target tip orientations, unit quaternions (w, x, y, z).
        config: method and tolerances.
        seed: seed of the random starts.
        starts: optional (T, 3n) start configurations θ, φ, L (rad, rad, m) instead of
            the random ones.
        progress: show a tqdm bar over the targets.

    Returns ``BaselineSolve(q (T, 3n), seconds)``.
    """
    robot = load_robot(robot)
    positions = np.asarray(positions, dtype=float).reshape(-1, 3)
    rotations = matrix_from_wxyz(np.asarray(wxyz, dtype=float).reshape(-1, 4))
    starts = (random_configurations(robot, len(positions), seed) if starts is None
              else np.asarray(starts, dtype=float).reshape(len(positions), robot.dof))
    fixed_length = np.repeat(robot.lengths_fixed(), 3) & (np.arange(robot.dof) % 3 == 2)
    free_index = np.flatnonzero(~fixed_length)
    bounds = []
    for s in robot.segments:
        phi = ((s.phi_min, s.phi_max) if s.phi_limited else (None, None))
        bounds += [(0.0, s.theta_max), phi, (s.length_min, s.length_max)]
    bounds = [bounds[i] for i in free_index]
    options: dict[str, Any] = {"maxfev": config.max_evaluations, "xtol": config.xtol}
    options["ftol" if config.method == "Powell" else "fatol"] = config.ftol
    if config.method != "Powell":
        options["xatol"] = options.pop("xtol")
    rows: Any = range(len(positions))
    if progress:
        from tqdm.auto import tqdm
        rows = tqdm(rows, desc=f"scipy {config.method} {robot.name}", unit="target",
                    leave=False)
    q = starts.copy()
    start = time.perf_counter()
    error = _squared_pose_error_function(robot, free_index)
    for i in rows:
        params = ca.DM(np.concatenate([positions[i], rotations[i].ravel()]))

        def objective(x: np.ndarray, params: ca.DM = params) -> float:
            return float(error(x, params))

        found = scipy.optimize.minimize(objective, starts[i][free_index], method=config.method,
                                        bounds=bounds, options=options)
        q[i, free_index] = found.x
    seconds = time.perf_counter() - start
    # Wrap φ into [−π, π) for the user (it was free during the search).
    q[:, 1::3] = np.where(np.isfinite(np.array([s.phi_min for s in robot.segments])),
                          q[:, 1::3], (q[:, 1::3] + math.pi) % (2 * math.pi) - math.pi)
    return BaselineSolve(clip_to_limits(robot, q), seconds)
