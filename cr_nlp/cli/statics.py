"""``cr-nlp statics``: Cosserat-rod equilibrium shape for tendon tensions and loads."""

from __future__ import annotations

import argparse
import math
from typing import Any

from ._io import UsageError, load_robot_arg, parse_numbers, parse_vector3, read_json, write_json


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Register ``cr-nlp statics`` on the command's subparsers."""
    p = sub.add_parser("statics", help="Cosserat-rod statics: shape from tendon tensions "
                                       "and loads (robot file with a 'mechanics' block)")
    p.add_argument("--robot", required=True, help="robot JSON file or bundled name "
                                                  "(tdcr2_rao2021)")
    p.add_argument("--tensions", help="t1,...,tN tendon tensions in N (robot file's order)")
    p.add_argument("--tip-force", help="fx,fy,fz force on the tip, N, world frame")
    p.add_argument("--tip-moment", help="mx,my,mz moment on the tip, N·m, world frame")
    p.add_argument("--gravity", help="gx,gy,gz gravity, m/s², world frame (default none)")
    p.add_argument("--cases", help='JSON file {"cases": [{"tensions": [...], "tip_force": '
                                   '[...], "tip_moment": [...]}, ...]}; prints a JSON list')
    p.add_argument("--json", action="store_true", help="print JSON (with the backbone)")
    p.set_defaults(run=run)


def _cases_from_file(path: str, n_tendons: int) -> tuple[list, list, list]:
    data = read_json(path, "--cases")
    cases = data.get("cases") if isinstance(data, dict) else None
    if not isinstance(cases, list) or not cases:
        raise UsageError(f"{path}: expected {{\"cases\": [{{\"tensions\": [...]}}, ...]}}")
    tensions, forces, moments = [], [], []
    for i, case in enumerate(cases):
        if not isinstance(case, dict) or "tensions" not in case:
            raise UsageError(f"{path}: cases[{i}]: needs a 'tensions' list")
        unknown = sorted(set(case) - {"tensions", "tip_force", "tip_moment"})
        if unknown:
            raise UsageError(f"{path}: cases[{i}].{unknown[0]}: unknown key")
        t = case["tensions"]
        if not isinstance(t, list) or len(t) != n_tendons:
            raise UsageError(f"{path}: cases[{i}].tensions: expected {n_tendons} numbers")
        tensions.append(_numbers(path, f"cases[{i}].tensions", t, nonnegative=True))
        for key, out in (("tip_force", forces), ("tip_moment", moments)):
            value = case.get(key, [0.0, 0.0, 0.0])
            if not isinstance(value, list) or len(value) != 3:
                raise UsageError(f"{path}: cases[{i}].{key}: expected 3 numbers")
            out.append(_numbers(path, f"cases[{i}].{key}", value))
    return tensions, forces, moments


def _numbers(path: str, field: str, values: list, nonnegative: bool = False) -> list[float]:
    """Finite floats (≥ 0 with ``nonnegative``: tensions pull) of a cases file's list."""
    out = []
    for j, value in enumerate(values):
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise UsageError(f"{path}: {field}[{j}]: expected a number, got {value!r:.40}")
        try:
            x = float(value)
        except OverflowError:  # an integer past float's range
            x = math.inf
        if not math.isfinite(x):
            raise UsageError(f"{path}: {field}[{j}]: must be finite, got {value!r:.40}")
        if nonnegative and x < 0:
            raise UsageError(f"{path}: {field}[{j}]: a tension must not be negative (a "
                             f"tendon pulls), got {value!r}")
        out.append(x)
    return out


def run(args: argparse.Namespace) -> int:
    """Solve and print the tip pose and convergence (text), or JSON with ``--json`` or
    ``--cases``."""
    from ..model.cosserat import solve_statics

    robot = load_robot_arg(args.robot)
    if robot.mechanics is None:
        raise UsageError(f"--robot: {robot.name} has no 'mechanics' block (see "
                         "models/README.md)")
    if (args.cases is None) == (args.tensions is None):
        raise UsageError("give either --tensions or --cases")
    gravity = parse_vector3(args.gravity, "--gravity")
    if args.cases is not None:
        tensions, forces, moments = _cases_from_file(args.cases, robot.n_tendons)
    else:
        tensions = [parse_numbers(args.tensions, "--tensions")]
        if len(tensions[0]) != robot.n_tendons:
            raise UsageError(f"--tensions: {robot.name} has {robot.n_tendons} tendons, got "
                             f"{len(tensions[0])} numbers")
        forces = [parse_vector3(args.tip_force, "--tip-force") or [0.0, 0.0, 0.0]]
        moments = [parse_vector3(args.tip_moment, "--tip-moment") or [0.0, 0.0, 0.0]]
    try:
        result = solve_statics(robot, tensions, forces, moments, gravity)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    records: list[dict[str, Any]] = []
    for i in range(len(tensions)):
        records.append({
            "position": result.tip_position[i].tolist(),
            "wxyz": result.tip_wxyz[i].tolist(),
            "converged": bool(result.converged[i]),
            "residual": float(result.residual[i]),
            "tendon_displacements": result.tendon_displacements[i].tolist(),
            "backbone": result.positions[i].tolist(),
        })
    if args.cases is not None:
        write_json(records, None)
        return 0
    rec = records[0]
    if args.json:
        write_json(rec, None)
        return 0
    print(f"robot          {robot.name} (Cosserat rod, {robot.n_tendons} tendons)")
    print("tip position   [{:.9f}, {:.9f}, {:.9f}] m".format(*rec["position"]))
    print("tip wxyz       [{:.9f}, {:.9f}, {:.9f}, {:.9f}]".format(*rec["wxyz"]))
    print(f"converged      {rec['converged']} (boundary residual {rec['residual']:.2e} N·m)")
    disp = ", ".join(f"{v:.9f}" for v in rec["tendon_displacements"])
    print(f"displacements  [{disp}] m")
    return 0 if rec["converged"] else 1
