"""The measurement-file options shared by ``cr-nlp calibrate`` and ``cr-nlp predict``."""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING

from ._io import UsageError

if TYPE_CHECKING:
    from ..model import Robot
    from ..tasks.measurements import Measurements


def add_data_options(p: argparse.ArgumentParser) -> None:
    """``--tendon-columns``, ``--tip-columns`` and ``--units``."""
    p.add_argument("--tendon-columns",
                   help="command columns in the robot file's tendon order "
                        "(default tendon_1,…,tendon_N)")
    p.add_argument("--tip-columns", default="tip_x,tip_y,tip_z",
                   help="measured tip columns x,y,z (default tip_x,tip_y,tip_z)")
    p.add_argument("--units", choices=["m", "mm"], default="m",
                   help="length unit of commands and tip in the file (default m)")


def read_data_arg(robot: Robot, value: str, args: argparse.Namespace, *,
                  require_tip: bool = True) -> Measurements:
    """The measurements of a ``--data``/``--validate`` value (a CSV file, or a bundled
    recording's name such as ``ftdcr_v6_train``); ``require_tip=False``: a file without
    the tip columns gives commands only."""
    from .._resources import resolve_data_file
    from ..tasks.measurements import DataFileError, read_measurements

    try:
        path = resolve_data_file(value)
    except FileNotFoundError as exc:
        raise UsageError(str(exc)) from None
    columns = (args.tendon_columns.split(",") if args.tendon_columns else None)
    tips = args.tip_columns.split(",")
    try:
        return read_measurements(path, robot.n_tendons, tendon_columns=columns,
                                 tip_columns=tips, units=args.units,
                                 require_tip=require_tip)
    except DataFileError as exc:
        raise UsageError(str(exc)) from None
