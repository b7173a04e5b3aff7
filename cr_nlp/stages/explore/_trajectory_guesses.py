"""Initial trajectories for the trajectory LM: the roadmap's path, the straight line in
the bending vector z, then straight lines bent by random half-sine bumps."""

from __future__ import annotations

import math

import numpy as np

from ...model import Robot, q_to_z_numpy


def initial_guesses(robot: Robot, z_start: np.ndarray, z_goal: np.ndarray,
                    path: np.ndarray | None, waypoints: int, count: int, perturbation: float,
                    rng: np.random.Generator) -> tuple[np.ndarray, list[str]]:
    """(``count``, waypoints, 3n) initial trajectories in z and what each one is
    ("roadmap", "straight", "perturbed").

    Args:
        robot: the robot.
        z_start, z_goal: (3n,) start and goal bending vectors (rad, rad, m).
        path: the roadmap's (waypoints, 3n) configurations θ, φ, L, or None; its ends are
            replaced by the exact start and goal.
        waypoints: configurations per trajectory, start and goal included.
        count: guesses wanted.
        perturbation: radians, the bump's amplitude per segment at the middle waypoint
            (zero at start and goal).
        rng: the source of the bumps' directions.
    """
    s = np.linspace(0.0, 1.0, waypoints)[:, None]
    straight = z_start[None] + s * (z_goal - z_start)[None]
    guesses, kinds = [], []
    if path is not None:
        z = q_to_z_numpy(np.reshape(path, (waypoints, -1)))
        z[0], z[-1] = z_start, z_goal
        guesses.append(z)
        kinds.append("roadmap")
    guesses.append(straight)
    kinds.append("straight")
    bump = np.sin(np.pi * s)
    bending = np.zeros(robot.dof, bool)
    bending[0::3] = bending[1::3] = True
    while len(guesses) < count:
        direction = rng.normal(size=robot.dof) * bending
        direction *= perturbation / max(np.linalg.norm(direction), 1e-12)
        direction *= math.sqrt(robot.n_segments)   # ≈ perturbation per segment
        guesses.append(straight + bump * direction[None])
        kinds.append("perturbed")
    return np.stack(guesses[:count]), kinds[:count]
