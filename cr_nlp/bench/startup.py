"""``cr-nlp bench startup``: how long a user waits for a first answer, as whole processes.

Each entry point runs as a new Python process that calls the ``cr-nlp`` command's own
``main`` (what ``cr-nlp ik …`` runs) twice: the first call is what a user's one-shot
command costs, the second (same process, programs compiled) the steady state. An entry
runs ``cold`` (an empty cache folder: JAX's compiled code, cr_nlp's traced programs,
roadmaps and seed pools all start empty, as for a robot or scene never seen) and then
``warm`` (a second process on the cache the first one filled, once the background
process that optimises the cold run's quickly compiled programs is done:
``cr_nlp._compile_effort``; the cold process's steady call runs that quick code).

Per process the table splits the wall time into: the interpreter start and imports;
tracing and lowering (JAX's own trace and MLIR times plus cr_nlp's export of its
programs); XLA (compiling, or loading compiled code from JAX's cache); the rest of the
first call; and the steady call. ``import`` is ``import cr_nlp`` alone.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from .._compile_effort import wait_for_upgrade
from .._files import write_atomic
from ._common import Column, environment, environment_markdown, fixed, markdown_table, write_report
from .suites import STARTUP_ENTRIES

IK_TARGETS = 1000
"""Targets of the ``ik`` entry (tdcr3, free; the README's one-shot IK)."""
PLAN_PROBLEMS = 20
"""Problems of the ``plan`` entry (tdcr3 in the shelf)."""
STATICS_CASES = 64
"""Tension cases of the ``statics`` entry (tdcr2_rao2021)."""
NEW_ROBOT = {
    "name": "startup_new3",
    "description": "Not bundled (cr-nlp bench startup writes it): a 3-segment robot with "
                   "tdcr3's layout and other lengths and radii.",
    "segments": [{"length": 0.9, "theta_max": 3.0}, {"length": 1.1, "theta_max": 3.0},
                 {"length": 0.8, "theta_max": 3.0}],
    "backbone_radius": 0.08, "points_per_segment": 10,
    "tendons": {"per_segment": 3, "radius": 0.065, "offsets": [0.0, 0.3, 0.6],
                "routing": "per_segment"},
    "base": {"position": [0.0, 0.0, 0.0], "wxyz": [1.0, 0.0, 0.0, 0.0]},
    "tendon_speed_max": 0.2, "tendon_accel_max": 1.0,
}
"""The robot of the ``ik-new`` and ``plan-new`` entries: a robot file no process has seen
(start-up on a user's own robot, where nothing of tdcr3's is reused)."""

def entry_argv(entry: str, inputs: Path, out: Path) -> list[str] | None:
    """The ``cr-nlp`` arguments of an entry (None: ``import``) on the inputs in ``inputs``
    (``write_inputs``), writing to ``out``."""
    return {
        "import": None,
        "ik": ["ik", "--robot", "tdcr3", "--targets", str(inputs / "targets.json"),
               "--out", str(out / "ik.json")],
        "plan": ["plan", "--robot", "tdcr3", "--scene", "shelf", "--problems",
                 str(inputs / "problems.json"), "--out", str(out / "plan.json")],
        "follow": ["follow", "--robot", "tdcr3", "--scene", "follow_icra", "--path", "icra",
                   "--out", str(out / "follow.json")],
        "statics": ["statics", "--robot", "tdcr2_rao2021", "--cases",
                    str(inputs / "statics.json")],
        "calibrate": ["calibrate", "--robot", "ftdcr_v6", "--data", "ftdcr_v6_train",
                      "--validate", "ftdcr_v6_val", "--out", str(out / "calibrated.json")],
        "predict": ["predict", "--robot", "ftdcr_v6_calibrated", "--data", "ftdcr_v6_val",
                    "--out", str(out / "predicted.csv")],
        "demo": ["demo", "--out", str(out / "demo")],
        "ik-new": ["ik", "--robot", str(inputs / "new_robot.json"), "--targets",
                   str(inputs / "targets_new.json"), "--out", str(out / "ik.json")],
        "plan-new": ["plan", "--robot", str(inputs / "new_robot.json"), "--scene", "shelf",
                     "--problems", str(inputs / "problems_new.json"),
                     "--out", str(out / "plan.json")],
    }[entry]


def write_inputs(folder: Path, entries: Sequence[str] = STARTUP_ENTRIES, seed: int = 0) -> None:
    """The input files of ``entries``: 1000 IK targets, 20 planning problems in the
    shelf (for tdcr3 and, for the ``-new`` entries, for ``NEW_ROBOT``, whose file is
    written there too), 64 statics cases (seeded: every run times the same work)."""
    from ..model import load_robot

    folder.mkdir(parents=True, exist_ok=True)
    robot = load_robot("tdcr3")
    if "ik" in entries:
        _write_targets(folder / "targets.json", robot, seed)
    if "plan" in entries:
        _write_problems(folder / "problems.json", robot, seed)
    if "ik-new" in entries or "plan-new" in entries:
        write_atomic(folder / "new_robot.json", json.dumps(NEW_ROBOT, indent=1).encode())
        new = load_robot(folder / "new_robot.json")
        if "ik-new" in entries:
            _write_targets(folder / "targets_new.json", new, seed)
        if "plan-new" in entries:
            _write_problems(folder / "problems_new.json", new, seed)
    if "statics" in entries:
        _write_statics(folder, seed)


def _write_targets(path: Path, robot: Any, seed: int) -> None:
    from .ik import free_case

    case = free_case(robot, IK_TARGETS, seed)
    poses = [{"position": p.tolist(), "wxyz": w.tolist()}
             for p, w in zip(case.positions, case.wxyz, strict=True)]
    write_atomic(path, json.dumps({"poses": poses}).encode())


def _write_problems(path: Path, robot: Any, seed: int) -> None:
    from ..tasks.geometry.ik import IKConfig
    from ..world import load_scene
    from .plan import plan_problems

    starts, goals = plan_problems(robot, load_scene("shelf"), PLAN_PROBLEMS,
                                  IKConfig.safety_margin, seed)
    problems = [{"start": s.tolist(), "goal": g.tolist()}
                for s, g in zip(starts, goals, strict=True)]
    write_atomic(path, json.dumps({"problems": problems}).encode())


def _write_statics(folder: Path, seed: int) -> None:
    import numpy as np

    from ..model import load_robot

    rod = load_robot("tdcr2_rao2021")
    rng = np.random.default_rng(seed)
    cases = [{"tensions": rng.uniform(0.0, 2.0, rod.n_tendons).tolist()}
             for _ in range(STATICS_CASES)]
    write_atomic(folder / "statics.json", json.dumps({"cases": cases}).encode())


# ---------------------------------------------------------------- the parent

def _process(entry: str, inputs: Path, out: Path, cache: Path, devices: int | None
             ) -> dict[str, Any]:
    # As a user runs it: cr_nlp's own caches, its default compile effort.
    env = {k: v for k, v in os.environ.items()
           if k not in ("CR_NLP_JAX_CACHE", "JAX_COMPILATION_CACHE_DIR", "CR_NLP_COMPILE")}
    env["CR_NLP_CACHE_DIR"] = str(cache)
    env["CR_NLP_STARTUP_T0"] = repr(time.time())
    command = [sys.executable, "-m", "cr_nlp.cli._startup_probe", entry, str(inputs),
               str(out)]
    t0 = time.perf_counter()
    done = subprocess.run(command, env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if done.returncode != 0:
        raise RuntimeError(f"startup probe {entry} failed ({done.returncode}):\n"
                           f"{done.stderr[-3000:]}")
    row = json.loads(done.stdout.strip().splitlines()[-1])
    row["wall"] = wall
    return row


def run_startup_benchmark(entries: Sequence[str] = STARTUP_ENTRIES, repeats: int = 1,
                          out: str | Path | None = None, devices: int | None = None,
                          progress: bool = True) -> list[dict[str, Any]]:
    """Time every entry cold (empty cache) and warm (second process), ``repeats`` times
    each (medians reported); print the table and write ``startup.md``/``startup.csv`` to
    ``out``. Returns the rows."""
    import numpy as np
    from tqdm import tqdm

    rows: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory(prefix="cr_nlp_startup_") as work:
        work = Path(work)
        inputs = work / "inputs"
        write_inputs(inputs, entries)
        runs = [(e, r) for e in entries for r in range(repeats)]
        samples: dict[tuple[str, str], list[dict[str, Any]]] = {}
        for entry, r in tqdm(runs, desc="startup", disable=not progress):
            cache = work / f"cache-{entry}-{r}"
            for state in ("cold", "warm"):
                if state == "warm":  # the optimised code every later process gets
                    wait_for_upgrade(cache / "programs")
                row = _process(entry, inputs, work / "out", cache, devices)
                samples.setdefault((entry, state), []).append(row)
        for (entry, state), found in samples.items():
            keys = sorted({k for row in found for k in row if k != "status"})
            row = {"entry": entry, "cache": state}
            for k in keys:
                values = [r[k] for r in found if isinstance(r.get(k), int | float)]
                row[k] = float(np.median(values)) if values else None
            if row.get("steady"):
                row["first_over_steady"] = row["first"] / row["steady"]
            rows.append(row)
    env = environment()
    report = format_report(rows, env, repeats)
    write_report("startup", report, out, tables={"startup": rows}, env=env,
                 settings={"entries": list(entries), "repeats": repeats})
    return rows


COLUMNS = [
    Column("entry", "entry"), Column("cache", "cache"),
    Column("first_answer", "to first answer (s)", fixed(1)),
    Column("start", "interpreter (s)", fixed(2)),
    Column("import", "import (s)", fixed(2)),
    Column("trace", "trace + lower (s)", fixed(2)),
    Column("xla", "XLA compile / load (s)", fixed(2)),
    Column("first_solve", "first call, rest (s)", fixed(2)),
    Column("steady", "steady call (s)", fixed(2)),
    Column("first_over_steady", "first / steady", fixed(1)),
]


SUMMARY = [
    Column("entry", "entry point"),
    Column("cold", "cold: to first answer (s)", fixed(1)),
    Column("warm", "warm: to first answer (s)", fixed(1)),
    Column("warm_parts", "warm: interpreter + import / trace / XLA / first call (s)"),
    Column("steady", "steady call (s)", fixed(2)),
]


def summary_rows(rows: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """One row per entry: cold and warm time to the first answer, the warm split."""
    out = []
    for entry in dict.fromkeys(r["entry"] for r in rows):
        cold = next((r for r in rows if r["entry"] == entry and r["cache"] == "cold"), {})
        warm = next((r for r in rows if r["entry"] == entry and r["cache"] == "warm"), {})

        def part(key: str, row: dict = warm) -> str:
            value = row.get(key)
            return "—" if value is None else f"{value:.1f}"

        started = (warm.get("start") or 0.0) + (warm.get("import") or 0.0)
        out.append({"entry": entry, "cold": cold.get("first_answer"),
                    "warm": warm.get("first_answer"),
                    "warm_parts": f"{started:.1f} / {part('trace')} / {part('xla')} / "
                                  f"{part('first_solve')}",
                    "steady": warm.get("steady")})
    return out


def format_report(rows: Sequence[dict[str, Any]], env: dict[str, str], repeats: int) -> str:
    """The Markdown report: the summary, the full table and how it was measured."""
    return "\n".join([
        "## Start-up summary",
        "",
        markdown_table(summary_rows(rows), SUMMARY),
        "",
        "## Start-up: whole processes, cold (empty cache) and warm (second process)",
        "",
        f"Median of {repeats} run(s) per row. Each process calls the `cr-nlp` command's "
        "`main` twice: 'to first answer' is the wall time from spawning the process to the "
        "end of the first call (a user's one-shot command), split into the interpreter "
        "start, imports, tracing and lowering, XLA (compiling, or loading from JAX's "
        "cache) and the rest of the first call; 'steady call' is the second call. "
        "Tracing and XLA seconds are summed over threads: where programs compile side by "
        "side (`compile_ahead`), they exceed the wall time they took and the rest comes "
        "out negative. ik: "
        f"{IK_TARGETS} free tdcr3 targets; plan: {PLAN_PROBLEMS} problems in the shelf; "
        "follow: ICRA; statics: "
        f"{STATICS_CASES} tension cases on tdcr2_rao2021; calibrate: FTDCR v6 training "
        "file; predict: its validation file; demo: the three demo tasks; ik-new and "
        "plan-new: the same jobs on a 3-segment robot file that is not bundled "
        "(tdcr3's layout, other lengths and radii: nothing compiled for tdcr3 serves "
        "it).",
        "",
        markdown_table(rows, COLUMNS),
        "",
        environment_markdown(env),
    ])

