"""Measured data of a real robot: commanded tendon displacements and measured tip positions.

A CSV file with a header row. The command columns (``tendon_1 … tendon_N`` by default,
in the robot file's tendon order) hold the commanded displacements, positive = pulled;
the tip columns (``tip_x, tip_y, tip_z`` by default) the measured tip position in the
measurement frame. ``units`` ("m" or "mm") applies to both; other columns are ignored.
Every problem raises one ``DataFileError`` naming the file, the column and the row.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..._files import InputFileError, atomic_open

UNITS = {"m": 1.0, "mm": 1e-3}
"""Length units a data file may use, with their size in metres."""


class DataFileError(InputFileError):
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

from ..._moved import moved_names  # noqa: E402 — the old addresses, for one release (CHANGELOG 2026-12-02)

__getattr__ = moved_names(__name__, {"read_measurements": "cr_nlp.tasks.readers",
                                     "read_labels": "cr_nlp.tasks.readers"})
