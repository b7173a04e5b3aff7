"""``cr-nlp statics``: Cosserat-rod equilibrium shape for tendon tensions (or commanded
displacements) and loads."""

from __future__ import annotations

import argparse
import math
from typing import Any, NamedTuple

from ._io import UsageError, load_robot_arg, parse_numbers, parse_vector3, read_json, write_json
from ._loads import (
    add_load_options,
    case_keys,
    fitted_gravity,
    loads_from_args,
    needs_mechanics,
)


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Register ``cr-nlp statics`` on the command's subparsers."""
    p = sub.add_parser(
        "statics", help="Cosserat-rod statics: shape from tendon tensions and loads (robot "
                        "file with a 'mechanics' block); the equilibrium reached by loading "
                        "the robot from rest, whether it is stable, how many were found",
        description="The answer is the equilibrium a robot reaches when its tensions and "
                    "loads grow together from zero; 'stable' says whether it is a minimum of "
                    "the energy, 'equilibria' how many distinct equilibria were found for "
                    "the same loads (other starts are tried where the direct solve's answer "
                    "is doubtful: unstable, unconverged, or past a buckling load with a slow "
                    "continuation), 'snap_load' the load factor of a snap-through on the way.")
    p.add_argument("--robot", required=True, help="robot JSON file or bundled name "
                                                  "(tdcr2_rao2021)")
    p.add_argument("--tensions", help="t1,...,tN tendon tensions in N (robot file's order)")
    p.add_argument("--displacements",
                   help="d1,...,dN commanded tendon displacements in m (robot file's order, "
                        "positive = pulled; its actuation gains and zero offsets apply): "
                        "the tensions are found from the tendons' stiffness (the mechanics "
                        "block's tendon_stiffness, e.g. from calibrate --model cosserat), a "
                        "slack tendon carries none")
    add_load_options(p, note="", gravity_note=" (default none, or a fitted robot's "
                                              "mechanics.calibration_gravity; with --cases: "
                                              "for the cases without their own)")
    p.add_argument("--cases", help='JSON file {"cases": [{"tensions": [...], "tip_force": '
                                   '[...], "tip_moment": [...], "gravity": [...], '
                                   '"distributed_force": [...], "point_loads": [{"s": m, '
                                   '"force": [...], "moment": [...]}]}, ...]}; prints a JSON '
                                   'list')
    p.add_argument("--all-equilibria", action="store_true",
                   help="solve from several starts and list every equilibrium found "
                        "(JSON: 'all_equilibria')")
    p.add_argument("--json", action="store_true", help="print JSON (with the backbone)")
    p.set_defaults(run=run)


class StaticsCases(NamedTuple):
    """The cases of a ``--cases`` file (or of the command line), one entry per case."""

    tensions: list
    tip_force: list
    tip_moment: list
    gravity: list          # None where the case gives none (the --gravity default)
    distributed_force: list
    point_loads: list      # lists of {"s", "force", "moment"}


def _cases_from_file(path: str, n_tendons: int, length: float = math.inf) -> StaticsCases:
    """Read and check a cases file; every error names the case and the key."""
    from ..model.loads import parse_point_loads

    data = read_json(path, "--cases")
    cases = data.get("cases") if isinstance(data, dict) else None
    if not isinstance(cases, list) or not cases:
        raise UsageError(f"{path}: expected {{\"cases\": [{{\"tensions\": [...]}}, ...]}}")
    out = StaticsCases([], [], [], [], [], [])
    for i, case in enumerate(cases):
        if not isinstance(case, dict) or "tensions" not in case:
            raise UsageError(f"{path}: cases[{i}]: needs a 'tensions' list")
        unknown = sorted(set(case) - set(case_keys()))
        if unknown:
            raise UsageError(f"{path}: cases[{i}].{unknown[0]}: unknown key (a case has "
                             f"{', '.join(case_keys())})")
        t = case["tensions"]
        if not isinstance(t, list) or len(t) != n_tendons:
            raise UsageError(f"{path}: cases[{i}].tensions: expected {n_tendons} numbers")
        out.tensions.append(_numbers(path, f"cases[{i}].tensions", t, nonnegative=True))
        for key in ("tip_force", "tip_moment", "gravity", "distributed_force"):
            value = case.get(key)
            if value is None and key == "gravity":
                out.gravity.append(None)
                continue
            value = [0.0, 0.0, 0.0] if value is None else value
            if not isinstance(value, list) or len(value) != 3:
                raise UsageError(f"{path}: cases[{i}].{key}: expected 3 numbers")
            getattr(out, key).append(_numbers(path, f"cases[{i}].{key}", value))
        try:
            loads = parse_point_loads(case.get("point_loads"), length,
                                      f"cases[{i}].point_loads")
        except ValueError as exc:
            raise UsageError(f"{path}: {exc}") from None
        out.point_loads.append([{"s": s, "force": f, "moment": m} for s, f, m in loads])
    return out


def _numbers(path: str, field: str, values: list, nonnegative: bool = False) -> list[float]:
    """Finite floats (≥ 0 with ``nonnegative``: tensions pull) of a cases file's list."""
    from ..model.loads import finite_number

    out = []
    for j, value in enumerate(values):
        try:
            x = finite_number(value, f"{field}[{j}]")
        except ValueError as exc:
            raise UsageError(f"{path}: {exc}") from None
        if nonnegative and x < 0:
            raise UsageError(f"{path}: {field}[{j}]: a tension must not be negative (a "
                             f"tendon pulls), got {value!r}")
        out.append(x)
    return out


def _record(result: Any, i: int, every: bool) -> dict[str, Any]:
    snap = float(result.snap_load[i])
    record: dict[str, Any] = {
        "position": result.tip_position[i].tolist(),
        "wxyz": result.tip_wxyz[i].tolist(),
        "converged": bool(result.converged[i]),
        "residual": float(result.residual[i]),
        "stable": bool(result.stable[i]),
        "equilibria": int(result.equilibria[i]),
        "snap_load": None if math.isnan(snap) else snap,
        "tendon_displacements": result.tendon_displacements[i].tolist(),
        **({"tensions": result.tensions[i].tolist(), "slack": result.slack[i].tolist()}
           if hasattr(result, "slack") else {}),
        "backbone": result.positions[i].tolist(),
    }
    if every:
        record["all_equilibria"] = [
            {"position": e.tip_position.tolist(), "stable": e.stable, "reached": e.reached,
             "backbone": e.positions.tolist()} for e in result.all_equilibria[i]]
    return record


def run(args: argparse.Namespace) -> int:
    """Solve and print the tip pose and convergence (text), or JSON with ``--json`` or
    ``--cases``."""
    from ..model.cosserat import solve_displacement_statics, solve_statics

    robot = load_robot_arg(args.robot)
    needs_mechanics(robot, "--robot")
    given = [o for o, v in (("--tensions", args.tensions), ("--displacements",
                                                              args.displacements),
                             ("--cases", args.cases)) if v is not None]
    if len(given) != 1:
        raise UsageError("give one of --tensions, --displacements or --cases"
                         + (f", not {' and '.join(given)}" if given else ""))
    length = sum(seg.length_min for seg in robot.segments)
    if args.cases is not None:
        if args.point_load or args.distributed_force or args.loads:
            raise UsageError("--point-load, --distributed-force and --loads go with "
                             "--tensions; in a --cases file give them per case")
        cases = _cases_from_file(args.cases, robot.n_tendons, length)
        gravity = (parse_vector3(args.gravity, "--gravity") or fitted_gravity(robot)
                   or [0.0, 0.0, 0.0])
    else:
        option = "--tensions" if args.tensions is not None else "--displacements"
        tensions = parse_numbers(args.tensions or args.displacements, option)
        if len(tensions) != robot.n_tendons:
            raise UsageError(f"{option}: {robot.name} has {robot.n_tendons} tendons, got "
                             f"{len(tensions)} numbers")
        loads = loads_from_args(args, length, robot)
        gravity = loads["gravity"] or [0.0, 0.0, 0.0]
        cases = StaticsCases([tensions], [loads["tip_force"] or [0.0, 0.0, 0.0]],
                             [loads["tip_moment"] or [0.0, 0.0, 0.0]], [None],
                             [loads["distributed_force"] or [0.0] * 3], [loads["point_loads"]])
    case_loads = {"tip_force": cases.tip_force, "tip_moment": cases.tip_moment,
                  "gravity": [gravity if g is None else g for g in cases.gravity],
                  "distributed_force": cases.distributed_force,
                  "point_loads": cases.point_loads}
    try:
        if args.displacements is not None:
            if args.all_equilibria:
                raise UsageError("--all-equilibria goes with --tensions (the displacement "
                                 "statics reports the equilibrium it reaches)")
            result = solve_displacement_statics(robot, cases.tensions, **case_loads)
        else:
            result = solve_statics(robot, cases.tensions, **case_loads,
                                   all_equilibria=args.all_equilibria)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    records = [_record(result, i, args.all_equilibria) for i in range(len(cases.tensions))]
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
    snap = ("" if rec["snap_load"] is None
            else f"; snapped through at {rec['snap_load']:.3f} of the loads")
    print(f"stable         {rec['stable']} ({rec['equilibria']} equilibria found{snap})")
    disp = ", ".join(f"{v:.9f}" for v in rec["tendon_displacements"])
    print(f"displacements  [{disp}] m")
    if "tensions" in rec:
        tensions = ", ".join(f"{v:.6f}" for v in rec["tensions"])
        slack = [k + 1 for k, s in enumerate(rec["slack"]) if s]
        print(f"tensions       [{tensions}] N"
              + (f" (slack: tendon {', '.join(map(str, slack))})" if slack else ""))
    for k, e in enumerate(rec.get("all_equilibria", [])):
        print("equilibrium {}  tip [{:.6f}, {:.6f}, {:.6f}] m, {}{}".format(
            k + 1, *e["position"], "stable" if e["stable"] else "unstable",
            ", reached" if e["reached"] else ""))
    return 0 if rec["converged"] else 1
