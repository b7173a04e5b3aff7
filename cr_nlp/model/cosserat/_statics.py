"""The batched Cosserat statics (``solve_statics``): rounds of the shooting, the branch
check and the stability test over a batch of load cases (numpy in, numpy out).

The per-case rod and its shooting are ``model.cosserat`` (and ``model._rod``). Here a batch
is split into the cases that need no shooting (no external force: M(0) is known), the
direct continuation of the others (tensions whole, loads ramped: cheap, and the loading
path's answer wherever the equilibrium is unique), and, for the doubtful ones, the
loading path itself (tensions and loads together from rest) and more starts
(``_check``). Units: metres, radians, newtons, N·m, kg, m/s².
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ...runtime import cached, configure
from ..loads import static_loads
from ..robot import Robot
from ._batch_rows import _one, _padded, _rows, _split, _typed
from ._equilibria import DOUBTFUL, distinct, jacobi_margin, load_parameter, shape_and_margin
from ._rod import CaseLoads, StaticsConfig, _layout
from ._shooting import Equilibrium, StaticsResult, _finish, _finished, _Newton, _run, _shooting

# Newton iterations every case of a batch gets; the few cases that need more continue in
# a smaller batch, so that they do not hold the whole batch in the loop.
_FIRST_ROUND = 10


@cached(maxsize=64)
def _programs(robot: Robot, config: StaticsConfig) -> tuple[Any, Any, Any, Any]:
    """(first round, further rounds, finish, stability): jitted and vmapped over cases;
    jit keeps one compiled program per padded batch size."""
    lay, coarse = _layout(robot, config), _layout(robot, config, coarse=True)

    def first(tension: jax.Array, loads: CaseLoads, x0: jax.Array, lam0: jax.Array,
              mode: jax.Array) -> _Newton:
        start, iterate, done = _shooting(lay, coarse, config, tension, loads, mode)
        return _run(iterate, done, start(x0, lam0), min(_FIRST_ROUND, config.max_iterations))

    def further(tension: jax.Array, loads: CaseLoads, mode: jax.Array,
                state: _Newton) -> _Newton:
        _, iterate, done = _shooting(lay, coarse, config, tension, loads, mode)
        return _run(iterate, done, state, max(0, config.max_iterations - _FIRST_ROUND))

    def finish(base_moment: jax.Array, tension: jax.Array,
               loads: CaseLoads) -> dict[str, jax.Array]:
        return _finish(lay, config, base_moment, tension, loads)

    def stability(base_moment: jax.Array, tension: jax.Array, loads: CaseLoads) -> jax.Array:
        return jacobi_margin(lay, config, base_moment, tension, loads)

    return (_split(jax.vmap(first), 5), _split(jax.vmap(further), 4),
            _split(jax.vmap(finish), 3), _split(jax.vmap(stability), 3))


def settle_function(robot: Robot, config: StaticsConfig) -> Any:
    """The traced settle of one case from a nearby equilibrium, as a function of a batch
    of one: (tensions (1, n) N, ``CaseLoads`` (1, …) base frame, M(0) (1, 3) N·m base
    frame, ∂M(L)/∂M(0) (1, 3, 3) base frame or NaN) → (Newton's state, the stability
    margin, the shape, the answer's ∂M(L)/∂M(0)): Newton under the full loads from the given
    M(0) (one round), its stability and its shape. ``settled_statics`` reads its outputs;
    ``_settle_program`` compiles it alone, and a program that solves the tensions first
    (the live update's LM) can run it after them. Newton's first Jacobian is the given one
    (the previous equilibrium's) unless it holds a NaN (then differences). The stability
    test's unperturbed pass is the shape's (``shape_and_margin``: its four passes with the
    full constitutive iterations, one sequential pass fewer than the two apart: 2.27 →
    2.13 ms for tdcr2 under gravity and a payload)."""
    lay, coarse = _layout(robot, config), _layout(robot, config, coarse=True)

    def settle(tension: jax.Array, loads: CaseLoads, x0: jax.Array, jacobian: jax.Array
               ) -> tuple[_Newton, jax.Array, dict[str, jax.Array], jax.Array]:
        mode = jnp.asarray([0.0, 1.0], tension.dtype)
        start, iterate, done = _shooting(lay, coarse, config, tension, loads, mode,
                                         secant=True)
        state = _run(iterate, done, start(x0, 1 + 0 * x0[0], jacobian),
                     min(_FIRST_ROUND, config.max_iterations))
        margin, tip, shape = shape_and_margin(lay, config, state.x, tension, loads)
        return state, margin, _finished(lay, config, state.x, loads, shape), tip

    return _one(settle)


@cached(maxsize=64)
def _settle_program(robot: Robot, config: StaticsConfig) -> Any:
    """``settle_function`` compiled alone (a live update's verdict when its tensions come
    from elsewhere: one call instead of three)."""
    return _split(settle_function(robot, config), 4)


class _Solved(NamedTuple):
    """Shooting answers of some rows (numpy)."""

    x: np.ndarray           # (R, 3) M(0), N·m
    iterations: np.ndarray  # (R,)
    converged: np.ndarray   # (R,) the loop's own test
    stall: np.ndarray       # (R,) load factor of a fold, −1: none


def _solve_rows(robot: Robot, config: StaticsConfig, tension: np.ndarray, loads: CaseLoads,
                x0: np.ndarray, lam0: np.ndarray, mode: np.ndarray, dtype: Any,
                further_round: Any = True) -> _Solved:
    """Shoot the given rows from M(0) = ``x0`` at load factor ``lam0`` with ``mode``
    (R, 2) (see ``_shooting``): every row gets ``_FIRST_ROUND`` iterations, then the
    unfinished ones among ``further_round`` (True: all; or a (R,) mask) continue in a
    smaller batch."""
    first, further, _, _ = _programs(robot, config)
    count = len(tension)
    rows = (tension, loads)
    state = first(*_typed(_padded((*rows, x0, lam0, mode)), dtype))
    x, its = np.array(state.x)[:count], np.array(state.it)[:count]
    stall = np.array(state.stall)[:count]
    limit = min(_FIRST_ROUND, config.max_iterations)
    tol = config.resolved_tolerance() * _layout(robot, config).moment_scale

    def finished(s: _Newton, n: int) -> np.ndarray:
        return ((np.asarray(s.lam)[:n] >= 1.0)
                & (np.linalg.norm(np.asarray(s.r)[:n], axis=1) <= tol))

    ok = finished(state, count)
    left = np.flatnonzero(~ok & (its >= limit) & further_round)
    if left.size and config.max_iterations > limit:
        # Padded with copies of the first unfinished case (zero rows would have no state).
        def pick(a: Any) -> Any:
            return _padded(np.asarray(a)[left], edge=True)

        more = further(*_typed(jax.tree_util.tree_map(pick, (*rows, mode)), dtype),
                       jax.tree_util.tree_map(lambda a: jnp.asarray(pick(a)), state))
        x[left], its[left] = np.asarray(more.x)[:left.size], np.asarray(more.it)[:left.size]
        stall[left] = np.asarray(more.stall)[:left.size]
        ok[left] = finished(more, left.size)
    return _Solved(x, its, ok, stall)


def _stable(robot: Robot, config: StaticsConfig, x: np.ndarray, tension: np.ndarray,
            loads: CaseLoads, dtype: Any) -> np.ndarray:
    """(R,) True where M(0) = ``x`` gives a stable equilibrium (``model._equilibria``)."""
    stability = _programs(robot, config)[3]
    det = stability(*_typed(_padded((x, tension, loads)), dtype))
    return np.asarray(det)[:len(x)] > 0.0


# Other starts of a doubtful case, beside the direct continuation's answer: Newton under
# the full loads from the mirror image of that answer's M(0) (solved with the loading path,
# in one batch). A failed or unstable path answer (and every case with ``all_equilibria``)
# also gets Newton from M(0) = 0 and from four pushes sideways, and the loading path again
# in small steps (``small_step``).
_SEARCH_STARTS = 5


def small_step(config: StaticsConfig) -> float:
    """Largest load increment of the loading path's second try: small steps follow the
    branch past a bifurcation (an imperfect column buckles towards its imperfection).

    A third of the iteration budget (1/8 with the default 24 iterations): λ reaches 1
    after 1/step accepted steps, which leaves room for one rejected step in two. (A fixed
    1/32 never reached λ = 1 within 24 iterations: the second try always failed.)"""
    return 1.0 / max(1, config.max_iterations // 3)


def _starts(x: np.ndarray, push: np.ndarray) -> np.ndarray:
    """(R, 5, 3) M(0) starts for Newton under the full loads around the path's answers
    ``x`` (R, 3): zero and four pushes sideways of size ``push`` (R,), N·m."""
    sideways = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0]], float)
    return np.concatenate([np.zeros((len(x), 1, 3)),
                           x[:, None] + push[:, None, None] * sideways[None]], axis=1)


class _Check(NamedTuple):
    """What the branch check of some rows found."""

    base: np.ndarray        # (R, 3) the reported M(0)
    stable: np.ndarray      # (R,)
    equilibria: np.ndarray  # (R,)
    replaced: np.ndarray    # (R,) the loading path's answer was unstable or failed
    found: list             # per row: [(M(0), stable, reported)]


def _check(robot: Robot, config: StaticsConfig, tension: np.ndarray, loads: CaseLoads,
           push: np.ndarray, known: list[tuple[_Solved, np.ndarray]], search: np.ndarray,
           dtype: Any) -> _Check:
    """Count the distinct equilibria among the answers already ``known`` (the path's
    first, each with its stability) and, where ``search``, those of more starts; where the
    path's answer is not stable take the small-step path's if that is, else the stable
    equilibrium nearest to it."""
    rows = len(tension)
    scale = _layout(robot, config).moment_scale
    # columns: the path, the small-step path, the known others, the search starts
    columns = 2 + len(known) - 1 + (_SEARCH_STARTS if search.any() else 0)
    moments = np.zeros((rows, columns, 3))
    valid = np.zeros((rows, columns), bool)
    stable = np.zeros((rows, columns), bool)
    for k, (solved, solved_stable) in enumerate(known):
        col = 0 if k == 0 else k + 1
        moments[:, col], valid[:, col], stable[:, col] = (solved.x, solved.converged,
                                                          solved_stable)
    careful = np.flatnonzero(search)
    if careful.size:
        # One batch: the small-step path from rest, then Newton under the full loads from
        # the search starts, which get the first round only (one that needs more is
        # rarely the answer).
        x0 = _starts(moments[careful, 0], push[careful]).reshape(-1, 3)
        r = np.concatenate([careful, np.repeat(careful, _SEARCH_STARTS)])
        path_rows = np.arange(len(r)) < careful.size
        solved = _solve_rows(robot, config, tension[r], _rows(loads, r),
                             np.concatenate([np.zeros((careful.size, 3)), x0]),
                             np.where(path_rows, 0.0, 1.0),
                             np.where(path_rows[:, None], [1.0, small_step(config)],
                                      [0.0, 1.0]), dtype, further_round=path_rows)
        c = np.concatenate([np.ones(careful.size, int),
                            np.tile(np.arange(_SEARCH_STARTS), careful.size)
                            + 1 + len(known)])
        x, converged = solved.x, solved.converged
        stable_extra = np.zeros(len(r), bool)
        if converged.any():
            good = np.flatnonzero(converged)
            stable_extra[good] = _stable(robot, config, x[good], tension[r[good]],
                                         _rows(loads, r[good]), dtype)
        moments[r, c], valid[r, c], stable[r, c] = x, converged, stable_extra
    first = distinct(moments, valid, scale)
    chosen = np.zeros(rows, int)
    for i in np.flatnonzero(~(valid[:, 0] & stable[:, 0])):
        if valid[i, 1] & stable[i, 1]:  # the small-step path
            chosen[i] = 1
            continue
        options = np.flatnonzero(valid[i] & stable[i])
        if options.size:  # the stable equilibrium nearest to where the path ended
            gaps = np.linalg.norm(moments[i, options] - moments[i, 0], axis=1)
            chosen[i] = options[np.argmin(gaps)]
    found = []
    for i in range(rows):
        entries = list(np.flatnonzero(first[i]))
        # the chosen one stands for its group even when an equal answer came first
        same = np.linalg.norm(moments[i, entries] - moments[i, chosen[i]], axis=1)
        entries = [k for k, gap in zip(entries, same, strict=True) if gap > 1e-6 * scale]
        found.append([(moments[i, chosen[i]], bool(stable[i, chosen[i]]), True)]
                     + [(moments[i, k], bool(stable[i, k]), False) for k in entries])
    pick = np.arange(rows)
    return _Check(moments[pick, chosen], stable[pick, chosen], first.sum(axis=1),
                  chosen > 1, found)


def solve_statics(robot: Robot, tensions: Any, tip_force: Any = None, tip_moment: Any = None,
                  gravity: Any = None, config: StaticsConfig = StaticsConfig(), *,
                  distributed_force: Any = None, point_loads: Any = None,
                  all_equilibria: bool = False, start_moment: Any = None,
                  start_jacobian: Any = None) -> StaticsResult:
    """Equilibrium shapes for a batch of tendon tensions and loads (numpy in, numpy out).

    The answer is the equilibrium reached by loading the robot from rest (tensions and
    loads scaled together from zero, the branch followed; see the module), with its
    stability and the number of distinct equilibria found for the same loads.

    Args:
        robot: a robot with a ``mechanics`` block and fixed segment lengths.
        tensions: (n_tendons,) or (B, n_tendons) tendon tensions, newtons, ≥ 0, in the
            robot file's tendon order.
        tip_force: (3,) or (B, 3) force on the tip, N, world frame (default none).
        tip_moment: (3,) or (B, 3) moment on the tip, N·m, world frame (default none).
        gravity: (3,) or (B, 3) gravitational acceleration, m/s², world frame (default none).
        config: discretisation, tolerance and dtype.
        distributed_force: (3,) or (B, 3) force per metre along the whole backbone, N/m,
            world frame (default none).
        point_loads: wrenches at arc lengths, world frame: a list of
            ``{"s": m from the base, "force": [N], "moment": [N·m]}`` for every case, or
            one such list per case (``model.loads``).
        all_equilibria: solve every loaded case from several starts and return the
            distinct equilibria found in ``StaticsResult.all_equilibria``.
        start_moment: (3,) or (B, 3) moments at the base of nearby equilibria, N·m, world
            frame (e.g. the previous step's ``base_moment`` of a slow motion). A case is
            then solved by Newton under its full loads from there, the equilibrium a robot
            moving slowly from that one stays on, where that converges within one round
            and is stable (tdcr2 under gravity and a payload: 5–6 iterations from a
            neighbour, 4 for one case, against 7–10 from rest); elsewhere by the loading
            path from rest, as without it.
        start_jacobian: (3, 3) ∂M(L)/∂M(0) at ``start_moment``'s equilibrium, world frame:
            the ``tip_moment_jacobian`` of the one-case result that gave ``start_moment``.
            A one-case solve from ``start_moment`` takes it as Newton's first Jacobian
            instead of differences on a coarse grid (a slow motion's next step: 3 Newton
            iterations instead of 4, and no differences). Ignored for a batch.

    Returns:
        ``StaticsResult`` in the world frame; a case that did not converge is marked in
        ``converged`` (a value, not an exception).

    Raises:
        ValueError: wrong shapes, negative or non-finite tensions or loads, an unknown key
            or a point load off the robot (naming the case and the key), a robot without
            mechanics.

    Long: the public entry documents every load argument; its body (~110 lines) is the
    checks, the continued start, the direct continuation and the branch check's call, in
    order, on shared per-case arrays.
    """
    configure()
    t = np.atleast_2d(np.asarray(tensions, dtype=float))
    if t.ndim != 2 or t.shape[1] != robot.n_tendons:
        raise ValueError(f"tensions: {robot.name} has {robot.n_tendons} tendons, got shape "
                         f"{np.shape(tensions)}")
    if not np.all(np.isfinite(t)) or np.any(t < 0):
        bad = np.argwhere(~np.isfinite(t) | (t < 0))[0]
        raise ValueError(f"case {bad[0]}: tensions: tendon {bad[1] + 1}: a tension must be "
                         f"a finite number ≥ 0 N, got {t[tuple(bad)]}")
    if config.dtype not in ("float64", "float32"):
        raise ValueError(f"dtype: 'float64' or 'float32', got {config.dtype!r}")
    lay = _layout(robot, config)
    length = float(lay.arc_length[-1])
    if len(t) == 1:  # one tension set under every load case
        t = np.repeat(t, _load_batch(tip_force, tip_moment, gravity, distributed_force,
                                     point_loads), axis=0)
    batch = t.shape[0]
    world = static_loads(batch, length, tip_force, tip_moment, gravity, distributed_force,
                         point_loads)
    base_rot = robot.base_rotation
    base_pos = np.asarray(robot.base_position)
    frame = world.in_base_frame(base_rot)
    loads = _case_loads(frame)
    dtype = config.numpy_dtype
    # Without an external force N ≡ 0: M is constant between the point moments.
    base = frame.tip_moment + frame.point_moment.sum(axis=1)
    iterations = np.zeros(batch, dtype=int)
    stable, equilibria = np.ones(batch, bool), np.ones(batch, int)
    snap_load = np.full(batch, np.nan)
    found: list = [[(base[i], True, True)] for i in range(batch)]
    shot = np.flatnonzero(frame.has_force())
    out = jacobian = None
    # float64 without touching the process-wide flag (the batched stages keep theirs).
    with jax.enable_x64(config.dtype == "float64"):
        if shot.size and start_moment is not None:
            near = _start_moments(start_moment, batch) @ base_rot
            kept = _continued(robot, config, t[shot], _rows(loads, shot), near[shot], dtype,
                              _start_jacobian(start_jacobian, base_rot))
            if batch == 1:  # (the one case's shape; in a batch every case's is made below)
                out, jacobian = kept.shape, kept.jacobian
            base[shot[kept.any]] = kept.x
            iterations[shot[kept.any]] = kept.iterations
            for i in shot[kept.any]:
                found[i] = [(base[i], True, True)]
            shot = shot[~kept.any]
        if shot.size:
            part, tension = _rows(loads, shot), t[shot]
            # The direct continuation (tensions whole, the loads ramped) first: where the
            # equilibrium is unique it is the loading path's, and it is the cheaper one.
            direct = _solve_rows(robot, config, tension, part, np.zeros((shot.size, 3)),
                                 np.zeros(shot.size), np.tile([0.0, 1.0], (shot.size, 1)),
                                 dtype)
            direct_stable = _stable(robot, config, direct.x, tension, part, dtype)
            base[shot], iterations[shot] = direct.x, direct.iterations
            stable[shot] = direct_stable
            for i in shot:
                found[i] = [(base[i], bool(stable[i]), True)]
            ei = robot.mechanics.bending_stiffness
            doubtful = (all_equilibria | ~direct_stable | ~direct.converged
                        | ((direct.iterations > _FIRST_ROUND)
                           & (load_parameter(lay, frame.rows(shot), ei) >= DOUBTFUL)))
            if doubtful.any():
                d = np.flatnonzero(doubtful)
                rows, sub_tension, sub_loads = shot[d], tension[d], _rows(part, d)
                # the loading path and Newton from the direct answer's mirror, one batch
                both = np.concatenate([d, d])
                solved = _solve_rows(
                    robot, config, tension[both], _rows(part, both),
                    np.concatenate([np.zeros((d.size, 3)), -direct.x[d]]),
                    np.concatenate([np.zeros(d.size), np.ones(d.size)]),
                    np.concatenate([np.ones((d.size, 2)), np.tile([0.0, 1.0], (d.size, 1))]),
                    dtype, further_round=np.arange(2 * d.size) < d.size)
                path = _Solved(*_rows(solved, np.arange(d.size)))
                mirror = _Solved(*_rows(solved, np.arange(d.size, 2 * d.size)))
                answers = np.flatnonzero(solved.converged)
                solved_stable = np.zeros(2 * d.size, bool)
                solved_stable[answers] = _stable(robot, config, solved.x[answers],
                                                 tension[both[answers]],
                                                 _rows(part, both[answers]), dtype)
                path_stable = solved_stable[:d.size]
                search = all_equilibria | ~(path.converged & path_stable)
                force_size = (np.linalg.norm(frame.tip_force[rows], axis=1)
                              + np.linalg.norm(frame.point_force[rows], axis=2).sum(1)
                              + np.linalg.norm(frame.distributed_force[rows], axis=1)
                              * length
                              + np.linalg.norm(frame.gravity[rows], axis=1)
                              * float(lay.total_mass_moment[0]))
                push = np.maximum(0.5 * length * force_size, lay.moment_scale)
                check = _check(robot, config, sub_tension, sub_loads, push,
                               [(path, path_stable), (_Solved(*_rows(direct, d)),
                                                      direct_stable[d]),
                                (mirror, solved_stable[d.size:])], search, dtype)
                base[rows], stable[rows] = check.base, check.stable
                equilibria[rows], iterations[rows] = check.equilibria, path.iterations
                folded = path.stall >= 0
                snap_load[rows[folded]] = path.stall[folded]
                snap_load[rows[check.replaced & np.isnan(snap_load[rows])]] = 1.0
                for i, entries in zip(rows, check.found, strict=True):
                    found[i] = entries
        if out is None:  # (a one-case continued answer has its shape already)
            finish = _programs(robot, config)[2]
            out = finish(*_typed(_padded((base, t, loads)), dtype))
            out = {k: np.asarray(v)[:batch] for k, v in out.items()}
        shapes = None
        if all_equilibria:
            shapes = _shapes(robot, config, found, t, loads, base_rot, base_pos, dtype)
    return _result(robot, lay, out, iterations, stable, equilibria, snap_load, shapes,
                   jacobian)


def _result(robot: Robot, lay: Any, out: dict, iterations: np.ndarray, stable: np.ndarray,
            equilibria: np.ndarray, snap_load: np.ndarray, shapes: list | None = None,
            jacobian: np.ndarray | None = None) -> StaticsResult:
    """The world-frame ``StaticsResult`` of the base-frame shapes ``out`` (``_finish``'s,
    numpy) and what the solve found per case."""
    base_rot = robot.base_rotation
    positions = out["positions"].astype(float) @ base_rot.T + np.asarray(robot.base_position)
    rotations = np.einsum("ij,bpjk->bpik", base_rot, out["rotations"].astype(float))
    return StaticsResult(
        positions=positions, rotations=rotations, arc_length=lay.arc_length,
        tendon_displacements=out["tendon_displacements"].astype(float),
        converged=out["converged"].astype(bool), residual=out["residual"].astype(float),
        iterations=iterations,
        base_moment=out["base_moment"].astype(float) @ base_rot.T,
        base_force=out["base_force"].astype(float) @ base_rot.T,
        stable=stable, equilibria=equilibria, snap_load=snap_load, all_equilibria=shapes,
        tip_moment_jacobian=None if jacobian is None else base_rot @ jacobian @ base_rot.T)


def settle_arguments(robot: Robot, config: StaticsConfig, loads: Any, start_moment: Any,
                     start_jacobian: Any = None) -> tuple:
    """``settle_function``'s arguments after the tensions, typed for its program: the
    loads (a one-case ``model.loads.StaticLoads``, world frame) in the base frame, M(0) of
    the nearby equilibrium (``start_moment``, (3,) N·m, world frame) and its ∂M(L)/∂M(0)
    (``start_jacobian``, (3, 3) world frame, or None: differences)."""
    base_rot = robot.base_rotation
    jacobian = _start_jacobian(start_jacobian, base_rot)
    start = np.full((1, 3, 3), np.nan) if jacobian is None else jacobian.reshape(1, 3, 3)
    near = _start_moments(start_moment, 1) @ base_rot
    dtype = config.numpy_dtype
    return _typed((_case_loads(loads.in_base_frame(base_rot)), near, start), dtype)


def settled_statics(robot: Robot, config: StaticsConfig, outputs: Any) -> StaticsResult | None:
    """The ``StaticsResult`` of the one case that ``settle_function`` settled (its outputs,
    on the device or fetched), or None where Newton did not reach the full loads within
    its round or the answer is unstable: there ``solve_statics`` without a start (the
    loading path from rest) answers the case, as ``solve_statics`` itself does."""
    kept = _settled(robot, config, outputs)     # (leaf by leaf: jax.device_get 6× slower)
    if not kept.any[0]:
        return None
    return _result(robot, _layout(robot, config), kept.shape, kept.iterations,
                   np.ones(1, bool), np.ones(1, int), np.full(1, np.nan),
                   jacobian=kept.jacobian)


class _Continued(NamedTuple):
    any: np.ndarray         # (R,) the rows answered
    x: np.ndarray           # their M(0), base frame
    iterations: np.ndarray
    shape: dict | None      # one row answered: its ``_finish`` (numpy)
    jacobian: np.ndarray | None = None  # one row answered: (1, 3, 3) ∂M(L)/∂M(0), base frame


def _continued(robot: Robot, config: StaticsConfig, tension: np.ndarray, loads: CaseLoads,
               near: np.ndarray, dtype: Any, jacobian: np.ndarray | None = None
               ) -> _Continued:
    """Newton under the full loads from M(0) = ``near`` (R, 3), base frame, one round:
    the rows whose answer converged and is stable. One row: from ``jacobian`` (3, 3),
    ∂M(L)/∂M(0) at ``near``'s equilibrium, base frame, where given."""
    rows = len(tension)
    if rows == 1:
        start = np.full((1, 3, 3), np.nan) if jacobian is None else jacobian.reshape(1, 3, 3)
        return _settled(robot, config, _settle_program(robot, config)(
            *_typed((tension, loads, near, start), dtype)))
    solved = _solve_rows(robot, config, tension, loads, near, np.ones(rows),
                         np.tile([0.0, 1.0], (rows, 1)), dtype, further_round=False)
    ok = solved.converged.copy()
    if ok.any():
        good = np.flatnonzero(ok)
        ok[good] = _stable(robot, config, solved.x[good], tension[good],
                           _rows(loads, good), dtype)
    return _Continued(ok, solved.x[ok], solved.iterations[ok], None)


def _settled(robot: Robot, config: StaticsConfig, outputs: Any) -> _Continued:
    """The one-row ``_Continued`` of ``settle_function``'s outputs: answered where Newton
    reached the full loads within the tolerance and the answer is stable."""
    state, margin, shape, tip = outputs
    x, it = np.array(state.x), np.asarray(state.it)
    tol = config.resolved_tolerance() * _layout(robot, config).moment_scale
    ok = ((np.asarray(state.lam) >= 1.0) & (np.linalg.norm(np.asarray(state.r), axis=1)
                                             <= tol) & (np.asarray(margin) > 0.0))
    if not ok[0]:
        return _Continued(ok, x[ok], it[ok], None)
    return _Continued(ok, x, it, {k: np.asarray(v) for k, v in shape.items()},
                      np.asarray(tip, dtype=float))


def _start_jacobian(value: Any, base_rot: np.ndarray) -> np.ndarray | None:
    """``start_jacobian`` (world frame) as (3, 3) in the base frame, checked; None: none."""
    if value is None:
        return None
    j = np.asarray(value, dtype=float)
    if j.size != 9 or not np.all(np.isfinite(j)):
        raise ValueError(f"start_jacobian: expected a finite (3, 3) ∂M(L)/∂M(0), got shape "
                         f"{j.shape}")
    return base_rot.T @ j.reshape(3, 3) @ base_rot


def _start_moments(value: Any, batch: int) -> np.ndarray:
    """``start_moment`` as (B, 3) N·m, checked."""
    m = np.asarray(value, dtype=float)
    if m.shape not in ((3,), (batch, 3)) or not np.all(np.isfinite(m)):
        raise ValueError(f"start_moment: expected (3,) or ({batch}, 3) finite moments, "
                         f"N·m, got shape {m.shape}")
    return np.broadcast_to(m, (batch, 3))


def _case_loads(frame: Any) -> CaseLoads:
    """The programs' loads of a ``StaticLoads``; without a force per metre in any case its
    array is (B, 0), which selects the smaller program."""
    arrays = list(frame.arrays())
    if not np.any(arrays[3]):
        arrays[3] = np.zeros((len(arrays[3]), 0))
    return CaseLoads(*arrays)


def _load_batch(*loads: Any) -> int:
    """The number of cases the loads give (1 when every load is one row)."""
    sizes = [len(v) for v in loads[:4] if v is not None and np.ndim(v) == 2]
    points = loads[4]
    if points is not None and len(points) and not isinstance(points[0], dict):
        sizes.append(len(points))
    return max(sizes, default=1)


def _shapes(robot: Robot, config: StaticsConfig, found: list, tension: np.ndarray,
            loads: CaseLoads, base_rot: np.ndarray, base_pos: np.ndarray,
            dtype: Any) -> list[list[Equilibrium]]:
    """The shapes of every equilibrium found, per case, the reported one first."""
    case = np.array([i for i, entries in enumerate(found) for _ in entries], int)
    flat = [e for entries in found for e in entries]
    x = np.array([e[0] for e in flat]).reshape(-1, 3)
    out = _programs(robot, config)[2](*_typed(_padded((x, tension[case],
                                                         _rows(loads, case))), dtype))
    positions = np.asarray(out["positions"], float)[:len(x)] @ base_rot.T + base_pos
    rotations = np.einsum("ij,bpjk->bpik", base_rot,
                          np.asarray(out["rotations"], float)[:len(x)])
    shapes: list[list[Equilibrium]] = [[] for _ in found]
    for k, (i, (moment, stable, reached)) in enumerate(zip(case, flat, strict=True)):
        shapes[i].append(Equilibrium(positions[k], rotations[k], moment @ base_rot.T,
                                     stable, reached))
    for entries in shapes:
        entries.sort(key=lambda e: not e.reached)
    return shapes
