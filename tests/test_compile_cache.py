"""A second process loads the IK's compiled programs from JAX's persistent cache instead
of compiling them again (``runtime.enable_compilation_cache``)."""

import json
import os
import subprocess
import sys
from pathlib import Path

SCRIPT = r"""
import json
import jax.monitoring
from cr_nlp import IKConfig, IKSolver, use_host_devices

use_host_devices()
counts = {"hits": 0, "misses": 0}

def count(event, **_):
    if event == "/jax/compilation_cache/cache_hits":
        counts["hits"] += 1
    elif event == "/jax/compilation_cache/cache_misses":
        counts["misses"] += 1

jax.monitoring.register_event_listener(count)
from cr_nlp.bench.ik import free_case
from cr_nlp import load_robot

robot = load_robot("tdcr3")
case = free_case(robot, 6, seed=1)
solver = IKSolver(robot, config=IKConfig(pool_size=256, retry_rounds=0))
result = solver.solve(case.positions, case.wxyz)
# The LM programs: the searches (keyed ("search", seeds, plan, chunk)).
lm_programs = [key for key in solver._search.main.compiled if key[0] == "search"]
print(json.dumps({**counts, "programs": len(lm_programs),
                  "compile": result.timing.compile, "success": result.success.tolist()}))
"""


def _run(cache: Path) -> dict:
    env = {**os.environ, "CR_NLP_JAX_CACHE": str(cache)}
    out = subprocess.run([sys.executable, "-c", SCRIPT], env=env, capture_output=True,
                         text=True, timeout=600, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_a_second_process_loads_the_compiled_ik_programs(tmp_path: Path) -> None:
    cache = tmp_path / "jax"
    first = _run(cache)
    assert first["hits"] == 0 and first["programs"] >= 1
    assert any(cache.iterdir()), "the first process wrote nothing to the cache"
    second = _run(cache)
    # Every LM program the solver compiled comes from the cache the second time.
    assert second["hits"] >= second["programs"]
    assert second["misses"] < first["misses"]
    assert all(first["success"]) and second["success"] == first["success"]
