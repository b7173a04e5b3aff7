"""``cr-nlp bench tension --suite live``: the drag's row counts what the solver's verdict
says and splits each update into the LM and the verdict."""

from __future__ import annotations

import numpy as np

from cr_nlp.bench.tension_live import bench_drag
from cr_nlp.model import load_robot
from cr_nlp.model.cosserat import solve_statics
from cr_nlp.tasks.mechanics.live_ik import TensionLiveIKSolver

RAO = load_robot("tdcr2_rao2021")
GRAVITY = [0.0, 0.0, -9.81]
PAYLOAD = [0.0, 0.0, -0.005 * 9.81]


def test_a_drag_row_reports_the_verdicts_and_the_split() -> None:
    t = np.linspace(0.0, 1.0, 5)[:, None]
    motion = np.concatenate([1 + 2 * t, 0 * t, 0.5 * t, 1 - t, t, 0 * t], axis=1)
    row = bench_drag(RAO, None, motion, repeats=1)
    assert row["scene"] == "none" and row["updates"] == 4
    # The same drag solved here: the row counts what the verdict says of each update.
    live = TensionLiveIKSolver(RAO, None, gravity=GRAVITY, tip_force=PAYLOAD)
    tips = solve_statics(RAO, motion, PAYLOAD, None, GRAVITY).tip_position
    current, verified = motion[0], 0
    for tip in tips[1:]:
        answer = live.solve(current, tip)
        verified += answer.success
        assert 0.0 < answer.timing.refine + answer.timing.verify <= answer.seconds
        current = answer.tensions
    assert row["verified"] == verified == 4
    assert row["max_error_mm"] < 0.1 and row["min_clearance_mm"] == np.inf
    assert row["refine_ms"] > 0.0 and row["verify_ms"] > 0.0 and row["explore_ms"] == 0.0
    assert row["median_ms"] <= row["p90_ms"]
