"""The child process the TUI runs the commissioning flow in (``calibrate.tui.flow_runner``).

The flows below are module-level functions so that the spawned child can import them; they stand
in for ``run_commissioning`` (the real flow in a child is exercised in
``test_tui_commissioning.py``).
"""

from __future__ import annotations

import os
import sys
import threading
from types import SimpleNamespace

import pytest

from calibrate.commission_events import Step, StepFinished, StepStarted
from calibrate.run_directory import FLOW_LOG
from calibrate.tui.flow_runner import (
    BENCH_NICE,
    COMPUTE_NICE,
    ProcessFlowRunner,
    ThreadFlowRunner,
    _stop_when_orphaned,
)
from collect.errors import HardwareFault

EVENTS = [StepStarted(Step.COLLECT), StepFinished(Step.COLLECT, True), StepStarted(Step.FINETUNE), StepFinished(Step.FINETUNE, True)]


def nice_of_this_thread() -> int:
    return os.getpriority(os.PRIO_PROCESS, threading.get_native_id())


def emit_and_report(config, on_event, stop_event):
    """Emits ``EVENTS``; returns (pid, nice after each event, whether stop was seen)."""
    nice = []
    for event in EVENTS:
        on_event(event)
        nice.append(nice_of_this_thread())
    print("flow output that must not reach the terminal")
    print("flow error output", file=sys.stderr)
    return os.getpid(), nice, stop_event.is_set()


def wait_for_stop(config, on_event, stop_event):
    """Emits one event, then waits (up to 30 s) for the stop request."""
    on_event(StepStarted(Step.COLLECT))
    return stop_event.wait(30.0)


def signal_own_group_then_wait_for_stop(config, on_event, stop_event):
    """Sends SIGHUP and SIGTERM to itself, as a closing terminal or a service manager sends them to
    the whole process group, then waits (up to 30 s) for the UI's stop; returns whether it came."""
    import signal

    for signum in (signal.SIGHUP, signal.SIGTERM, signal.SIGINT):
        os.kill(os.getpid(), signum)
    on_event(StepStarted(Step.COLLECT))
    return stop_event.wait(30.0)


def raise_fault(config, on_event, stop_event):
    raise HardwareFault("camera-stall", "camera: no frame for 0.50 s")


def die(config, on_event, stop_event):
    os._exit(7)  # a crash: no result, no exception


@pytest.fixture
def config(tmp_path):
    return SimpleNamespace(run_dir=tmp_path / "run")


def test_child_sends_events_in_order_and_yields_the_cpu_more_from_fine_tuning_on(config, capfd):
    received = []
    ui_nice = nice_of_this_thread()
    pid, nice, stopped = ProcessFlowRunner(emit_and_report).run(config, received.append)
    assert received == EVENTS
    assert pid != os.getpid() and not stopped
    bench, compute = min(ui_nice + BENCH_NICE, 19), min(ui_nice + COMPUTE_NICE, 19)
    assert nice == [bench, bench, compute, compute]
    assert nice_of_this_thread() == ui_nice
    out, err = capfd.readouterr()
    assert "flow" not in out and "flow" not in err
    log = (config.run_dir / FLOW_LOG).read_text()
    assert "flow output that must not reach the terminal" in log and "flow error output" in log


def test_stop_request_reaches_the_child(config):
    runner = ProcessFlowRunner(wait_for_stop)
    assert runner.run(config, lambda event: runner.request_stop()) is True


def test_the_child_outlives_a_signal_to_the_process_group_and_stops_through_the_ui(config):
    """Was: only SIGINT was ignored; a SIGHUP or SIGTERM to the group killed the flow at once: arm
    not retracted, session file unclosed, no acceptance.json."""
    runner = ProcessFlowRunner(signal_own_group_then_wait_for_stop)
    assert runner.run(config, lambda event: runner.request_stop()) is True


def test_a_fault_in_the_child_is_raised_with_its_kind(config):
    with pytest.raises(HardwareFault) as info:
        ProcessFlowRunner(raise_fault).run(config, lambda event: None)
    assert info.value.kind == "camera-stall" and "no frame" in str(info.value)


def test_a_child_that_dies_is_reported_not_waited_for(config):
    with pytest.raises(RuntimeError, match=f"exit code 7.*{FLOW_LOG}"):
        ProcessFlowRunner(die).run(config, lambda event: None)


def test_the_thread_runner_runs_the_same_flows_in_this_process(config):
    pid, nice, stopped = ThreadFlowRunner(emit_and_report, bench_nice=0, compute_nice=0).run(config, lambda event: None)
    assert pid == os.getpid() and len(set(nice)) == 1 and not stopped
    with pytest.raises(HardwareFault):
        ThreadFlowRunner(raise_fault).run(config, lambda event: None)


def test_the_child_stops_the_flow_when_the_ui_process_is_gone():
    stop = threading.Event()
    _stop_when_orphaned(stop, parent_pid=os.getppid() + 1)  # not our parent: the UI is gone
    assert stop.is_set()


def flood_then_stop(config, on_event, stop_event):
    """Sends events (about 1 MB, more than a pipe holds) before and after the stop, then returns."""
    chunk = "x" * 4096
    for _ in range(256):
        on_event(chunk)
    stop_event.wait(30.0)
    for _ in range(256):  # its safe stop's reports
        on_event(chunk)
    return "stopped"


def test_a_ui_side_that_fails_waits_for_the_flows_stop_without_hanging(config):
    """The UI's event handler raises: the flow is stopped and the failure raised once the child has
    ended (was: the child's last messages filled the pipe nobody read, and the UI waited for it for ever)."""
    def failing_ui(event):
        raise RuntimeError("the UI failed")

    runner = ProcessFlowRunner(flood_then_stop)
    done = []
    thread = threading.Thread(target=lambda: done.append(pytest.raises(RuntimeError, runner.run, config, failing_ui)),
                              daemon=True)
    thread.start()
    thread.join(60.0)
    assert done and "the UI failed" in str(done[0].value), "the UI side hung on its stopped flow"
