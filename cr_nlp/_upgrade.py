"""The background process that compiles quickly compiled programs fully
(``python -m cr_nlp._upgrade --devices N``; see ``cr_nlp._compile_effort``).

Started detached by a process that compiled programs quickly, at the lowest CPU
priority. One runs at a time per cache (a lock file); it compiles every noted program
of its own environment that is not marked done, each exactly as ``_programs`` compiles it
(the stored program over arguments of the noted shapes, split over the devices as noted),
so that XLA's cache holds the code a later process asks for, then marks it done. It looks
again until none is left, and exits."""

from __future__ import annotations

import argparse
import contextlib
import fcntl
import json
import os
import sys
import time
from collections.abc import Sequence
from pathlib import Path


def _arguments(note: dict, in_shardings: tuple | None) -> list:
    """Abstract arguments of the noted shapes, dtypes and weak types, placed as the
    program's were: split over the devices (``in_shardings``), else committed to one
    device or not."""
    import jax
    import numpy as np

    leaves = note["leaves"]
    placements = in_shardings
    if placements is None:
        one = jax.sharding.SingleDeviceSharding(jax.devices()[0])
        placements = [one if committed else None for *_, committed in leaves]
    return [jax.ShapeDtypeStruct(tuple(shape), np.dtype(dtype), weak_type=weak, sharding=where)
            for (shape, dtype, weak, _), where in zip(leaves, placements, strict=True)]


def upgrade(key: str) -> bool:
    """Compile the program stored under ``key`` fully into XLA's cache and mark it done;
    False where its entry or note is missing or unreadable (the note is then dropped)."""
    import jax

    from . import _compile_effort as effort
    from ._programs import _load, split_shardings

    note_path = effort._note(key)
    entry = _load(key)
    try:
        note = json.loads(note_path.read_text())
    except (OSError, ValueError):
        note = None
    if entry is None or note is None:
        with contextlib.suppress(OSError):
            note_path.unlink()
        return False
    exported, _ = entry
    in_shardings, out_shardings = split_shardings(note["batched"])
    jax.jit(exported.call, in_shardings=in_shardings, out_shardings=out_shardings).lower(
        *_arguments(note, in_shardings)).compile()
    effort._marker(key).touch()
    return True


def run(devices: int) -> int:
    """Compile every pending note of this environment; 0 when done, 1: another one runs
    (checked before JAX is imported: a second one costs next to nothing)."""
    from .runtime import programs_dir

    with contextlib.suppress(OSError):
        os.nice(19)
    folder = programs_dir()
    with open(folder / "upgrade.lock", "a") as lock:
        for attempt in range(20):       # a waiter's probe holds it for a moment
            try:
                fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except BlockingIOError:
                if attempt == 19:
                    return 1
                time.sleep(0.05)
        _compile_pending(devices, folder)
    return 0


def _compile_pending(devices: int, folder: Path) -> None:
    """Compile the notes in ``folder`` of this process's environment (on ``devices`` host
    devices, as the process that noted them), looking again until none is left."""
    from . import _compile_effort as effort
    from ._programs import environment_key
    from .runtime import configure, use_host_devices

    use_host_devices(devices)
    configure()
    import jax

    # Every program into the cache, as ``runtime.enable_compilation_cache`` has it (the
    # parent's cache directory comes as $JAX_COMPILATION_CACHE_DIR).
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    mine = {}
    for x64 in (False, True):        # programs traced in float64 (statics) and not
        with jax.enable_x64(x64):
            mine[effort.environment_hash(environment_key())] = x64
    tried: set[str] = set()
    while True:
        todo = []
        for key in effort.pending(folder):
            with contextlib.suppress(OSError, ValueError):
                x64 = mine.get(json.loads(effort._note(key).read_text())["environment"])
                if key not in tried and x64 is not None:
                    todo.append((key, x64))
        if not todo:
            return
        for key, x64 in todo:
            tried.add(key)
            t0 = time.perf_counter()
            try:
                with jax.enable_x64(x64):
                    done = upgrade(key)
            except Exception as exc:  # noqa: BLE001 — one program's failure is logged
                print(f"cr_nlp upgrade: {key}: {exc}", flush=True)
                continue
            print(f"cr_nlp upgrade: {key}: {'compiled' if done else 'dropped'} in "
                  f"{time.perf_counter() - t0:.1f} s", flush=True)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m cr_nlp._upgrade")
    parser.add_argument("--devices", type=int, required=True,
                        help="JAX host devices of the process that noted the programs")
    return run(parser.parse_args(argv).devices)


if __name__ == "__main__":
    sys.exit(main())
