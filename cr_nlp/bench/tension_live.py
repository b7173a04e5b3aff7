"""Benchmark: live tension IK, the viewer's dragged target under load (issue 51's 5 ms).

``cr-nlp bench tension --suite live`` on ``tdcr2_rao2021`` under gravity and a 5 g tip
payload: a drag of ``waypoints`` updates whose targets are the tips of a smooth, clear,
rate-feasible tension motion (``tension_clutter.clear_motions``), solved one at a time by
``TensionLiveIKSolver`` from the previous answer's tensions, as ``cr-nlp view`` does. One row
without a scene and one in the clutter scene of ``tension_clutter.clutter_scene``. Every
update is judged by the solver's verdict (fresh statics, the tension bounds, python-fcl).

The first drag compiles and is timed apart; the figures per update are medians and 90th
percentiles over ``repeats`` later drags, with the medians of each answer's own
``timing``: the warm-started LM with the verdict's fresh statics (``refine``: one program
where the last equilibrium is known), the rest of the verdict (python-fcl, bounds;
``verify``) and the pool's fallback where the warm start missed (``explore``). Units: ms.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np

from ..model import load_robot
from ..model.cosserat import solve_statics
from ._common import Column, environment, environment_markdown, fixed, markdown_table, write_report
from .tension_clutter import RATE_MAX, clear_motions, clutter_scene
from .tension_motion import GRAVITY, PAYLOAD


def drag(live: Any, motion: np.ndarray, tips: np.ndarray) -> tuple[list[Any], np.ndarray]:
    """One drag: each tip solved from the previous answer's tensions (the first from
    ``motion[0]``); the answers and each update's wall seconds."""
    current, answers, seconds = motion[0], [], []
    for tip in tips[1:]:
        start = time.perf_counter()
        answer = live.solve(current, tip)
        seconds.append(time.perf_counter() - start)
        answers.append(answer)
        current = answer.tensions
    return answers, np.array(seconds)


def bench_drag(robot: Any, scene: dict | None, motion: np.ndarray,
               repeats: int) -> dict[str, Any]:
    """The row of one scene: ``repeats`` timed drags after a first one that compiles."""
    from ..tasks.mechanics.live_ik import TensionLiveIKSolver

    tips = solve_statics(robot, motion, PAYLOAD, None, GRAVITY).tip_position
    start = time.perf_counter()
    live = TensionLiveIKSolver(robot, scene, gravity=GRAVITY, tip_force=PAYLOAD)
    answers, _ = drag(live, motion, tips)
    first = time.perf_counter() - start
    timed = [drag(live, motion, tips) for _ in range(repeats)]
    times = np.concatenate([seconds for _, seconds in timed])
    later = [a for answered, _ in timed for a in answered]

    def median_ms(stage: str) -> float:
        return 1e3 * float(np.median([a.timing[stage] for a in later]))

    return {
        "scene": "clutter" if scene else "none", "updates": len(tips) - 1,
        "verified": sum(a.success for a in answers),
        "warm": sum(a.stage.value == "refine" for a in answers),
        "max_error_mm": 1e3 * max(a.position_error for a in answers),
        "min_clearance_mm": 1e3 * min(a.min_clearance for a in answers),
        "median_ms": 1e3 * float(np.median(times)),
        "p90_ms": 1e3 * float(np.percentile(times, 90)),
        "refine_ms": median_ms("refine"), "verify_ms": median_ms("verify"),
        "explore_ms": median_ms("explore"), "first_s": first}


COLUMNS = [
    Column("scene", "scene"), Column("updates", "updates"), Column("verified", "verified"),
    Column("warm", "warm-started"), Column("max_error_mm", "max error (mm)", fixed(4)),
    Column("min_clearance_mm", "min clearance (mm)", fixed(1)),
    Column("median_ms", "median ms per update", fixed(2)),
    Column("p90_ms", "90th pct (ms)", fixed(2)),
    Column("refine_ms", "LM + statics (ms)", fixed(2)),
    Column("verify_ms", "fcl, bounds (ms)", fixed(2)),
    Column("explore_ms", "pool fallback (ms)", fixed(2)),
    Column("first_s", "first drag (s)", fixed(1)),
]


def run_tension_live_benchmark(robot: str = "tdcr2_rao2021", waypoints: int = 60,
                               repeats: int = 3, seed: int = 0, rate_fraction: float = 0.7,
                               out: str | Path | None = None) -> list[dict[str, Any]]:
    """Both rows (no scene, clutter), printed and written to ``out``."""
    from ..tasks.mechanics.follow import TensionFollowConfig, TensionPathFollower

    rob = load_robot(robot)
    scene = clutter_scene(rob, seed)
    follower = TensionPathFollower(rob, scene, TensionFollowConfig(tension_rate_max=RATE_MAX))
    motions = clear_motions(follower, 1, waypoints, rate_fraction, np.random.default_rng(seed))
    if not motions:
        raise RuntimeError(f"no clear, rate-feasible motion of {waypoints} waypoints found "
                           f"in the clutter scene of seed {seed}; try another --seed")
    rows = [bench_drag(rob, s, motions[0], repeats) for s in (None, scene)]
    env = environment()
    report = (f"## Live tension IK under load, {robot}\n\n"
              f"Gravity and a 5 g tip payload; a drag of {waypoints - 1} updates along the "
              f"tips of a clear tension motion (rate ≤ {rate_fraction:g} of {RATE_MAX:g} "
              f"N/s, {len(scene['obstacles'])} obstacles, seed {seed}), each solved from "
              "the previous answer's tensions and judged by the verdict (fresh statics, "
              f"python-fcl); per update: medians over {repeats} drags after the first, "
              "with the medians of each answer's LM (with the verdict's statics: one "
              "program) and the rest of its verdict.\n\n"
              + markdown_table(rows, COLUMNS) + "\n\n" + environment_markdown(env))
    write_report("tension_live", report, out, tables={"live": rows}, env=env,
                 settings={"robot": robot, "waypoints": waypoints, "repeats": repeats,
                           "seed": seed, "rate_fraction": rate_fraction})
    return rows
