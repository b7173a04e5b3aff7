"""Measured data of a real robot: commanded tendon displacements and measured tip positions.

A CSV file with a header row. The command columns (``tendon_1 … tendon_N`` by default,
in the robot file's tendon order) hold the commanded displacements, positive = pulled;
the tip columns (``tip_x, tip_y, tip_z`` by default) the measured tip position in the
measurement frame. ``units`` ("m" or "mm") applies to both; other columns are ignored.
Every problem raises one ``DataFileError`` naming the file, the column and the row.
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..._files import atomic_open

UNITS = {"m": 1.0, "mm": 1e-3}
"""Length units a data file may use, with their size in metres."""


class DataFileError(ValueError):
    """A measurement file that cannot be used; the message names file, column and row."""


@dataclass(frozen=True)
class Measurements:
    """Rows of a measurement file, in metres."""

    commands: np.ndarray
    """(N, n_tendons) commanded tendon displacements, m (positive = pulled)."""
    tip: np.ndarray | None
    """(N, 3) measured tip positions in the measurement frame, m (None: not read)."""
    source: str = ""
    """The file the rows came from."""
    times: np.ndarray | None = None
    """(N,) the rows' times, s, non-decreasing (None: no time column was read; the file's
    order is then the time order)."""

    def __len__(self) -> int:
        return len(self.commands)


def default_tendon_columns(n_tendons: int) -> list[str]:
    """``tendon_1 … tendon_N``."""
    return [f"tendon_{i + 1}" for i in range(n_tendons)]


DEFAULT_TIP_COLUMNS = ("tip_x", "tip_y", "tip_z")


def read_measurements(path: str | Path, n_tendons: int, *,
                      tendon_columns: list[str] | None = None,
                      tip_columns: list[str] | tuple[str, ...] | None = DEFAULT_TIP_COLUMNS,
                      units: str = "m", require_tip: bool = True,
                      time_column: str | None = None) -> Measurements:
    """Read a measurement CSV (see the module docstring) into metres.

    Args:
        path: the CSV file.
        n_tendons: the robot's tendon count; ``tendon_columns`` must name that many.
        tendon_columns: command columns in the robot file's tendon order (default
            ``tendon_1 … tendon_N``).
        tip_columns: the three measured-tip columns, or None to read commands only.
        units: "m" or "mm", for commands and tips alike.
        time_column: a column of times (s) to read where the file has it; the rows must
            be in time order (the history-aware model runs through them in that order).

    Raises:
        DataFileError: missing file or column, wrong tendon count, an empty file, a cell
            that is not a finite number (naming file, column and data row, 1-based), a
            time earlier than the row before.
    """
    source = str(path)
    if units not in UNITS:
        raise DataFileError(f"{source}: units must be one of {sorted(UNITS)}, got {units!r}")
    columns = list(tendon_columns) if tendon_columns is not None else \
        default_tendon_columns(n_tendons)
    if len(columns) != n_tendons:
        raise DataFileError(f"{source}: {len(columns)} tendon columns given "
                            f"({', '.join(columns)}), the robot has {n_tendons} tendons")
    tips = list(tip_columns) if tip_columns is not None else []
    if tip_columns is not None and len(tips) != 3:
        raise DataFileError(f"{source}: the tip needs 3 columns (x, y, z), got {tips}")
    try:
        with open(path, newline="") as handle:
            rows = list(csv.reader(handle))
    except FileNotFoundError:
        raise DataFileError(f"{source}: file not found") from None
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise DataFileError(f"{source}: cannot read: {exc}") from None
    if not rows:
        raise DataFileError(f"{source}: the file is empty (a header row is needed)")
    header = [h.strip() for h in rows[0]]
    index = {name: i for i, name in enumerate(header)}
    if not require_tip and not any(name in index for name in tips):
        tips = []
    for name in columns + tips:
        if name not in index:
            kind = "tip" if name in tips else "tendon"
            raise DataFileError(f"{source}: {kind} column {name!r} not found "
                                f"(columns: {', '.join(header)})")
    body = [(k + 1, r) for k, r in enumerate(rows[1:]) if any(cell.strip() for cell in r)]
    if not body:
        raise DataFileError(f"{source}: no data rows after the header")
    clock = [time_column] if time_column and time_column in index else []
    wanted = columns + tips + clock
    values = np.empty((len(body), len(wanted)))
    for out, (row_number, row) in enumerate(body):
        if len(row) != len(header):
            raise DataFileError(f"{source}: row {row_number} has {len(row)} cells, the "
                                f"header has {len(header)}")
        for k, name in enumerate(wanted):
            cell = row[index[name]].strip()
            try:
                x = float(cell)
            except ValueError:
                raise DataFileError(f"{source}: column {name!r}, row {row_number}: not a "
                                    f"number: {cell!r}") from None
            if not math.isfinite(x):
                raise DataFileError(f"{source}: column {name!r}, row {row_number}: "
                                    f"{cell!r} is not a finite number")
            values[out, k] = x
    times = _in_time_order(values[:, -1], [k for k, _ in body], source, clock[0]) \
        if clock else None
    values = values[:, :len(columns) + len(tips)] * UNITS[units]
    commands = values[:, :n_tendons]
    tip = values[:, n_tendons:] if tips else None
    return Measurements(commands, tip, source, times)


def _in_time_order(times: np.ndarray, row_numbers: list[int], source: str,
                   column: str) -> np.ndarray:
    """``times`` (s), after checking that no row is earlier than the one before."""
    late = np.flatnonzero(np.diff(times) < 0)
    if late.size:
        raise DataFileError(f"{source}: column {column!r}, row {row_numbers[late[0] + 1]}: "
                            f"earlier than the row before (rows must be in time order)")
    return times.copy()


def read_labels(path: str | Path, column: str) -> np.ndarray | None:
    """(N,) the text of ``column`` in each data row of a measurement CSV (rows as
    ``read_measurements`` reads them), None when the file has no such column."""
    with open(path, newline="") as handle:
        rows = list(csv.reader(handle))
    header = [h.strip() for h in rows[0]] if rows else []
    if column not in header:
        return None
    k = header.index(column)
    return np.array([r[k].strip() for r in rows[1:] if any(cell.strip() for cell in r)])


def write_tip_csv(path: str | Path, tip: np.ndarray, units: str = "m",
                  columns: tuple[str, ...] | list[str] = DEFAULT_TIP_COLUMNS,
                  extra: dict[str, np.ndarray] | None = None) -> None:
    """Write tip positions (N, 3) m as a CSV in ``units`` with a header of ``columns``,
    preceded by the ``extra`` columns (name → (N,) values, written as they are)."""
    scale = 1.0 / UNITS[units]
    extra = extra or {}
    with atomic_open(path, newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(list(extra) + list(columns))
        cols = [np.asarray(v) for v in extra.values()]
        for i, row in enumerate(np.asarray(tip) * scale):
            writer.writerow([repr(float(c[i])) for c in cols] + [repr(float(v)) for v in row])
