"""The stop on SIGINT and SIGTERM: ``stop_on_signals`` turns either into ``Stopped`` in
the main thread; ``signals_held`` keeps a block (a file being written) whole, the stop
then coming when the block ends. Standard library only."""

from __future__ import annotations

import contextlib
import signal
import threading
from collections.abc import Iterator
from typing import Any


class Stopped(KeyboardInterrupt):
    """SIGINT or SIGTERM arrived while a command ran under ``stop_on_signals``. A
    ``KeyboardInterrupt``, so that every ``finally`` and ``except KeyboardInterrupt`` on
    the way out runs (the viewer stops its server, a batch closes its cluster)."""

    def __init__(self, signum: int) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = signum
        """The signal's number: the command exits with 128 + signum when it fails."""
        self.name = signal.Signals(signum).name
        """"SIGINT" or "SIGTERM"."""


class _Hold:
    """How many ``signals_held`` blocks are open, and the signal that came meanwhile."""

    depth = 0
    pending: int | None = None


@contextlib.contextmanager
def stop_on_signals() -> Iterator[None]:
    """Raise ``Stopped`` in the main thread on SIGINT and SIGTERM while the block runs,
    whatever this process inherited: a shell starts a background job with SIGINT
    ignored (Python then leaves it ignored), and SIGTERM's default ends the process
    without running any cleanup. The previous handlers are restored afterwards; outside
    the main thread (where Python cannot set handlers) this does nothing."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def stop(signum: int, frame: Any) -> None:
        if _Hold.depth:
            _Hold.pending = signum
            return
        raise Stopped(signum)

    previous = {s: signal.signal(s, stop) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for s, handler in previous.items():
            signal.signal(s, signal.SIG_DFL if handler is None else handler)


@contextlib.contextmanager
def signals_held() -> Iterator[None]:
    """Run the block without a stop in its middle: a SIGINT or SIGTERM that arrives meanwhile
    raises ``Stopped`` when the block ends (a stop inside ``np.savez`` would leave its zip
    half open, and the zip's clean-up error would hide the stop). Main thread only; in
    another thread (where no handler runs) this does nothing."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    _Hold.depth += 1
    try:
        yield
    finally:
        _Hold.depth -= 1
    if not _Hold.depth and _Hold.pending is not None:
        signum, _Hold.pending = _Hold.pending, None
        raise Stopped(signum)
