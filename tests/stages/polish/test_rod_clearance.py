"""The clearance rows of a Cosserat backbone in the tension-space exact stage
(``stages.polish._rod_clearance``): the slot rows Ipopt sees, evaluated by CasADi from the
grid points, against the numpy pair distances (``world.clearance`` formulas) that choose
the slots, on backbones in a scene of spheres and boxes."""

from __future__ import annotations

import casadi as ca
import numpy as np

from cr_nlp.model import load_robot
from cr_nlp.model.cosserat import CasadiRod, StaticsConfig
from cr_nlp.stages.polish._rod_clearance import RodClearance
from cr_nlp.world.scene import load_scene


def test_slot_rows_are_the_pair_distances_of_the_chosen_pairs() -> None:
    robot = load_robot("tdcr2_rao2021")
    arc = np.asarray(CasadiRod(robot, StaticsConfig(), ()).layout.arc_length)
    scene = load_scene({"obstacles": [
        {"name": "ball", "type": "sphere", "center": [0.03, 0.01, 0.25], "radius": 0.02},
        {"name": "crate", "type": "box", "center": [-0.04, 0.0, 0.15],
         "size": [0.03, 0.05, 0.04]}]})
    clear = RodClearance(robot, scene, arc, 0.002, max_pairs=16, near_margin=0.2,
                         face_smoothing=0.002, per_step=4)
    points = ca.MX.sym("points", 3, len(arc))
    rows, slots = clear.rows(points)
    function = ca.Function("rows", [points, *slots], [rows])
    rng = np.random.default_rng(3)
    for _ in range(5):
        # a bent backbone of the robot's length in its base frame, grid points (S+1, 3)
        step = np.diff(arc, prepend=0.0)[:, None]
        slope = np.cumsum(rng.normal(0.0, 0.15, (len(arc), 2)), axis=0)
        positions = np.c_[np.cumsum(slope * step, axis=0), arc]
        distances = clear.distances(positions)
        parameters, lower, chosen = clear.slot_parameters(distances)
        values = np.asarray(function(positions.T, *parameters)).ravel()
        on = np.isfinite(lower)
        assert on.sum() == len(chosen) > 0
        np.testing.assert_allclose(values[on], distances[chosen], atol=1e-12, rtol=0)
