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


def _arguments(note: dict) -> list:
    """Abstract arguments of the noted shapes, dtypes and weak types, placed as the
    program's were: split over the devices, else committed to one device or not."""
    import jax
    import numpy as np

    from ._programs import _mesh, _sharding

    leaves, batched = note["leaves"], note["batched"]
    if batched is None:
        one = jax.sharding.SingleDeviceSharding(jax.devices()[0])
        placements = [one if committed else None for *_, committed in leaves]
    else:
        mesh = _mesh()
        placements = [_sharding(mesh, b) for b in batched]
    return [jax.ShapeDtypeStruct(tuple(shape), np.dtype(dtype), weak_type=weak, sharding=where)
            for (shape, dtype, weak, _), where in zip(leaves, placements, strict=True)]


def upgrade(key: str) -> bool:
    """Compile the program stored under ``key`` fully into XLA's cache and mark it done;
    False where its entry or note is missing or unreadable (the note is then dropped)."""
    import jax

    from . import _compile_effort as effort
    from ._programs import _load, _mesh, _sharding

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
    shardings = ({} if note["batched"] is None else
                 {"in_shardings": tuple(_sharding(_mesh(), b) for b in note["batched"]),
                  "out_shardings": _sharding(_mesh(), True)})
    jax.jit(exported.call, **shardings).lower(*_arguments(note)).compile()
    effort._marker(key).touch()
    return True


def run(devices: int) -> int:
    """Compile every pending note of this environment; 0 when done, 1: another one runs."""
    from . import _compile_effort as effort
    from ._programs import environment_key
    from .runtime import configure, programs_dir, use_host_devices

    with contextlib.suppress(OSError):
        os.nice(19)
    use_host_devices(devices)
    configure()
    import jax

    # Every program into the cache, as ``runtime.enable_compilation_cache`` has it (the
    # parent's cache directory comes as $JAX_COMPILATION_CACHE_DIR).
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    folder = programs_dir()
    with open(folder / "upgrade.lock", "w") as lock:
        try:
            fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            return 1
        mine = effort.environment_hash(environment_key())
        tried: set[str] = set()
        while True:
            todo = []
            for key in effort.pending(folder):
                if key in tried:
                    continue
                with contextlib.suppress(OSError, ValueError):
                    if json.loads(effort._note(key).read_text())["environment"] == mine:
                        todo.append(key)
            if not todo:
                return 0
            for key in todo:
                tried.add(key)
                t0 = time.perf_counter()
                try:
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
