"""Figures and the ``show`` / ``bench clearance`` commands."""

import argparse
from pathlib import Path

import numpy as np
import pytest

from cr_nlp.cli import build_parser
from cr_nlp.model import Robot, tip_pose
from cr_nlp.viz import backbone_frames, draw, save_figure
from cr_nlp.world import load_scene

MODELS = Path(__file__).resolve().parents[2] / "models"


@pytest.fixture(scope="module")
def tdcr3() -> Robot:
    return Robot.from_file(MODELS / "robots" / "tdcr3.json")


def test_backbone_frames_follow_the_model(tdcr3: Robot) -> None:
    q = np.array([0.7, 0.3, 1.0, 1.2, -2.0, 1.0, 0.4, 1.0, 1.0])
    positions, rotations = backbone_frames(tdcr3, q, samples=10)
    tip_position, tip_rotation = (np.asarray(x) for x in tip_pose(tdcr3, q))
    np.testing.assert_allclose(positions[-1], tip_position, atol=1e-9)
    np.testing.assert_allclose(rotations[-1], tip_rotation, atol=1e-9)
    np.testing.assert_allclose(positions[0], 0.0)
    assert positions.shape == (31, 3) and rotations.shape == (31, 3, 3)


def test_draw_scene_trajectory_targets_with_equal_axes(tdcr3: Robot) -> None:
    scene = load_scene("cabinet")
    trajectory = [np.array([0.2 * k, 0.5, 1.0, 0.1 * k, -1.0, 1.0, 0.3, 0.0, 1.0])
                  for k in range(5)]
    target = np.eye(4)
    target[:3, 3] = [1.0, 0.0, 1.5]
    ax = draw(tdcr3, scene=scene, trajectory=trajectory, targets=[target, [0.5, 0.5, 2.0]],
              tendons=True)
    spans = [np.diff(lim)[0] for lim in (ax.get_xlim(), ax.get_ylim(), ax.get_zlim())]
    aspect = np.asarray(ax.get_box_aspect())
    # Equal scaling: the box aspect is proportional to the data spans.
    np.testing.assert_allclose(aspect / aspect[0], np.array(spans) / spans[0], rtol=1e-6)
    assert ax.get_zlim()[1] >= 2.1   # the cabinet's top is in view


def test_save_figure_writes_a_png(tdcr3: Robot, tmp_path: Path) -> None:
    path = save_figure(tdcr3, np.array([0.5, 0.0, 1.0] * 3), load_scene("lattice"),
                       path=tmp_path / "fig" / "lattice.png", show_parts=True)
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def _parser() -> argparse.ArgumentParser:
    return build_parser()


def test_show_command_draws_and_reports_the_verdict(tmp_path: Path,
                                                     capsys: pytest.CaptureFixture) -> None:
    out = tmp_path / "show.png"
    args = _parser().parse_args(["show", "--robot", "tdcr3", "--scene", "shelf",
                                 "--q", "0.652,-1.199,2.774,1.277,2.346,-0.764", "--out", str(out)])
    assert args.run(args) == 0
    assert out.read_bytes()[:4] == b"\x89PNG"
    printed = capsys.readouterr().out
    assert "collision-free" in printed and "shelf" in printed


def test_show_command_rejects_a_bad_configuration(tmp_path: Path) -> None:
    from cr_nlp.cli import UsageError

    args = _parser().parse_args(["show", "--robot", "tdcr3", "--q", "9,0,0,0,0,0",
                                 "--out", str(tmp_path / "x.png")])
    with pytest.raises(UsageError, match="θ1"):
        args.run(args)


def test_bench_clearance_arguments() -> None:
    args = _parser().parse_args(["bench", "clearance", "--scene", "lattice", "shelf",
                                 "--configs", "1000", "--dtype", "float32", "float64"])
    assert args.scene == ["lattice", "shelf"] and args.configs == 1000
    assert args.dtype == ["float32", "float64"] and callable(args.run)


def test_bench_clearance_function_measures(tdcr3: Robot) -> None:
    from cr_nlp.bench._common import environment
    from cr_nlp.bench.clearance import bench_clearance, format_table

    row = bench_clearance(str(MODELS / "robots" / "tdcr3.json"), "lattice", configs=2000,
                          dtype="float64", repeats=2)
    assert row.parts == 27 and row.configs > 0 and row.median_s > 0
    table = format_table([row], environment())
    assert "configs/s" in table and "- jax:" in table and "lattice" in table
