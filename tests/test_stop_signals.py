"""Ctrl-C, SIGTERM and SIGHUP handling of the command line (``collect.stop_signals``), in this
process: the first signal stops, a repeat never cuts that stop short. (Whole commands, SIGHUP
included, are interrupted in a child: test_collect_run, test_commission_flow, test_tui_commissioning.)"""

from __future__ import annotations

import os
import signal
import time
from pathlib import Path

import pytest

from collect.stop_signals import INTERRUPTS, STILL_STOPPING, Terminated, raise_interrupt, stop_signals_handled


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


def test_once_a_command_has_stopped_a_repeat_cannot_change_how_its_process_ends(interrupt_handlers_restored, capfd):
    """Was: the command's block put the default handlers back after a stop that took under 20 ms,
    and a second Ctrl-C killed the exiting process (exit -2 to its parent, not 130)."""
    with pytest.raises(KeyboardInterrupt):
        with stop_signals_handled(raise_interrupt, INTERRUPTS, process_ends=True):
            os.kill(os.getpid(), signal.SIGINT)
    assert all(signal.getsignal(sig) == signal.SIG_IGN for sig in INTERRUPTS)
    for sig in INTERRUPTS:
        os.kill(os.getpid(), sig)  # ignored: the process goes on to exit with 130
    assert capfd.readouterr().err == ""


def test_a_nested_stop_leaves_every_signal_acknowledged_until_the_process_ends(interrupt_handlers_restored, capfd):
    """`bubble tui` handles SIGTERM in its own block inside the command's: after that stop, a Ctrl-C
    is only acknowledged (the command's own handler would raise in the exiting app)."""
    calls = []
    with stop_signals_handled(raise_interrupt, INTERRUPTS, process_ends=True):
        with stop_signals_handled(calls.append):
            os.kill(os.getpid(), signal.SIGTERM)
        os.kill(os.getpid(), signal.SIGINT)
        assert capfd.readouterr().err == STILL_STOPPING.decode()
    assert calls == [signal.SIGTERM]
    assert all(signal.getsignal(sig) == signal.SIG_IGN for sig in INTERRUPTS)


def test_a_command_without_a_stop_puts_the_handlers_back(interrupt_handlers_restored):
    before = {sig: signal.getsignal(sig) for sig in INTERRUPTS}
    with stop_signals_handled(raise_interrupt, INTERRUPTS, process_ends=True):
        pass
    assert {sig: signal.getsignal(sig) for sig in INTERRUPTS} == before


@pytest.mark.parametrize("stage", ["build", "parse"])
def test_ctrl_c_before_the_command_starts_is_one_line_and_exit_130(monkeypatch, capsys, stage,
                                                                   interrupt_handlers_restored):
    """Was: a KeyboardInterrupt traceback for a Ctrl-C in the ~0.4 s in which ``bubble`` imports its
    commands and parses the command line (a real SIGINT, sent at that moment)."""
    import argparse
    import importlib

    from calibrate.cli import main

    signal.signal(signal.SIGINT, signal.default_int_handler)  # a fresh process's, whatever a test before left

    def interrupted(original):
        def call(*args, **kwargs):
            os.kill(os.getpid(), signal.SIGINT)  # Python's handler raises KeyboardInterrupt here
            return original(*args, **kwargs)
        return call

    if stage == "build":
        monkeypatch.setattr(importlib, "import_module", interrupted(importlib.import_module))
    else:
        monkeypatch.setattr(argparse.ArgumentParser, "parse_args", interrupted(argparse.ArgumentParser.parse_args))
    try:
        code = main(["info", "s.h5"])
    except KeyboardInterrupt:
        pytest.fail("a KeyboardInterrupt traceback")
    assert (code, capsys.readouterr().err) == (130, "bubble: interrupted\n")
    monkeypatch.undo()
    for argv, exit_code in ((["--version"], 0), (["nope"], 2)):  # argparse's own exits are as before
        with pytest.raises(SystemExit) as exited:
            main(argv)
        assert exited.value.code == exit_code


def test_a_command_that_finished_without_seeing_its_stop_ends_as_stopped(monkeypatch, capsys, synthetic_session,
                                                                        interrupt_handlers_restored):
    """A SIGTERM whose ``Terminated`` a library swallowed (trimesh's imports catch BaseException):
    was exit 0, as if nothing had been asked."""
    import collect.session_info
    from calibrate.cli import main

    real = collect.session_info.describe_session

    def swallowing(path):
        try:
            os.kill(os.getpid(), signal.SIGTERM)  # the command's handler raises Terminated here
            for _ in range(100):
                time.sleep(0.01)
        except BaseException:  # noqa: BLE001 - as such a library does
            pass
        return real(path)

    monkeypatch.setattr(collect.session_info, "describe_session", swallowing)
    assert main(["info", str(synthetic_session)]) == 143
    out, err = capsys.readouterr()
    assert str(synthetic_session) in out and err == "bubble: interrupted (SIGTERM)\n"


def test_the_executable_keeps_its_exit_code_when_a_stop_signal_comes_as_it_exits(tmp_path):
    """Was: a Ctrl-C just after a command's end (its fault's line printed) ended the process by the
    signal, exit -2 instead of the command's code."""
    import subprocess
    import sys

    script = tmp_path / "bubble_then_ctrl_c.py"
    script.write_text(
        "import os, signal, sys\n"
        "import calibrate.cli as cli\n"
        "real = cli.main\n"
        "def main_then_ctrl_c(*args, **kwargs):\n"
        "    code = real(*args, **kwargs)\n"
        "    os.kill(os.getpid(), signal.SIGINT)  # as the process exits\n"
        "    return code\n"
        "cli.main = main_then_ctrl_c\n"
        "sys.argv = ['bubble', 'info', '/dev/null']\n"
        "cli.run()\n")
    done = subprocess.run([sys.executable, str(script)], cwd=Path(__file__).resolve().parents[1], capture_output=True,
                          text=True, timeout=120, preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    assert (done.returncode, done.stderr) == (2, "bubble: error: /dev/null is not a regular file (a device, a pipe or "
                                                 "a socket), not a session file\n")


def test_a_block_the_process_exits_after_leaves_the_stop_signals_ignored(interrupt_handlers_restored):
    with stop_signals_handled(raise_interrupt, INTERRUPTS, process_ends=True, exits_after=True):
        pass
    assert {signal.getsignal(sig) for sig in INTERRUPTS} == {signal.SIG_IGN}
