"""Figures of a calibration report: tip error histograms and predicted against measured
tip paths (matplotlib, written as PNG)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np

from ..model import Robot
from ..model.actuation import predict_tip
from ..tasks.calibration.measurements import Measurements


def write_report_figures(robot: Robot, train: Measurements, validation: Measurements | None,
                         folder: Path,
                         predict: Callable[[np.ndarray], np.ndarray] | None = None
                         ) -> list[Path]:
    """``errors.png`` (histogram of tip errors, mm) and ``tip_paths.png`` (x, y, z of the
    predicted and measured tip per row, mm) in ``folder``; returns the paths written.
    ``predict``: commands (N, T) m → tips (N, 3) m (default: the geometric model's)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ._figures import write_figure

    sets = [("train", train)] + ([("validation", validation)] if validation else [])
    predict = predict or (lambda commands: predict_tip(robot, commands))
    predicted = {name: predict(d.commands) for name, d in sets}
    errors = {name: 1e3 * np.linalg.norm(predicted[name] - d.tip, axis=1) for name, d in sets}

    fig, ax = plt.subplots(figsize=(6, 3.5))
    top = max(float(np.percentile(e, 99.5)) for e in errors.values())
    bins = np.linspace(0.0, top, 40)
    for name, e in errors.items():
        ax.hist(e, bins=bins, alpha=0.6, density=True,
                label=f"{name}: mean {e.mean():.1f}, p95 {np.percentile(e, 95):.1f} mm")
    ax.set_xlabel("tip error (mm)")
    ax.set_ylabel("density")
    ax.set_title(f"{robot.name}: predicted from commands vs measured")
    ax.legend()
    fig.tight_layout()
    paths = [folder / "errors.png"]
    write_figure(fig, paths[0], dpi=110)
    plt.close(fig)

    fig, axes = plt.subplots(3, len(sets), figsize=(6 * len(sets), 6), sharex="col",
                             squeeze=False)
    for col, (name, d) in enumerate(sets):
        for k, axis in enumerate("xyz"):
            ax = axes[k, col]
            ax.plot(1e3 * d.tip[:, k], color="0.3", lw=1.0, label="measured")
            ax.plot(1e3 * predicted[name][:, k], color="C1", lw=1.0, label="predicted")
            ax.set_ylabel(f"{axis} (mm)")
        axes[0, col].set_title(name)
        axes[-1, col].set_xlabel("row")
    axes[0, 0].legend(loc="best")
    fig.tight_layout()
    paths.append(folder / "tip_paths.png")
    write_figure(fig, paths[1], dpi=110)
    plt.close(fig)
    return paths
