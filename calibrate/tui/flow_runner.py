"""Where the TUI runs the commissioning flow: a child process (the default) or a thread.

A runner calls ``flow(config, on_event=..., stop_event=...)`` away from the UI thread and
hands every event to ``on_event`` in the UI process; ``request_stop`` (any thread, any time)
sets the flow's ``stop_event``: the flow safe-stops the arm, retracts and closes the session file.

* ``ProcessFlowRunner`` (what ``bubble tui`` uses): the flow runs in a spawned child process, so the
  UI thread never waits for the GIL held by the bench loops, the recorder or the training loop.
  The child sends its events, then its result or a record of its exception, through a ``multiprocessing``
  queue. The flow runs below the UI's priority from birth (``BENCH_NICE``: the UI, which needs a
  few tens of ms of CPU a few times per second, gets a core at once, and the bench loops still get
  everything else), and from the first compute step on (fine-tuning, the bench is closed by then)
  well below it (``COMPUTE_NICE``, inherited by torch's worker threads), so the UI process wins
  the CPU while training keeps every core busy. The child ignores SIGINT (the UI decides when to
  stop), stops the arm by itself when the UI process dies (and then exits without waiting for
  anyone to read its last messages), and writes its log (stdout, stderr, log records) to
  ``RUN_DIR/flow.log`` instead of the terminal the UI draws on. An exception of the flow other than
  ``HardwareFault`` and ``InputError`` comes back as ``FlowError``, which names that log.
* ``ThreadFlowRunner``: the flow runs in a thread of this process, with the same priority rule
  (per thread on Linux). For flows that cannot be sent to another process (test doubles, embedding).
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import queue
import signal
import sys
import threading
import time
from abc import ABC, abstractmethod
from collections.abc import Callable
from pathlib import Path

from calibrate.commission_events import Step, StepStarted
from calibrate.run_directory import FLOW_LOG
from collect.errors import HardwareFault, InputError

#: ``flow(config, on_event=..., stop_event=...) -> CommissionResult``
Flow = Callable[..., object]
OnEvent = Callable[[object], None]

#: Nice increment of the flow from its start (bench steps): the scheduler prefers the UI (CFS weight
#: 1024 against 272) without starving the bench loops (the UI wants ~15 % of one core). With 3
#: (weight 526) the UI still waited up to 30 ms for a core during collection (docs/bench_tui.md).
BENCH_NICE = 6
#: Nice increment of the flow from the first compute step on (total, from the UI's priority).
COMPUTE_NICE = 10
COMPUTE_STEPS = (Step.FINETUNE, Step.VALIDATE, Step.POSE_CHECK, Step.VERDICT)
#: How often the UI side checks that the child is still alive, and the child that the UI is, s.
POLL_S = 0.25


class FlowError(RuntimeError):
    """The flow in the child process failed otherwise than with a ``HardwareFault`` or an ``InputError``:
    it raised another exception, or its process ended without a result. The text says which (the
    exception's own class and message) and names ``RUN_DIR/flow.log``, which holds the traceback."""


def _lower_thread_priority(increment: int) -> None:
    """Raise the calling thread's nice value by ``increment`` (Linux: per thread, inherited by the
    threads it starts later). Without privileges a thread can only lower its priority, never raise
    it back, hence a dedicated flow thread or process, which ends with the flow."""
    if increment <= 0:
        return
    try:
        tid = threading.get_native_id()
        os.setpriority(os.PRIO_PROCESS, tid, os.getpriority(os.PRIO_PROCESS, tid) + increment)
    except (AttributeError, OSError):  # not Linux/Unix, or not permitted: run at normal priority
        pass


def _yield_on_compute(on_event: OnEvent, bench_nice: int, compute_nice: int, flow_thread: int) -> OnEvent:
    """Lower the calling (flow) thread's priority by ``bench_nice`` now, and return an ``on_event``
    that lowers it to ``compute_nice`` in all at the first compute step.

    ``flow_thread``: ``threading.get_ident()`` of the thread that runs the flow; events from its
    helper threads (bench snapshots) pass through without touching their priority.
    """
    _lower_thread_priority(bench_nice)
    niced = False

    def forward(event: object) -> None:
        nonlocal niced
        if (
            not niced
            and isinstance(event, StepStarted)
            and event.step in COMPUTE_STEPS
            and threading.get_ident() == flow_thread
        ):
            niced = True
            _lower_thread_priority(compute_nice - bench_nice)
        on_event(event)

    return forward


class FlowRunner(ABC):
    """Runs one commissioning flow away from the UI thread (see the module docstring)."""

    def __init__(self, flow: Flow, bench_nice: int = BENCH_NICE, compute_nice: int = COMPUTE_NICE) -> None:
        self.flow = flow
        self.bench_nice = min(bench_nice, compute_nice)
        self.compute_nice = compute_nice

    @abstractmethod
    def run(self, config, on_event: OnEvent):
        """Run the flow to its end (blocks): returns its result or raises its exception.

        ``on_event`` is called from the calling thread (process runner) or the flow's thread.
        """

    @abstractmethod
    def request_stop(self) -> None:
        """Ask the flow to stop (thread-safe; also before ``run`` starts it)."""

    def abandon(self) -> bool:
        """Stop waiting for a flow that was asked to stop and has not (quitting gave up on it): ``run``
        raises ``FlowError`` at once and leaves the flow to end by itself. True where that is possible
        (a flow in a child process); a flow in a thread of this process cannot be left: False."""
        return False


class ThreadFlowRunner(FlowRunner):
    """The flow in a dedicated thread of this process."""

    def __init__(self, flow: Flow, bench_nice: int = BENCH_NICE, compute_nice: int = COMPUTE_NICE) -> None:
        super().__init__(flow, bench_nice, compute_nice)
        self._stop_event = threading.Event()

    def request_stop(self) -> None:
        self._stop_event.set()

    def run(self, config, on_event: OnEvent):
        outcome: dict = {}

        def flow_thread() -> None:
            forward = _yield_on_compute(on_event, self.bench_nice, self.compute_nice, threading.get_ident())
            try:
                outcome["result"] = self.flow(config, on_event=forward, stop_event=self._stop_event)
            except BaseException as err:  # re-raised in the caller's thread
                outcome["error"] = err

        thread = threading.Thread(target=flow_thread, name="commissioning-flow")
        thread.start()
        thread.join()
        if "error" in outcome:
            raise outcome["error"]
        return outcome["result"]


class ProcessFlowRunner(FlowRunner):
    """The flow in a spawned child process; ``flow`` must be picklable (a module-level function)."""

    def __init__(self, flow: Flow, bench_nice: int = BENCH_NICE, compute_nice: int = COMPUTE_NICE) -> None:
        super().__init__(flow, bench_nice, compute_nice)
        start_resource_tracker()
        self._context = multiprocessing.get_context("spawn")
        self._stop_event = self._context.Event()
        self._abandoned = threading.Event()

    def request_stop(self) -> None:
        self._stop_event.set()

    def abandon(self) -> bool:
        """The child goes on alone: it has its stop, and stops by itself once this process is gone
        (was: ``run``, and with it the UI's exit, waited for it however long it took)."""
        self._abandoned.set()
        return True

    def run(self, config, on_event: OnEvent):
        log = Path(config.run_dir) / FLOW_LOG
        messages = self._context.Queue()
        child = self._context.Process(
            target=_child_main,
            args=(self.flow, config, messages, self._stop_event, self.bench_nice, self.compute_nice, os.getpid()),
            name="bubble-commissioning",
        )
        _start_niced(child, self.bench_nice)
        try:
            while True:
                if self._abandoned.is_set():  # every pass: a flow that keeps sending never leaves the queue empty
                    raise FlowError(f"left the commissioning process to stop by itself; see {log}")
                try:
                    kind, payload = messages.get(timeout=POLL_S)
                except queue.Empty:
                    if child.is_alive():
                        continue
                    try:  # it may have sent its last message just before exiting
                        kind, payload = messages.get(timeout=1.0)
                    except queue.Empty:
                        raise FlowError(f"the commissioning process ended without a result (exit code "
                                        f"{child.exitcode}); see {log}") from None
                if kind == "event":
                    on_event(payload)
                elif kind == "result":
                    return payload
                else:
                    raise _error_from_record(*payload, log)
        finally:
            if child.is_alive():
                self._stop_event.set()  # the UI side failed: the flow must not go on unattended
            while child.is_alive() and not self._abandoned.is_set():  # its safe stop's messages read and dropped:
                try:  # a full pipe would hold it for ever (was: a join, then SIGTERM, which it ignores, and a join)
                    messages.get(timeout=POLL_S)
                except queue.Empty:
                    pass
            if not self._abandoned.is_set():
                child.join()
            messages.close()


def start_resource_tracker() -> None:
    """Start multiprocessing's resource tracker on the real stderr (once per process; later calls
    return at once). ``bubble tui`` calls it at start-up, so that the first run does not start it
    (a Python process) in the instant the operator starts the run.

    The tracker inherits the descriptor of ``sys.stderr``; a running textual app has replaced
    ``sys.stderr`` with a capture object whose ``fileno()`` is -1, which makes the spawn fail.
    """
    from multiprocessing import resource_tracker

    captured = sys.stderr
    try:
        sys.stderr = sys.__stderr__ if sys.__stderr__ is not None else open(os.devnull, "w")
        resource_tracker.ensure_running()
    finally:
        sys.stderr = captured


def _start_niced(child, nice: int) -> None:
    """Start ``child`` from a short-lived thread that lowered its own priority by ``nice`` first:
    the child inherits it from birth, so its start-up (interpreter, imports: ~1 s of CPU) already
    runs below the UI instead of competing with it (a key press in that second waited 48 ms)."""
    failure: list[BaseException] = []

    def start() -> None:
        _lower_thread_priority(nice)
        try:
            child.start()
        except BaseException as err:  # re-raised in the caller's thread
            failure.append(err)

    starter = threading.Thread(target=start, name="flow-starter")
    starter.start()
    starter.join()
    if failure:
        raise failure[0]


def _stop_when_orphaned(stop_event, parent_pid: int) -> None:
    """Child thread: set ``stop_event`` when the UI process is gone (re-parented child)."""
    while not stop_event.is_set():
        if os.getppid() != parent_pid:
            logging.getLogger(__name__).error("the UI process is gone: stopping the flow")
            stop_event.set()
            return
        time.sleep(POLL_S)


def _redirect_output(run_dir: Path) -> None:
    """Send fd 1/2 and the log records to ``run_dir/flow.log`` (the terminal belongs to the UI)."""
    try:
        run_dir.mkdir(parents=True, exist_ok=True)
        log_fd = os.open(run_dir / FLOW_LOG, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
    except OSError:  # a bad run directory: the flow reports it; nothing may reach the terminal
        log_fd = os.open(os.devnull, os.O_WRONLY)
    for fd in (1, 2):
        os.dup2(log_fd, fd)
    os.close(log_fd)
    sys.stdout = open(1, "w", buffering=1, closefd=False)
    sys.stderr = open(2, "w", buffering=1, closefd=False)
    logging.basicConfig(stream=sys.stderr, level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")


def _error_record(err: BaseException) -> tuple[str, str, str]:
    """What the UI needs of the flow's exception, as plain strings: (class, fault kind, message)."""
    if isinstance(err, HardwareFault):
        return "HardwareFault", err.kind, str(err)
    if isinstance(err, InputError):
        return "InputError", "", str(err)
    return type(err).__name__, "", str(err)


def _error_from_record(name: str, kind: str, message: str, log: Path) -> BaseException:
    """The exception the UI shows for a record of ``_error_record``; ``log``: the child's ``flow.log``."""
    if name == "HardwareFault":
        return HardwareFault(kind, message)
    if name == "InputError":
        return InputError(message)
    # the flow's class once, and where its traceback is (was: RuntimeError("ValueError: ..."), shown as
    # "Internal error: RuntimeError: ValueError: ..." with no word of the log)
    return FlowError(f"{name}: {message}; see {log}")


def _send_last(messages, message: tuple, parent_pid: int) -> None:
    """Put the flow's last ``message`` on ``messages`` and wait until the queue's feeder thread has
    written everything to the pipe, or until the UI process (``parent_pid``) is gone, checked every
    ``POLL_S`` s: nobody reads the pipe then, and a feeder blocked on a full pipe never ends. (Was: the
    exit waited for the feeder without a limit, so a child whose UI process had died (killed, crashed)
    stayed for ever after saving its data, deaf to SIGTERM, until kill -9.)"""
    messages.put(message)
    messages.close()
    flushing = threading.Thread(target=messages.join_thread, name="queue-flush", daemon=True)
    flushing.start()
    while flushing.is_alive() and os.getppid() == parent_pid:
        flushing.join(POLL_S)
    if os.getppid() != parent_pid:  # the exit must not join the feeder either, whoever reaches it first
        messages.cancel_join_thread()


def _child_main(flow: Flow, config, messages, stop_event, bench_nice: int, compute_nice: int, parent_pid: int) -> None:
    """Entry point of the child process: run the flow, send events, then the result or the error."""
    # The UI stops the flow on each of these (a terminal's Ctrl-C, its closing, a service manager)
    # and a signal to the whole process group reaches this process too: stopping here at once would
    # leave the arm unretracted and the session file open. The orphan watch covers a UI that died.
    for signum in (signal.SIGINT, signal.SIGHUP, signal.SIGTERM):
        signal.signal(signum, signal.SIG_IGN)
    _redirect_output(Path(config.run_dir))
    watch = threading.Thread(target=_stop_when_orphaned, args=(stop_event, parent_pid), name="orphan-watch", daemon=True)
    watch.start()
    # born at bench_nice (_start_niced): only the step to compute_nice is left to take
    forward = _yield_on_compute(lambda event: messages.put(("event", event)), 0, compute_nice - bench_nice,
                                threading.get_ident())
    try:
        last = ("result", flow(config, on_event=forward, stop_event=stop_event))
    except BaseException as err:
        logging.getLogger(__name__).exception("the commissioning flow raised")
        last = ("error", _error_record(err))
    _send_last(messages, last, parent_pid)
