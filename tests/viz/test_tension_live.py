"""Live IK on the Cosserat rod in the viewer (``viz._tension_live``, ``cr-nlp view --model
cosserat``): the dragged target solved for tensions under gravity and a payload, the tube
drawn on the rod's equilibrium, each answer replayed by a fresh statics solve."""

from __future__ import annotations

import numpy as np
import pytest

from cr_nlp.model import load_robot
from cr_nlp.model.cosserat import solve_statics
from cr_nlp.viz._geometry import backbone_frames
from cr_nlp.viz._replay import AROUND, SAMPLES
from cr_nlp.viz._tension_live import resample_frames

from .test_viewer import _viewer_module

RAO = load_robot("tdcr2_rao2021")
GRAVITY = [0.0, 0.0, -9.81]
PAYLOAD = [0.0, 0.0, -0.005 * 9.81]


def test_resampled_frames_are_the_arcs_at_the_rings() -> None:
    # A chain of arcs sampled finely, resampled to the tube's rings, against the same
    # arcs sampled at the rings in closed form.
    robot = load_robot("tdcr3")
    q = np.array([1.0, -0.8, 0.9, 1.7, 0.8, 1.0, 0.9, -0.6, 1.0])
    fine = backbone_frames(robot, q, samples=6 * SAMPLES)
    pos, rot = resample_frames(*fine, robot.n_segments)
    want_pos, want_rot = backbone_frames(robot, q, samples=SAMPLES)
    np.testing.assert_allclose(pos, want_pos, atol=1e-12)
    np.testing.assert_allclose(rot, want_rot, atol=1e-12)
    # between grid points: linear interpolation, off by the chord's sag only (< 1 mm here)
    coarse = backbone_frames(robot, q, samples=SAMPLES // 2 * 3)
    pos, rot = resample_frames(*coarse, robot.n_segments)
    assert np.abs(pos - want_pos).max() < 1e-3
    np.testing.assert_allclose(np.einsum("kji,kjl->kil", rot, rot),
                               np.broadcast_to(np.eye(3), rot.shape), atol=1e-12)


def test_a_dragged_target_is_solved_for_tensions_under_load() -> None:
    viewer = _viewer_module()
    with pytest.raises(ValueError, match="has no 'mechanics' block"):
        viewer.Viewer("tdcr3", model="cosserat", live_ik=False)
    t = np.linspace(0.0, 1.0, 4)[:, None]
    motion = np.concatenate([1 + 2 * t, 0 * t, 0.5 * t, 1 - t, t, 0 * t], axis=1)
    tips = solve_statics(RAO, motion, PAYLOAD, None, GRAVITY).tip_position
    loads = {"gravity": GRAVITY, "tip_force": PAYLOAD}
    with viewer.Viewer(RAO, model="cosserat", loads=loads) as view:
        assert view._live_on and not hasattr(view, "_exact_box")  # no exact stage live
        view._warming.join()
        # The warm-up compiled a drag's updates: the first, and the one program of those
        # whose last equilibrium is known.
        assert view._tension.solver()._program is not None
        # Before a target: the rod's rest shape under the loads, the gizmo at its tip.
        rest = solve_statics(RAO, np.zeros((1, 6)), PAYLOAD, None, GRAVITY)
        np.testing.assert_allclose(view._live_gizmo.position, rest.tip_position[0], atol=1e-6)
        for target in tips:
            answer = view.move_target(target, [1.0, 0.0, 0.0, 0.0])
            assert answer.success, answer.reason
            # Replayed by a fresh statics solve under the same loads: the target, and the
            # tube on the page is around that rod (the centre of its last ring: the tip).
            again = solve_statics(RAO, answer.tensions[None], PAYLOAD, None, GRAVITY)
            assert np.linalg.norm(again.tip_position[0] - target) < 1e-4
            rings = np.asarray(view._body.vertices).reshape(-1, AROUND, 3)
            assert len(rings) == 1 + RAO.n_segments * SAMPLES
            np.testing.assert_allclose(rings[-1, :-1].mean(axis=0), again.tip_position[0],
                                       atol=1e-5)
        assert "tensions" in view._live_text.content and "N" in view._live_text.content
        # the rod has no live Ipopt stage: asked for one, the page says so, the robot stays
        assert view.move_target(tips[0], [1.0, 0.0, 0.0, 0.0], exact=True) is None
        assert "no exact stage" in view._live_text.content


def test_cli_view_model_cosserat_names_what_it_needs(capsys) -> None:
    _viewer_module()
    from cr_nlp.cli import main

    assert main(["view", "--robot", "tdcr3", "--model", "cosserat"]) == 2
    assert "tdcr3 has no 'mechanics' block" in capsys.readouterr().err
    assert main(["view", "--robot", "tdcr2_rao2021", "--model", "cosserat",
                 "--gravity", "0,0"]) == 2
    assert "--gravity" in capsys.readouterr().err
