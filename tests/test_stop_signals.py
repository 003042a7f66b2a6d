"""Ctrl-C, SIGTERM and SIGHUP handling of the command line (``calibrate.stop_signals``), in this
process: the first signal stops, a repeat never cuts that stop short. (Whole commands, SIGHUP
included, are interrupted in a child: test_collect_run, test_commission_flow, test_tui_commissioning.)"""

from __future__ import annotations

import os
import signal

import pytest

from calibrate.stop_signals import INTERRUPTS, STILL_STOPPING, Terminated, raise_interrupt, stop_signals_handled


def test_a_repeat_during_the_stop_is_only_acknowledged(capfd):
    before = {sig: signal.getsignal(sig) for sig in INTERRUPTS}
    with stop_signals_handled(raise_interrupt, INTERRUPTS):
        with pytest.raises(KeyboardInterrupt) as first:
            os.kill(os.getpid(), signal.SIGINT)
        assert type(first.value) is KeyboardInterrupt  # Ctrl-C itself: the usual exception
        os.kill(os.getpid(), signal.SIGINT)  # the operator presses Ctrl-C again: the stop goes on
        os.kill(os.getpid(), signal.SIGTERM)  # and a kill: ignored as well
        assert capfd.readouterr().err == STILL_STOPPING.decode()
    assert {sig: signal.getsignal(sig) for sig in INTERRUPTS} == before


def test_sigterm_raises_terminated_with_the_shell_exit_code():
    with stop_signals_handled(raise_interrupt, INTERRUPTS):
        with pytest.raises(Terminated) as err:
            os.kill(os.getpid(), signal.SIGTERM)
    assert isinstance(err.value, KeyboardInterrupt)  # every `except KeyboardInterrupt` safe stop handles it
    assert (err.value.name, err.value.exit_code) == ("SIGTERM", 143)


def test_a_handler_that_only_asks_for_a_stop_is_called_once():
    calls = []
    with stop_signals_handled(calls.append, INTERRUPTS):
        for sig in (signal.SIGTERM, signal.SIGINT, signal.SIGTERM):
            os.kill(os.getpid(), sig)
    assert calls == [signal.SIGTERM]
