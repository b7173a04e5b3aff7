"""The Cosserat rod's options in one place, for every command that solves on it
(``statics``; ``ik``, ``plan``, ``follow`` and ``batch`` with ``--model cosserat``): the load
options and the ``--loads`` file, the keys of a ``--cases`` entry, and the check that the
robot has a ``mechanics`` block. Units: N, N·m, m/s², N/m, m."""

from __future__ import annotations

import argparse
import sys

from ._io import UsageError, parse_vector3, point_loads_arg, read_json


def case_keys() -> tuple[str, ...]:
    """The keys of one case of a ``cr-nlp statics --cases`` file: its tensions and the
    loads of a loads file (``model.loads.LOAD_KEYS``)."""
    from ..model.loads import LOAD_KEYS

    return ("tensions", *LOAD_KEYS)


def add_load_options(p: argparse.ArgumentParser, note: str = "--model cosserat: ",
                     gravity_note: str = "") -> None:
    """The load options of every command on the Cosserat rod (``statics``, and ``ik``,
    ``plan``, ``follow``, ``batch`` with ``--model cosserat``), ``note`` before each help
    text, ``gravity_note`` after ``--gravity``'s."""
    p.add_argument("--tip-force", help=f"{note}fx,fy,fz force on the tip, N, world frame")
    p.add_argument("--tip-moment", help=f"{note}mx,my,mz moment on the tip, N·m, world frame")
    p.add_argument("--gravity", help=f"{note}gx,gy,gz gravity, m/s², world frame"
                                     f"{gravity_note}")
    p.add_argument("--distributed-force", help=f"{note}wx,wy,wz force per metre along the "
                                               "backbone, N/m, world frame")
    p.add_argument("--point-load", action="append", metavar="S,FX,FY,FZ[,MX,MY,MZ]",
                   help=f"{note}a wrench at arc length S (m from the base), N and N·m, world "
                        "frame; repeat for more")
    p.add_argument("--loads", metavar="LOADS.json",
                   help=f"{note}the loads as a file, {{\"gravity\": [m/s²], "
                        "\"tip_force\": [N], \"tip_moment\": [N·m], \"distributed_force\": "
                        "[N/m], \"point_loads\": [{\"s\": m, \"force\": [N], \"moment\": "
                        "[N·m]}]} (any of them; not also given as an option)")


def loads_from_args(args: argparse.Namespace, length: float, robot: object = None) -> dict:
    """The load options and the ``--loads`` file as keyword arguments of the tension
    solvers (N, N·m, m/s², N/m), checked against the robot's ``length`` (m). Without a
    gravity given, a ``robot`` fitted to a recording (``mechanics.calibration_gravity``,
    from ``calibrate --model cosserat``) gets that recording's gravity, as ``predict``
    does, and a line on stderr says so.

    Raises:
        UsageError: naming the option, or the file and the key.
    """
    from ..model.loads import LOAD_KEYS, static_loads

    loads = {"tip_force": parse_vector3(args.tip_force, "--tip-force"),
             "tip_moment": parse_vector3(args.tip_moment, "--tip-moment"),
             "gravity": parse_vector3(args.gravity, "--gravity"),
             "distributed_force": parse_vector3(args.distributed_force, "--distributed-force"),
             "point_loads": point_loads_arg(args.point_load)}
    where = "the load options"
    if getattr(args, "loads", None):
        where = f"--loads: {args.loads}"
        data = read_json(args.loads, "--loads")
        if not isinstance(data, dict):
            raise UsageError(f"{where}: expected an object with any of {', '.join(LOAD_KEYS)}")
        for key, value in data.items():
            if key not in LOAD_KEYS:
                raise UsageError(f"{where}: {key}: unknown key (a loads file has "
                                 f"{', '.join(LOAD_KEYS)})")
            if loads[key]:
                raise UsageError(f"{where}: {key} is also given as --{key.replace('_', '-')}")
            loads[key] = value
    if not loads["gravity"]:
        loads["gravity"] = fitted_gravity(robot)
    try:
        static_loads(1, length, **loads)
    except ValueError as exc:
        raise UsageError(f"{where}: {str(exc).removeprefix('case 0: ')}") from None
    return loads


def fitted_gravity(robot: object) -> list[float] | None:
    """The gravity (m/s², world frame) of the recording ``robot`` was fitted to
    (``mechanics.calibration_gravity``, from ``calibrate --model cosserat``), announced on
    stderr; None for a robot without one."""
    fitted = getattr(getattr(robot, "mechanics", None), "calibration_gravity", ())
    if not fitted:
        return None
    gravity = [float(g) for g in fitted]
    print(f"cr-nlp: gravity {gravity} m/s², the recording's that {robot.name} was fitted "
          "to (mechanics.calibration_gravity); --gravity overrides it", file=sys.stderr)
    return gravity


def needs_mechanics(robot: object, option: str = "--model cosserat") -> None:
    """Refuse ``--model cosserat`` for a robot without mechanics (every tension task, ik,
    plan and follow, has its exact stage on the rod: ``--exact`` is not refused)."""
    if getattr(robot, "mechanics", None) is None:
        raise UsageError(f"{option}: {robot.name} has no 'mechanics' block (the rod's "
                         f"stiffness and tension limit); see models/README.md")
