"""Branch keeping along a path: IK answers carried from waypoint to waypoint by numerical
continuation, a candidate table, the smoothest sequence through it, and jump bridging.

Stage 1 ("explore") of path following. Independent IK at every waypoint may land on a
different branch of the IK solutions at neighbouring waypoints; a sequence that switches
branch jumps (a tendon would have to move faster than it can). This stage:

1. runs the caller's batched IK (``candidates``) on every ``stride``-th waypoint (the
   anchors) and the last, and carries each anchor's answers halfway to the neighbouring
   anchors by continuation chains (``continue_chains``: a few LM steps per waypoint, each
   from the previous waypoint's answer plus the chain's last step, so a chain stays on
   one branch); the chains from both sides meet in the middle;
   the chains may minimise a cheaper residual than the one that scores the table (the
   pose alone, for a robot whose answers are isolated: ``tasks.geometry.follow``);
2. writes every chain's answers into a candidate table (R waypoints × K slots) and picks
   the sequence with the smallest configuration jumps
   (``stages.explore._sequence.smoothest_choice``)
   in one device program (``extend_and_choose``);
3. finds the intervals where that sequence's tendon speed exceeds the robot's limit
   (the jumps) and bridges each: chains from the answers on both sides walk across the
   jump (at most ``bridge_window`` waypoints) and their answers join the table before the
   sequence is chosen again (``rounds`` times). A jump that the table's own chains
   already walked from both of its answers, each step unsolved or over the limit, is the
   path's demand on those branches (ICRA's pen-up move): a bridge would walk the same
   steps again, so it is not bridged (``walked_speeds``).

The problem enters only as the residual of one waypoint (``WaypointResidual``); the task
(``tasks.geometry.follow``) owns it. Configurations are bending vectors z (rad, rad, m).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ..._cached_jit import cached_jit
from ..._programs import compile_program
from ...model import Robot, q_to_z_numpy
from ...model.kinematics import tendon_lengths_z
from ...model.limits import project_z
from ...model.rotations import matrix_from_wxyz
from ..explore._sequence import smoothest_choice
from ._lm import LMConfig, lm_solve

CHAIN_CONVERGED = 1e-5
"""Residual norm (m, rad) at which a continuation chain's LM stops at a waypoint."""

WaypointResidual = Callable[[jax.Array, Any, Any], jax.Array]
"""r(z, target, shared) of one waypoint: z (3n,), target = (position (3,) m, rotation (9,)
row major, tracking switch ()), shared the caller's common data (scene arrays, Δt, …).
Its norm is the candidate's residual norm (pose error m/rad plus penalties)."""

Candidates = Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]
"""IK on A waypoints (positions (A, 3) m, wxyz (A, 4)): configurations q (A, B, 3n)
(θ, φ, L) and residual norms (A, B) (inf: no answer), B answers per waypoint."""


@dataclass(frozen=True)
class ContinuationSettings:
    """Settings of the branch-keeping stage (``tasks.geometry.follow.FollowConfig`` fills them)."""

    iterations: int = 6
    """LM iterations per waypoint of a continuation chain."""
    rounds: int = 2
    """Rounds of (find the jumps of the chosen sequence, bridge them, choose again)."""
    max_jumps: int = 4
    """Most jumps bridged per round (the largest first)."""
    bridge_window: int = 40
    """Waypoints each bridging chain walks from its jump outward."""
    stride: int = 10
    """IK on every ``stride``-th waypoint (and the last); 1: IK on every waypoint."""
    tolerance: float = 0.01
    """Candidates with a residual norm at or above this are used only where a waypoint has
    no better one (``smoothest_choice``)."""
    damping: float = 1e-4
    """Starting LM damping of the chains (``LMConfig.initial_damping``)."""
    give_up_iterations: int = 2
    """A chain still at or above ``tolerance`` after this many LM iterations at a
    waypoint stops iterating there (``LMConfig.give_up``; 0: off)."""

    def chain_config(self) -> LMConfig:
        """The chains' LM settings: converged at ``CHAIN_CONVERGED``, ``damping``, the
        give-up rule."""
        return LMConfig(cost_tolerance=0.5 * CHAIN_CONVERGED ** 2,
                        initial_damping=self.damping,
                        give_up=(((self.give_up_iterations, 0.5 * self.tolerance ** 2),)
                                 if self.give_up_iterations > 0 else ()))


def continue_chains(residual: WaypointResidual, score: WaypointResidual | None,
                    project: Callable[[jax.Array], jax.Array], iterations: int,
                    config: LMConfig, z_start: jax.Array, index: jax.Array, active: jax.Array,
                    positions: jax.Array, rotations: jax.Array, track: jax.Array, shared: Any,
                    free: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Numerical continuation of C answers along the path.

    Chain c starts at ``z_start[c]`` (3n,) and visits the waypoints ``index[c, 0]``,
    ``index[c, 1]``, … (C, L) in turn, at most ``iterations`` LM steps (``config``) on
    ``residual`` per waypoint from a secant prediction (the previous answer plus the
    chain's last step), converged at ``CHAIN_CONVERGED``: the answers only have to keep
    to their branch and rank the table, stage 2 refines the chosen sequence;
    where ``active[c, τ]`` (C, L) is False the chain holds still. ``positions`` (R, 3) m,
    ``rotations`` (R, 9), ``track`` (R,) are the waypoint targets. Returns z (C, L, 3n)
    and the residual norms (C, L) at every visited waypoint: of ``score`` where given
    (the chains may minimise a cheaper residual than the one the table is judged by),
    else of ``residual``."""
    def step(carry: tuple, tau: jax.Array) -> tuple[tuple, tuple]:
        z, velocity = carry
        at = index[:, tau]
        moving = active[:, tau, None]
        # Waypoints are close: the last step predicts the next answer on the same branch,
        # so a few LM steps finish it. A chain that holds still tracks nothing (switch 0),
        # so that it never keeps the batch's LM loop running.
        held = (positions[at], rotations[at], jnp.where(moving[:, 0], track[at], 0.0))
        solved, cost, *_ = lm_solve(residual, project, z + velocity, held, shared, free,
                                   jnp.int32(iterations), config=config)
        z_out = jnp.where(moving, solved, z)
        velocity = jnp.where(moving, z_out - z, velocity)
        return (z_out, velocity), (z_out, jnp.sqrt(2.0 * cost))

    start = (z_start, jnp.zeros_like(z_start))
    _, (z, err) = jax.lax.scan(step, start, jnp.arange(index.shape[1]))
    z, err = jnp.swapaxes(z, 0, 1), jnp.swapaxes(err, 0, 1)
    if score is not None:
        # Scored once after the walk, all C·L answers in one batch (not one small batch
        # per waypoint inside the scan): the scores never steer the chains.
        flat = z.reshape(-1, z.shape[-1])
        at = index.reshape(-1)
        r = jax.vmap(score, in_axes=(0, 0, None))(flat, (positions[at], rotations[at],
                                                         track[at]), shared)
        err = jnp.sqrt(jnp.sum(r * r, axis=-1)).reshape(index.shape)
    return z, err


def pad_chains(starts: np.ndarray, index: np.ndarray, active: np.ndarray,
               column: np.ndarray) -> tuple[np.ndarray, ...]:
    """C chains (starts (C, 3n); index, active (C, L); table column (C,)) padded with
    inactive ones to a multiple of 16, so that few chain programs are compiled (the
    anchors' 90 chains of a 150-waypoint path run as 96, not 128)."""
    extra = 16 * -(-len(starts) // 16) - len(starts)
    return (np.concatenate([starts, np.repeat(starts[:1], extra, 0)]),
            np.concatenate([index, np.zeros((extra, index.shape[1]), int)]),
            np.concatenate([active, np.zeros((extra, index.shape[1]), bool)]),
            np.concatenate([column, np.full(extra, column[-1] if len(column) else 0)]))


def extend_table(extra: int, table_z: jax.Array, table_err: jax.Array, chain_z: jax.Array,
                 chain_err: jax.Array, index: jax.Array, active: jax.Array,
                 column: jax.Array) -> tuple[jax.Array, jax.Array]:
    """The candidate table (R, K, 3n) z and (R, K) residual norms with ``extra`` empty
    columns appended and the chains' answers written in: chain c's answer at its τ-th
    waypoint goes to row ``index[c, τ]``, column ``column[c]``, where ``active[c, τ]``; a
    residual that is not finite counts as no answer (inf)."""
    r = table_z.shape[0]
    dtype = chain_z.dtype
    table_z = jnp.concatenate([table_z.astype(dtype),
                               jnp.zeros((r, extra, table_z.shape[2]), dtype)], axis=1)
    table_err = jnp.concatenate([table_err.astype(dtype),
                                 jnp.full((r, extra), jnp.inf, dtype)], axis=1)
    rows = jnp.where(active, index, r)                      # row r: dropped
    columns = jnp.broadcast_to(column[:, None], index.shape)
    chain_err = jnp.where(active & jnp.isfinite(chain_err), chain_err, jnp.inf)
    return (table_z.at[rows, columns].set(chain_z, mode="drop"),
            table_err.at[rows, columns].set(chain_err, mode="drop"))


def chain_links(links: np.ndarray, rows: np.ndarray, columns: np.ndarray,
                valid: np.ndarray) -> np.ndarray:
    """``links`` (R, K, 2) int with the steps of C chains entered, in place: chain c's
    table cells in the order it visited them are (``rows[c, s]``, ``columns[c, s]``)
    where ``valid[c, s]`` (C, S), its start cell first where it started from one; a step
    between adjacent rows links the two cells: ``links[r, k, 0]`` is the column of the
    cell at row r − 1 and ``links[r, k, 1]`` the one at row r + 1 that a chain stepped
    between with (r, k) (−1: none). Returns ``links``."""
    step = valid[:, :-1] & valid[:, 1:]
    here, there = rows[:, :-1][step], rows[:, 1:][step]
    col_here, col_there = columns[:, :-1][step], columns[:, 1:][step]
    for sign, side in ((1, 1), (-1, 0)):            # steps forward, then backward
        along = there - here == sign
        links[here[along], col_here[along], side] = col_there[along]
        links[there[along], col_there[along], 1 - side] = col_here[along]
    return links


def walked_speeds(robot: Robot, table_z: jax.Array, table_err: jax.Array,
                  links: jax.Array, choice: jax.Array, tolerance: jax.Array,
                  seconds: jax.Array) -> jax.Array:
    """Per interval i (R − 1,) m/s: the lower largest tendon speed of the table's two
    chain steps across it from the chosen answers (``links``: forward from row i's,
    backward from row i + 1's), a step whose far answer does not solve its waypoint
    (residual norm at or above ``tolerance``) counting as inf; NaN where either step is
    not in the table. Above the limit: a chain from either answer already crossed the
    interval and could not do it within the limit."""
    r = table_z.shape[0]
    rows = jnp.arange(r - 1)
    chosen = table_z[jnp.arange(r), choice]
    forward = links[rows, choice[:-1], 1]
    backward = links[rows + 1, choice[1:], 0]

    def step_speed(z_a: jax.Array, z_b: jax.Array, far_err: jax.Array,
                   column: jax.Array) -> jax.Array:
        change = tendon_lengths_z(robot, z_b - z_a).astype(z_a.dtype)
        speed = jnp.max(jnp.abs(change), axis=1) / seconds
        speed = jnp.where(far_err < tolerance, speed, jnp.inf)
        return jnp.where(column >= 0, speed, jnp.nan)

    ahead = step_speed(chosen[:-1], table_z[rows + 1, forward], table_err[rows + 1, forward],
                       forward)
    behind = step_speed(table_z[rows, backward], chosen[1:], table_err[rows, backward],
                        backward)
    return jnp.minimum(ahead, behind)                 # NaN where either is NaN


def extend_and_choose(robot: Robot, extra: int, table_z: jax.Array, table_err: jax.Array,
                      chain_z: jax.Array, chain_err: jax.Array, index: jax.Array,
                      active: jax.Array, column: jax.Array, links: jax.Array,
                      tolerance: jax.Array, seconds: jax.Array) -> tuple[jax.Array, ...]:
    """``extend_table``, then the smoothest sequence through it
    (``stages.explore._sequence.smoothest_choice``), its tendon speeds and the table's own steps
    across its intervals (``walked_speeds``; ``links`` (R, K, 2) of the extended table),
    in one device program.

    Returns the table (z, residual norms), the chosen (R, 3n) z, the largest tendon
    speed (R − 1,) m/s of every interval (Δℓ over ``seconds`` (R − 1,) s) and the walked
    speeds (R − 1,) m/s."""
    table_z, table_err = extend_table(extra, table_z, table_err, chain_z, chain_err, index,
                                      active, column)
    choice = smoothest_choice(table_z, table_err, tolerance)
    chosen = table_z[jnp.arange(table_z.shape[0]), choice]
    # Tendon lengths are linear in z (no constant term): the change over an interval is
    # the lengths of the change, without the cancellation of two ~1 m float32 lengths.
    change = tendon_lengths_z(robot, jnp.diff(chosen, axis=0)).astype(chosen.dtype)
    speed = jnp.max(jnp.abs(change), axis=1) / seconds
    walked = walked_speeds(robot, table_z, table_err, links, choice, tolerance, seconds)
    return table_z, table_err, chosen, speed, walked


class BranchContinuation:
    """Stage 1 of path following for one robot: candidates by IK and continuation, the
    smoothest sequence, jump bridging (module docstring). Programs are compiled once per
    shape and reused across paths.

    Args:
        robot: the robot.
        residual: the waypoint residual that judges every candidate (``WaypointResidual``);
            must be hashable (a module-level function or a ``functools.partial`` of one).
        candidates: the batched IK (``Candidates``).
        free: (3n,) 1.0 for the variables the chains may move, 0.0 for fixed lengths.
        dtype: JAX dtype of the device programs.
        settings: ``ContinuationSettings``.
        chain_residual: the residual the chains minimise, when cheaper than ``residual``
            (hashable too; None: ``residual`` itself). ``residual`` still scores their
            answers.
    """

    def __init__(self, robot: Robot, residual: WaypointResidual, candidates: Candidates,
                 free: Any, dtype: Any, settings: ContinuationSettings,
                 chain_residual: WaypointResidual | None = None) -> None:
        self.robot = robot
        self.residual = residual
        self.chain_residual = chain_residual
        self.candidates = candidates
        self.free = jnp.asarray(free, dtype)
        self.dtype = jnp.dtype(dtype)
        self.settings = settings
        self._compiled: dict[Any, Any] = {}
        self._choose_program = cached_jit(partial(extend_and_choose, robot),
                                          static_argnums=(0,), name="the waypoint choice",
                                          by_shape=True)
        self._extend = cached_jit(extend_table, static_argnums=(0,))
        self._score = cached_jit(partial(_scores, residual), name="the waypoint scores",
                                 by_shape=True)

    def sequence(self, positions: np.ndarray, wxyz: np.ndarray, seconds: np.ndarray,
                 shared: Any) -> np.ndarray:
        """The chosen (R, 3n) z (rad, rad, m; the device dtype) for R waypoints
        (positions (R, 3) m, wxyz (R, 4)); ``seconds`` (R − 1,) s between consecutive
        waypoints (tendon speeds); ``shared`` goes to the residual.

        On the device each round is two programs (the chains; the table, the sequence,
        its tendon speeds and walked speeds) and one read back (the chosen sequence and
        its speeds)."""
        base, links, ends, chains = self.anchor_chains(positions, wxyz, shared)
        table = self.choose(base, links, chains, 0, seconds)
        chosen, speed, walked = jax.device_get(table[2:])
        bridged: set[int] = set()
        for _ in range(self.settings.rounds):
            # An interval bridged once is not bridged again: measured on icra, the one
            # jump that no branch crosses (waypoint 70) was bridged a second time from the
            # answers the first round's chains brought, with the same final answer (0.1 s;
            # 1.3 s per round with whole-path chains).
            jumps = [i for i in self.jumps(speed, walked) if i not in bridged]
            if not jumps:
                break
            bridged |= set(jumps)
            chains, links = self.bridge(chosen, np.array(jumps), positions, wxyz, shared,
                                        ends, links)
            ends = None   # the ends' own answers are carried once
            table = self.choose(table[:2], links, chains, len(chains[2]), seconds)
            chosen, speed, walked = jax.device_get(table[2:])
        return np.asarray(chosen)

    def table(self, positions: np.ndarray, wxyz: np.ndarray,
              shared: Any) -> tuple[np.ndarray, np.ndarray]:
        """Candidates for R waypoints: z (R, K, 3n) and residual norms (R, K) (inf: no
        candidate), float64. Slots: [0, B) the anchors' own IK answers, [B, 2B) the
        forward chains (the first half of the way to the next anchor, rounded up), [2B, 3B)
        the backward chains (the second half, rounded up) (K = 3B; K = B with ``stride``
        1)."""
        base, _, _, chains = self.anchor_chains(positions, wxyz, shared)
        z, errors = self._extend(0, *base, *chains)
        return np.asarray(z, np.float64), np.asarray(errors, np.float64)

    def anchor_chains(self, positions: np.ndarray, wxyz: np.ndarray,
                      shared: Any) -> tuple[tuple, np.ndarray, tuple, tuple]:
        """``table`` before it is filled in: the anchors' table (z (R, K, 3n), residual
        norms (R, K), numpy, K = 3B), its chain steps (``chain_links``: (R, K, 2), each
        chain from its anchor's answer on), the first and last waypoints' own IK answers
        ((B, 3n) each, numpy) and the chains (``chains``' output) from every anchor halfway
        to its neighbouring anchors."""
        r = len(positions)
        stride = max(int(self.settings.stride), 1)
        anchors = np.unique(np.r_[np.arange(0, r, stride), r - 1])
        q, err = self.candidates(positions[anchors], wxyz[anchors])
        z_anchor = q_to_z_numpy(q)                                   # (A, B, 3n)
        if self.chain_residual is not None:
            # The candidates may come from a cheaper problem too (the pose alone): the
            # table judges every answer by ``residual``.
            err = np.where(np.isfinite(err), self.score(z_anchor, positions[anchors],
                                                        wxyz[anchors], shared), np.inf)
        ends = (z_anchor[0], z_anchor[-1])
        width = z_anchor.shape[1]
        slots = width if len(anchors) == r else 3 * width
        dof = self.robot.dof
        z = np.zeros((r, slots, dof))
        errors = np.full((r, slots), np.inf)
        z[anchors, :width], errors[anchors, :width] = z_anchor, err
        # Chain order: (interval between anchors, beam, forward/backward). Each chain walks
        # half the interval, rounded up, so the two meet on the middle waypoint(s):
        # walking the whole interval both ways took twice the LM steps for the same
        # answers (measured on square, sine and icra, 150 waypoints).
        lo, hi = anchors[:-1], anchors[1:]
        steps = -(-stride // 2)
        tau = np.arange(steps)
        visits = tau < -(-(hi - lo) // 2)[:, None]                     # (A − 1, S)
        index = np.where(visits[:, None], np.stack([lo[:, None] + 1 + tau,
                                                    hi[:, None] - 1 - tau], axis=1), 0)
        shape = (len(lo), width, 2)
        index = np.broadcast_to(index[:, None], shape + (steps,)).reshape(-1, steps)
        active = np.broadcast_to(visits[:, None, None], shape + (steps,)).reshape(-1, steps)
        starts = np.stack([z_anchor[:-1], z_anchor[1:]], axis=2).reshape(-1, dof)
        column = np.broadcast_to(width * np.arange(1, 3) + np.arange(width)[:, None],
                                 shape).reshape(-1)
        if len(anchors) == r:   # every waypoint has its own IK: nothing to continue
            starts, index, active, column = (x[:0] for x in (starts, index, active, column))
        start_row = np.broadcast_to(np.stack([lo, hi], axis=1)[:, None], shape).reshape(-1)
        start_column = np.broadcast_to(np.arange(width)[:, None], shape).reshape(-1)
        count = len(starts)
        links = chain_links(
            np.full((r, slots, 2), -1), np.c_[start_row[:count], index],
            np.c_[start_column[:count], np.broadcast_to(column[:, None], index.shape)],
            np.c_[np.ones(count, bool), active])
        return (z, errors), links, ends, self.chains(starts, index, active, column, positions,
                                                     wxyz, shared)

    def score(self, z: np.ndarray, positions: np.ndarray, wxyz: np.ndarray,
              shared: Any) -> np.ndarray:
        """Residual norms (A, B) of ``residual`` at candidates z (A, B, 3n) of A waypoints
        (positions (A, 3) m, wxyz (A, 4)), float64."""
        a, b, dof = z.shape
        rotations = matrix_from_wxyz(wxyz).reshape(-1, 9)
        target = (np.repeat(positions, b, 0).astype(self.dtype),
                  np.repeat(rotations, b, 0).astype(self.dtype), np.ones(a * b, self.dtype))
        norms = self._score(z.reshape(-1, dof).astype(self.dtype), target, shared)
        return np.asarray(norms, np.float64).reshape(a, b)

    def chains(self, starts: np.ndarray, index: np.ndarray, active: np.ndarray,
               column: np.ndarray, positions: np.ndarray, wxyz: np.ndarray,
               shared: Any) -> tuple[Any, ...]:
        """``continue_chains`` for C chains (starts (C, 3n); index, active (C, L); table
        column (C,)) over the R waypoints (positions (R, 3) m, wxyz (R, 4)), padded by
        ``pad_chains``: z (C', L, 3n) and residual norms (C', L) on the device (not waited
        for), then index, active and column padded alike. R is padded to a power of two
        (at least 32), so few programs are compiled."""
        starts, index, active, column = pad_chains(starts, index, active, column)
        padded, length = index.shape
        dtype = self.dtype
        if padded == 0:
            return (np.zeros((0, length, self.robot.dof), dtype), np.zeros((0, length), dtype),
                    index, active, column)
        # The waypoint tables are padded too (never visited: ``index`` < R).
        rows = max(32, 1 << (len(positions) - 1).bit_length())
        positions = np.concatenate([positions, np.repeat(positions[:1], rows - len(positions), 0)])
        rotations = matrix_from_wxyz(wxyz).reshape(-1, 9)
        rotations = np.concatenate([rotations, np.repeat(rotations[:1], rows - len(rotations), 0)])
        # numpy in the program's dtypes: jnp.asarray would launch one conversion each.
        args = (starts.astype(dtype), index.astype(np.int32), active,
                positions.astype(dtype), rotations.astype(dtype), np.ones(rows, dtype),
                shared, self.free)
        key = (padded, length, rows, self.settings)
        if key not in self._compiled:
            if self.chain_residual is None:
                solved, score = self.residual, None
            else:
                solved, score = self.chain_residual, self.residual
            fn = partial(continue_chains, solved, score, partial(project_z, self.robot),
                         self.settings.iterations, self.settings.chain_config())
            # Chains are independent: split over the devices like the IK's LM (measured:
            # unsplit, the anchors' 96 chains ran on one core).
            self._compiled[key] = compile_program(fn, args, name="the path continuation",
                                                  batched=(True,) * 3 + (False,) * 5, outputs=2,
                                                  by_shape=True)
        z, err = self._compiled[key](*args)
        return z, err, index, active, column

    def choose(self, table: tuple, links: np.ndarray, chains: tuple, extra: int,
               seconds: np.ndarray) -> tuple[Any, ...]:
        """``extend_and_choose`` on the device (not waited for): the table (z, residual
        norms) with ``extra`` columns for the chains (``links``: the extended table's chain
        steps), the chosen (R, 3n) z, the tendon speed (R − 1,) m/s of every interval and
        its walked speed (``walked_speeds``)."""
        tolerance = np.asarray(self.settings.tolerance, self.dtype)
        return self._choose_program(extra, *table, *chains, links.astype(np.int32),
                                    tolerance, np.asarray(seconds, self.dtype))

    def jumps(self, speed: np.ndarray, walked: np.ndarray) -> np.ndarray:
        """Intervals (indices i: between rows i and i+1) of a sequence whose tendon speed
        (R − 1,) m/s exceeds the robot's limit, the largest first (at most
        ``max_jumps``), except those whose walked speed (``walked_speeds``, (R − 1,) m/s)
        does too: the table's chains crossed them from both answers already."""
        speed = np.asarray(speed, np.float64)
        limit = self.robot.tendon_speed_max
        bad = np.flatnonzero((speed > limit) & ~(np.asarray(walked) > limit))   # inf: never
        return bad[np.argsort(-speed[bad], kind="stable")][: self.settings.max_jumps]

    def bridge(self, z: np.ndarray, jumps: np.ndarray, positions: np.ndarray,
               wxyz: np.ndarray, shared: Any, ends: tuple[np.ndarray, np.ndarray] | None,
               links: np.ndarray) -> tuple[tuple[Any, ...], np.ndarray]:
        """Continuation chains (``chains``' output) into new table columns after the
        table's (``links`` (R, K, 2): its chain steps): from each jump's left answer (of
        the (R, 3n) sequence z) forward and its right answer backward, and (``ends``: the
        (B, 3n) candidates of the first and last waypoints) from every first candidate
        forward and every last one backward; each chain walks at most ``bridge_window``
        waypoints (one compiled shape whatever the jump's place). Returns the chains and
        the links of the extended table (each chain's first answer re-solves the row it
        starts at)."""
        r, width = links.shape[:2]
        window = max(int(self.settings.bridge_window), 1)
        first_row = np.stack([jumps, jumps + 1], axis=1).reshape(-1)
        starts = z[first_row]
        if ends is not None:
            pairs = np.stack([ends[0], ends[1]], axis=1)               # (B, 2, 3n)
            starts = np.concatenate([pairs.reshape(-1, z.shape[1]), starts])
            first_row = np.concatenate([np.tile([0, r - 1], len(ends[0])), first_row])
        forward = np.arange(len(first_row)) % 2 == 0
        tau = np.arange(window)
        index = np.where(forward[:, None], first_row[:, None] + tau, first_row[:, None] - tau)
        active = (index >= 0) & (index < r)
        chains = self.chains(starts, np.clip(index, 0, r - 1), active,
                             width + np.arange(len(starts)), positions, wxyz, shared)
        index, active, column = chains[2:]
        links = np.concatenate([links, np.full((r, len(column), 2), -1)], axis=1)
        return chains, chain_links(links, index, np.broadcast_to(column[:, None], index.shape),
                                   active)


def _scores(residual: Callable, z: jax.Array, target: Any, shared: Any) -> jax.Array:
    """‖residual‖ of each candidate z (…, 3n) against its target (the waypoint scores)."""
    return jnp.linalg.norm(jax.vmap(residual, in_axes=(0, 0, None))(z, target, shared), axis=-1)
