"""The stop on SIGINT and SIGTERM (``cr_nlp._signals``): a held block runs to its end and
the stop follows it."""

from __future__ import annotations

import os
import signal

import pytest

from cr_nlp._signals import Stopped, signals_held, stop_on_signals


def test_a_signal_inside_a_held_block_stops_the_command_when_the_block_ends() -> None:
    steps = []
    with pytest.raises(Stopped) as caught, stop_on_signals():
        with signals_held():
            os.kill(os.getpid(), signal.SIGTERM)
            for i in range(1000):  # the handler has had its chance to run
                steps.append(i)
        steps.append("after")
    assert steps[:1000] == list(range(1000)) and steps[-1] != "after"
    assert caught.value.signum == signal.SIGTERM and caught.value.name == "SIGTERM"


def test_outside_a_held_block_the_signal_stops_at_once_and_handlers_are_restored() -> None:
    before = signal.getsignal(signal.SIGINT)
    with pytest.raises(Stopped) as caught, stop_on_signals():
        os.kill(os.getpid(), signal.SIGINT)
        for _ in range(10_000):
            pass
        pytest.fail("the signal did not stop the block")
    assert caught.value.signum == signal.SIGINT
    assert signal.getsignal(signal.SIGINT) is before
    with signals_held():  # nothing pending is left over from the earlier block
        pass
