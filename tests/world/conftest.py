"""Fixtures of the verdict tests (``test_check``, ``test_motion_check``): two robots and a
scene with one obstacle of every kind."""

import pytest

from cr_nlp.model import Robot
from cr_nlp.world import Scene

from ..conftest import MODELS, write_mixed_scene


@pytest.fixture(scope="module")
def robots() -> dict[str, Robot]:
    return {name: Robot.from_file(MODELS / "robots" / f"{name}.json")
            for name in ("tdcr3", "tdcr4_ext")}


@pytest.fixture(scope="module")
def mixed_scene(tmp_path_factory: pytest.TempPathFactory) -> Scene:
    """One obstacle of every kind, within reach of the robots."""
    root = tmp_path_factory.mktemp("mixed_check")
    slab = {"type": "box", "name": "slab", "center": [0.0, 0.9, 2.4], "size": [0.8, 0.3, 0.2]}
    return write_mixed_scene(root, [slab])
