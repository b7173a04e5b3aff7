"""History-aware actuation: play (backlash) operators on the tendon commands (issue 42).

A tendon driven through friction and backlash does not follow its command at once: after
a reversal the command must travel some width r before the tendon moves again. The play
operator of width r models that with one state per tendon,

    y(t) = clip(y(t−1), d(t) − r, d(t) + r),        y(−1) = 0 (at rest at the zero),

and a Prandtl–Ishlinskii sum of K of them, with per-tendon weights w_jk ≥ 0, gives the
command the static model sees (``actuation.History``):

    d_eff_j(t) = d_j(t) + Σ_k w_jk · (y_jk(t) − d_j(t)).

d_eff follows d with slope 1 while every operator is pushed, 1 − Σ_k w_jk inside all the
plays, so with Σ_k w_jk < 1 it rises strictly with d and the operator has an exact inverse
(``compensate_commands``): the commands that make the history-aware model take a planned
shape. Rows are in time order; the operators need only that order, not the time step.

Public functions take numpy and return float64 numpy; ``play_outputs`` and
``effective_commands_jax`` are the traceable JAX forms (``jax.lax.scan`` over time) that the
fit (``tasks.calibration.history``) differentiates.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ._actuation_block import History as History
from .actuation import predict_tip
from .robot import Robot


def history_of(robot: Robot) -> History | None:
    """The robot file's ``actuation.history`` block, None without one (static model)."""
    act = getattr(robot, "actuation", None)
    return None if act is None else act.history


def play_outputs(commands: jax.Array, widths: jax.Array,
                 initial: jax.Array | None = None) -> jax.Array:
    """(T, n, K) outputs of K play operators of widths (K,) m on each of the n command
    series (T, n) m, from ``initial`` (n, K) m (default zero: at rest at the zero);
    traceable and differentiable in commands and widths (``jax.lax.scan`` over time)."""
    commands = jnp.asarray(commands)
    state = (jnp.zeros(commands.shape[1:] + widths.shape, commands.dtype)
             if initial is None else jnp.asarray(initial, commands.dtype))

    def step(previous: jax.Array, command: jax.Array) -> tuple[jax.Array, jax.Array]:
        y = jnp.clip(previous, command[:, None] - widths, command[:, None] + widths)
        return y, y

    return jax.lax.scan(step, state, commands)[1]


def effective_commands_jax(commands: jax.Array, widths: jax.Array, weights: jax.Array,
                           initial: jax.Array | None = None) -> jax.Array:
    """(T, n) the commands the static model sees, m, for the command series (T, n) m
    through the play operators of widths (K,) m with weights (n, K); traceable."""
    y = play_outputs(commands, widths, initial)
    return commands + jnp.sum(weights * (y - commands[..., None]), axis=-1)


_effective_jit = jax.jit(effective_commands_jax)


def _arrays(history: History) -> tuple[np.ndarray, np.ndarray]:
    return (np.asarray(history.widths, np.float64), np.asarray(history.weights, np.float64))


def _series(commands: Any, n_tendons: int) -> np.ndarray:
    cmd = np.atleast_2d(np.asarray(commands, dtype=np.float64))
    if cmd.ndim != 2 or cmd.shape[1] != n_tendons:
        raise ValueError(f"commands must be a (T, {n_tendons}) series of tendon "
                         f"displacements (m), got shape {np.shape(commands)}")
    if not np.all(np.isfinite(cmd)):
        raise ValueError("commands contain non-finite values")
    return cmd


def effective_commands(history: History, commands: Any) -> np.ndarray:
    """(T, n_tendons) the commands the static model sees, m, for a command series
    (T, n_tendons) m in time order (``history``'s play operators from rest). Float64."""
    widths, weights = _arrays(history)
    cmd = _series(commands, len(weights))
    with jax.enable_x64(True):
        out = _effective_jit(jnp.asarray(cmd), jnp.asarray(widths), jnp.asarray(weights))
        return np.asarray(out, np.float64)


def predict_tip_series(robot: Robot, commands: Any, history: bool = True,
                       iterations: int = 12) -> np.ndarray:
    """Predicted measured tip positions (T, 3) m for a series of commanded tendon
    displacements (T, n_tendons) m in time order: the static model
    (``model.actuation.predict_tip``) of the commands after the robot file's
    ``actuation.history`` operators. ``history=False``, or a robot without that block:
    the static model of the commands as given (rows independent). Float64."""
    block = history_of(robot)
    cmd = _series(commands, robot.n_tendons)
    if block is None:
        return predict_tip(robot, cmd, iterations)
    static = replace(robot, actuation=replace(robot.actuation, history=None))  # one program
    return predict_tip(static, effective_commands(block, cmd) if history else cmd, iterations)


def compensate_commands(history: History, target: Any) -> np.ndarray:
    """(T, n_tendons) the command series, m, whose effective commands
    (``effective_commands``) are ``target`` (T, n_tendons) m: the exact inverse of the
    play operators, step by step from rest. With ``target`` the static model's commands
    for a planned shape sequence, the history-aware model reproduces the plan. Float64.

    Each step solves d_eff(d) = target for d, where d_eff is piecewise linear in d with
    kinks at the operators' previous outputs ± their widths and slope ≥ 1 − Σ_k w_jk > 0:
    evaluated at the kinks, inverted by linear interpolation (slope 1 past the last)."""
    widths, weights = _arrays(history)
    goal = _series(target, len(weights))
    state = np.zeros((goal.shape[1], len(widths)))
    out = np.empty_like(goal)
    for t in range(len(goal)):
        for j in range(goal.shape[1]):
            kinks = np.sort(np.concatenate([state[j] - widths, state[j] + widths]))
            y = np.clip(state[j], kinks[:, None] - widths, kinks[:, None] + widths)
            values = kinks + (y - kinks[:, None]) @ weights[j]
            e = goal[t, j]
            if e <= values[0]:
                d = kinks[0] + (e - values[0])
            elif e >= values[-1]:
                d = kinks[-1] + (e - values[-1])
            else:
                d = float(np.interp(e, values, kinks))
            out[t, j] = d
            state[j] = np.clip(state[j], d - widths, d + widths)
    return out
