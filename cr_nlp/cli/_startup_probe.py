"""The timed process of ``cr-nlp bench startup`` (``cr_nlp.bench.startup``): runs one
entry point through the command's own ``main`` twice and prints its timings as JSON.

Run as ``python -m cr_nlp.cli._startup_probe ENTRY INPUTS OUT``; not a subcommand.
"""

from __future__ import annotations

import contextlib
import importlib
import io
import json
import os
import sys
import time
from pathlib import Path
from typing import Any

_EVENTS = {
    "/jax/core/compile/jaxpr_trace_duration": "trace",
    "/jax/core/compile/jaxpr_to_mlir_module_duration": "trace",
    "/jax/core/compile/backend_compile_duration": "xla",
}


def probe(entry: str, inputs: Path, out: Path) -> dict[str, float]:
    """Run in the timed process: ``entry`` twice through the command's ``main``; seconds
    since the process was spawned (``$CR_NLP_STARTUP_T0``) and per part."""
    spawned = float(os.environ.get("CR_NLP_STARTUP_T0", time.time()))
    started = time.time() - spawned
    t0 = time.perf_counter()
    if entry == "import":
        importlib.import_module("cr_nlp")  # what a user's ``import cr_nlp`` costs

        return {"start": started, "import": time.perf_counter() - t0,
                "first_answer": time.time() - spawned}
    import jax.monitoring

    from .._programs import stats
    from ..bench.startup import entry_argv
    from .main import main

    parts = {"trace": 0.0, "xla": 0.0}

    def listen(event: str, duration: float, **_: Any) -> None:
        if event in _EVENTS:
            parts[_EVENTS[event]] += duration

    imported = time.perf_counter() - t0
    jax.monitoring.register_event_duration_secs_listener(listen)
    argv = entry_argv(entry, inputs, out)
    sink = io.StringIO()
    t1 = time.perf_counter()
    with contextlib.redirect_stdout(sink):
        status = main(argv)
    first = time.perf_counter() - t1
    first_answer = time.time() - spawned
    trace = parts["trace"]  # JAX's own trace and lowering events, cr_nlp's exports included
    xla = parts["xla"]
    t2 = time.perf_counter()
    with contextlib.redirect_stdout(sink):
        main(argv)
    steady = time.perf_counter() - t2
    return {"start": started, "import": imported, "trace": trace, "xla": xla,
            "first_solve": first - trace - xla, "first": first, "steady": steady,
            "first_answer": first_answer, "status": status,
            "programs_traced": stats.traced, "programs_loaded": stats.loaded}


if __name__ == "__main__":
    name, inputs_dir, out_dir = sys.argv[1:4]
    Path(out_dir).mkdir(parents=True, exist_ok=True)
    print(json.dumps(probe(name, Path(inputs_dir), Path(out_dir))))
