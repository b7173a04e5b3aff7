"""``cr-nlp bench tension --suite clutter``'s scene on any robot with a mechanics block: no
obstacle sits where every loaded backbone passes (python-fcl on backbones the scene was not
drawn from), and a scene that leaves no clear equilibrium is named, not searched forever."""

from __future__ import annotations

import numpy as np
import pytest

from cr_nlp.bench.tension_clutter import (
    GRAVITY,
    PAYLOAD,
    CrowdedScene,
    clear_tensions,
    clutter_scene,
)
from cr_nlp.model import load_robot
from cr_nlp.model.cosserat import solve_statics
from cr_nlp.stages.explore import random_tensions
from cr_nlp.tasks.mechanics.follow import TensionPathFollower
from cr_nlp.world import Scene
from cr_nlp.world.check import check_chains


def test_no_clutter_obstacle_blocks_the_fitted_robot_everywhere() -> None:
    """On the fitted FTDCR rod (short, its segments bending from the base) obstacles drawn
    on the backbones' points near the base touched every loaded backbone, and no clear
    tension set was left. Now each obstacle alone leaves most of 256 other loaded
    backbones clear by python-fcl, and the scene as a whole leaves clear equilibria."""
    robot = load_robot("ftdcr_v6_cosserat")
    scene = clutter_scene(robot, 0)
    solved = solve_statics(robot, random_tensions(robot, 256, 99), PAYLOAD, None, GRAVITY)
    chains = np.asarray(solved.positions)[solved.converged]
    per_segment = (chains.shape[1] - 1) // len(robot.segments)
    for obstacle in scene["obstacles"]:
        alone = Scene.from_dict({"obstacles": [obstacle]})
        touching = check_chains(robot, alone, chains, per_segment).obstacle_distance < 0.0
        assert touching.mean() < 0.7, obstacle["name"]
    follower = TensionPathFollower(robot, scene)
    # 64 sets: 256 candidates a round, the batch size the scene solved (one program)
    found = clear_tensions(follower, 64, np.random.default_rng(0), rounds=3)
    assert found.shape == (64, robot.n_tendons)


def test_a_scene_without_clear_equilibria_is_named() -> None:
    robot = load_robot("tdcr2_rao2021")
    wall = {"obstacles": [{"name": "around", "type": "sphere", "center": [0.0, 0.0, 0.0],
                           "radius": 2.0}]}
    follower = TensionPathFollower(robot, wall)
    with pytest.raises(CrowdedScene, match=r"0 of 32 random tension sets .* 4 wanted"):
        clear_tensions(follower, 4, np.random.default_rng(0), rounds=2)
