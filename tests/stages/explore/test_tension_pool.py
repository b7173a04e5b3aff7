"""The mechanics tasks' seed pool (``stages.explore``'s ``tension_pool``): cached on disk
per robot and load case, reused by a second process, rebuilt when the robot or the loads
change, and its tips those of a fresh statics solve."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
import time

import numpy as np
import pytest

from cr_nlp.model import load_robot
from cr_nlp.model.cosserat import solve_statics
from cr_nlp.model.loads import static_loads
from cr_nlp.stages.explore import tension_pool, tension_pool_cache_stats, tension_pool_path

RAO = load_robot("tdcr2_rao2021")
SIZE = 48
GRAVITY = [0.0, 0.0, -9.81]

SECOND_PROCESS = """
import json, sys
import numpy as np
from cr_nlp.model import load_robot
from cr_nlp.model.loads import static_loads
from cr_nlp.stages.explore import tension_pool, tension_pool_cache_stats
seed = int(sys.argv[1])
pool = tension_pool(load_robot("tdcr2_rao2021"), static_loads(1, 0.4, None, None,
                    [0.0, 0.0, -9.81]), 48, seed)
print(json.dumps({"stats": tension_pool_cache_stats(), "cached": pool.loaded_from_cache,
                  "tensions": pool.tensions.tolist()}))
"""


@pytest.fixture()
def seed() -> int:
    """A seed no earlier run used, so the first build is a build; its files are removed."""
    value = time.time_ns() % (1 << 30)
    yield value
    for loads in (static_loads(1, 0.4, None, None, GRAVITY), static_loads(1, 0.4)):
        for robot in (RAO, _stiffer()):
            tension_pool_path(robot, loads, SIZE, value).unlink(missing_ok=True)


def _stiffer():
    data = RAO.to_dict()
    data["mechanics"] = {**data["mechanics"], "youngs_modulus": 60e9}
    return load_robot(data)


def test_a_second_process_loads_the_pool_and_a_change_rebuilds_it(seed: int) -> None:
    loads = static_loads(1, 0.4, None, None, GRAVITY)
    before = tension_pool_cache_stats()
    pool = tension_pool(RAO, loads, SIZE, seed)
    assert not pool.loaded_from_cache
    assert tension_pool_path(RAO, loads, SIZE, seed).exists()
    # The pool's tips are the equilibria of its tensions under the loads.
    fresh = solve_statics(RAO, pool.tensions, gravity=GRAVITY)
    assert np.allclose(fresh.tip_position, pool.tips, atol=1e-9)
    out = subprocess.run([sys.executable, "-c", SECOND_PROCESS, str(seed)], check=True,
                         capture_output=True, text=True, timeout=600)
    second = json.loads(out.stdout.strip().splitlines()[-1])
    assert second["cached"] and second["stats"] == {"hits": 1, "builds": 0}
    assert np.array_equal(np.array(second["tensions"]), pool.tensions)
    # Other loads, or another robot, build their own pool.
    assert not tension_pool(RAO, static_loads(1, 0.4), SIZE, seed).loaded_from_cache
    assert not tension_pool(_stiffer(), loads, SIZE, seed).loaded_from_cache
    assert tension_pool(RAO, loads, SIZE, seed).loaded_from_cache
    after = tension_pool_cache_stats()
    assert after["builds"] - before["builds"] == 3 and after["hits"] - before["hits"] == 1


def test_a_damaged_cache_file_is_rebuilt(seed: int) -> None:
    loads = static_loads(1, 0.4, None, None, GRAVITY)
    tension_pool(RAO, loads, SIZE, seed)
    tension_pool_path(RAO, loads, SIZE, seed).write_bytes(b"not an npz file")
    again = tension_pool(RAO, loads, SIZE, seed)
    assert not again.loaded_from_cache and len(again.tensions) > 0
    assert tension_pool(RAO, loads, SIZE, seed).loaded_from_cache


def test_the_config_changes_the_key(seed: int) -> None:
    loads = static_loads(1, 0.4, None, None, GRAVITY)
    other = dataclasses.replace(RAO)   # an equal robot shares the file
    assert tension_pool_path(RAO, loads, SIZE, seed) == tension_pool_path(other, loads, SIZE,
                                                                          seed)
    assert tension_pool_path(RAO, loads, SIZE, seed) != tension_pool_path(RAO, loads,
                                                                          SIZE + 1, seed)
