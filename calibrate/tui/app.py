"""The bench TUI application: runs the commissioning flow away from the UI and shows its events.

Processes and threads: the flow (``calibrate.commissioning.run_commissioning``, the same code as
``bubble commission``) runs in a child process (``calibrate.tui.flow_runner``), so the UI thread
never competes for the GIL with the bench loops, the recorder or the training. A textual thread
worker waits for the child and receives its events; each one only goes into an ``EventInbox``.
A step boundary, a fault or the verdict posts one ``FlowEventsReady`` message (``post_message`` is
thread-safe) and the UI thread drains the whole batch at once. Progress reports and bench snapshots
(camera frames, pose, wrench) are picked up by a timer at ``refresh_hz``, so a flow that reports at
the camera's 45 fps never makes the UI compose a frame per report. The child runs below the UI's
scheduling priority (``BENCH_NICE``, and ``COMPUTE_NICE`` from fine-tuning on), so the UI wins the
CPU while the flow keeps every core busy.

Safety: the stop key (``s`` or space, a priority binding that works on every screen) sets the
flow's ``stop_event``; the flow safe-stops the arm, retracts and closes the session file. Nothing
moves before the operator confirms in a dialog. Quitting mid-run stops first and exits once the
flow has returned.
"""

from __future__ import annotations

import math
import os
import threading
import time
from collections.abc import Callable
from functools import partial
from pathlib import Path

from textual import events, on
from textual.app import App
from textual.binding import Binding
from textual.containers import Horizontal, Vertical
from textual.message import Message
from textual.widgets import Footer, Header, TabbedContent, TabPane
from textual.worker import Worker, WorkerState

from calibrate.commission_events import (
    CollectionProgress,
    ArmSafeStopped,
    FaultRaised,
    Step,
    StepFinished,
    TrainingProgress,
    Verdict,
)
from calibrate.run_directory import FLOW_LOG
from calibrate.tui.flow_runner import (BENCH_NICE, COMPUTE_NICE, Flow, FlowError, FlowRunner, ProcessFlowRunner,
                                       ThreadFlowRunner, start_resource_tracker)
from calibrate.tui.frame_gap_gc import CHECK_INTERVAL_S, FrameGapCollector
from calibrate.tui.inbox import EventInbox
from calibrate.tui.widgets.acceptance_table import AcceptanceTable
from calibrate.tui.widgets.banner import Banner
from calibrate.tui.widgets.bench_panel import BenchPanel
from calibrate.tui.widgets.collection_panel import CollectionPanel
from calibrate.tui.widgets.confirm import ConfirmStart
from calibrate.tui.widgets.registry_view import RegistryView
from calibrate.tui.widgets.sensor_view import SensorView
from calibrate.tui.widgets.steps_panel import StepsPanel
from calibrate.tui.widgets.training_curve import TrainingCurve
from collect.errors import EXIT_INTERRUPTED, HardwareFault, InputError
from hw_mocks.objects import object_name

#: The banner's line when idle, and during a run until a stop, a fault or the outcome replaces it. It never
#: hides once shown: hiding it would shift the whole screen up a line and re-lay every panel out in
#: the frame that answers the start (docs/tui.md "Responsiveness"). Both fit one line of an 80-column terminal
#: (78 cells inside the banner's padding; was: the idle hint took two lines below 101 columns, the run hint one,
#: so the start still moved the screen at the documented minimum of 100 x 30).
IDLE_HINT = "Press c to commission (asks before the arm moves). s or space stops the arm."
RUN_HINT = "Commissioning... s or space stops and retracts the arm; recorded data is kept."

#: The smallest terminal (columns, rows) in which every panel shows whole (docs/tui.md); below it the
#: app says so once per shrink. The stop keys work at any size.
MIN_TERMINAL = (100, 30)

#: How long quitting waits for a stopping flow before giving up on a clean close, s: then the app
#: leaves (exit code 1) and the flow's process, orphaned, stops by itself.
QUIT_WAIT_S = 60.0
#: A stop key this long (s) before the start dialog's "yes" is handled cancels the start.
STOP_CANCELS_START_S = 1.0

#: textual's animation level unless the user sets ``TEXTUAL_ANIMATIONS``: none. The only animation
#: here is the tab underline sliding for 0.3 s after each tab key, which recomposes the screen at up
#: to 60 frames/s; without it a tab switch composes one frame (docs/tui.md "Responsiveness").
DEFAULT_ANIMATION_LEVEL = "none"

#: Start-up tab warm-up (``BenchApp(warm_up_tabs=True)``): how often it checks that the tab it shows
#: has been laid out, s, and how many checks before it moves on regardless.
WARM_UP_POLL_S = 1 / 60
WARM_UP_MAX_POLLS = 30


class FlowEventsReady(Message):
    """Posted from the runner's thread when the inbox has new queued events."""


class BenchApp(App):
    """``bubble tui``: bench panel, sensor view, steps, training curve, acceptance, registry.

    ``config``: a ``calibrate.commissioning.CommissionConfig`` (fields used here: ``run_dir``,
    ``simulated``, ``sensor_spec``, ``registry_dir``, ``objects``, ``poses_per_object``).
    ``flow``: None runs ``run_commissioning`` in a child process; a callable with the same
    signature runs in a thread of this process instead (test doubles). ``clock``: monotonic
    time in s for ETAs and snapshot ages (tests pass a fixed clock). ``refresh_hz``: rate of the
    live bench/sensor refresh. ``bench_nice`` / ``compute_nice``: nice increment of the flow in the
    bench steps / from fine-tuning on (0 = as the UI; ``calibrate.tui.flow_runner``).
    ``tune_gc``: once mounted, run the process's garbage collector between frames
    (``calibrate.tui.frame_gap_gc``; ``bubble tui``, which owns its process). ``warm_up_tabs``: show
    every tab for one frame at start-up, so that no first switch to a tab is slow (``bubble tui``).
    """

    CSS_PATH = "bench.tcss"
    TITLE = "Bubble bench"
    #: No command palette (textual's ctrl+p): its search field takes every printable key, the stop
    #: keys ``s`` and space included, so while it was open they typed instead of stopping the arm.
    ENABLE_COMMAND_PALETTE = False

    #: The letter keys in either case (was: lower-case alone, and with Caps Lock on the stop key
    #: ``S`` did nothing, with no message).
    BINDINGS = [
        Binding("s,S", "stop", "STOP arm", key_display="s", priority=True),
        Binding("space", "stop", "STOP arm", show=False, priority=True),
        Binding("c,C", "commission", "Commission", key_display="c"),
        Binding("1", "show_tab('tab-commission')", "Steps"),
        Binding("2", "show_tab('tab-sensor')", "Sensor"),
        Binding("3", "show_tab('tab-acceptance')", "Acceptance"),
        Binding("4", "show_tab('tab-registry')", "Registry"),
        Binding("r,R", "reload_registry", "Reload registry", show=False),
        Binding("q,Q", "quit", "Quit", key_display="q"),
        Binding("ctrl+c", "quit", "Quit", show=False, priority=True),
    ]

    def __init__(
        self,
        config,
        *,
        flow: Flow | None = None,
        clock: Callable[[], float] = time.monotonic,
        refresh_hz: float = 5.0,
        bench_nice: int = BENCH_NICE,
        compute_nice: int = COMPUTE_NICE,
        tune_gc: bool = False,
        warm_up_tabs: bool = False,
    ) -> None:
        super().__init__()
        if "TEXTUAL_ANIMATIONS" not in os.environ:
            self.animation_level = DEFAULT_ANIMATION_LEVEL
        self.config = config
        self._flow = flow
        self._clock = clock
        self._refresh_hz = refresh_hz
        self._bench_nice = bench_nice
        self._compute_nice = compute_nice
        self.gc_collector = FrameGapCollector() if tune_gc else None
        self._warm_up_tabs = warm_up_tabs
        self.tabs_warmed_up: list[str] = []  # tab ids drawn by the start-up warm-up, in order
        self._tab_chosen: str | None = None  # a tab key pressed during the warm-up: it ends there
        self.started_up = False  # the first frames are drawn, the warm-up (if any) is over, the collector runs
        self._inbox = EventInbox()
        self._runner: FlowRunner | None = None
        self._flow_done = threading.Event()
        self._flow_done.set()
        self._worker: Worker | None = None
        self._quit_requested = False
        self._stop_requested = False  # this run was asked to stop: its flow's Verdict is no verdict
        self._stop_key_at = -math.inf  # time.monotonic() of the latest stop key
        #: the checks of this run's Verdict, as acceptance.json lists them (those after a failed gate "not
        #: run"; ``CommissionResult.checks`` holds the checks made); None before it
        self._verdict_checks: list[dict] | None = None
        self._gave_up = False  # quitting gave up on the flow after QUIT_WAIT_S
        #: Quitting gave up on a flow in a child process that still runs (``FlowRunner.abandon``): whoever
        #: ran the app ends this process without joining it (multiprocessing joins children at exit).
        self.left_flow_running = False
        self._arm_state = "idle"
        self._bench_open = False  # the flow holds the bench (from the start until collection ends)
        self._connected = False
        self._last_snapshot_at: float | None = None
        self._latest_images = None  # (ir, depth_m) of the latest snapshot
        self._fault_text: str | None = None  # banner text of the run's last FaultRaised
        self._too_small = False  # the terminal is below MIN_TERMINAL (and the operator was told)
        self.safe_stop: ArmSafeStopped | None = None  # the run's last safe stop of the arm
        self.result = None  # the last CommissionResult
        self.error: BaseException | None = None  # the last exception raised by the flow
        self.sub_title = ("SIMULATED" if config.simulated else "REAL") + f" · {config.run_dir}"

    # ----------------------------------------------------------------- layout
    def compose(self):
        cfg = self.config
        # Panels are kept as attributes: a modal screen on top must not hide them from updates.
        self.banner = Banner(id="banner")
        self.bench_panel = BenchPanel(cfg.simulated, id="bench")
        self.live_sensor = SensorView(compact=True, id="live-sensor")
        self.tabs = TabbedContent(initial="tab-commission", id="tabs")
        self.steps = StepsPanel(id="steps")
        # as the flow names them: a mesh file by its stem (was: a third object, and "9/12 poses")
        self.collection = CollectionPanel(tuple(object_name(o) for o in cfg.objects), int(cfg.poses_per_object),
                                          id="collection")
        self.training = TrainingCurve(id="training")
        self.sensor = SensorView(id="sensor")
        self.acceptance = AcceptanceTable(id="acceptance")
        self.registry = RegistryView(cfg.registry_dir, id="registry")
        yield Header()
        yield self.banner
        with Horizontal(id="main"):
            with Vertical(id="left"):
                yield self.bench_panel
                yield self.live_sensor
            with self.tabs:
                with TabPane("Commission [1]", id="tab-commission"):
                    with Vertical(id="commission"):
                        yield self.steps
                        yield self.collection
                        yield self.training
                with TabPane("Sensor [2]", id="tab-sensor"):
                    yield self.sensor
                with TabPane("Acceptance [3]", id="tab-acceptance"):
                    yield self.acceptance
                with TabPane("Registry [4]", id="tab-registry"):
                    yield self.registry
        yield Footer()

    def on_mount(self) -> None:
        self.banner.show(IDLE_HINT, "hint")
        self.set_interval(1.0 / self._refresh_hz, self.refresh_live)
        if self._warm_up_tabs:
            shown = self.tabs.active
            others = [pane.id for pane in self.tabs.query(TabPane) if pane.id != shown]
            self.call_after_refresh(self._show_tabs_once, [*others, shown])
        else:
            self.call_after_refresh(self._finish_start_up)  # after the first frame: its widgets are frozen too

    def on_resize(self, event: events.Resize) -> None:
        """Below ``MIN_TERMINAL`` panels are cut: say so once, when the terminal gets that small."""
        width, height = event.size
        too_small = width < MIN_TERMINAL[0] or height < MIN_TERMINAL[1]
        if too_small and not self._too_small:
            self.notify(f"The terminal is {width} x {height}: panels are cut below {MIN_TERMINAL[0]} x "
                        f"{MIN_TERMINAL[1]}; enlarge the window. s or space still stops the arm.",
                        severity="warning", timeout=10)
        self._too_small = too_small

    def _show_tabs_once(self, order: list[str], polls: int = 0) -> None:
        """Start-up (``warm_up_tabs``): show each tab until it has been laid out (drawn), ending on
        the first one, or on the operator's tab as soon as a tab key is pressed.

        A pane's first display costs up to ~90 ms more than later ones (the large sensor view:
        docs/tui.md); paying it at start-up keeps it out of the operator's first key presses.
        """
        if self._tab_chosen is not None:  # was: the warm-up went on and ended on the first tab
            self.tabs.active = self._tab_chosen
            self.call_after_refresh(self._finish_start_up)
            return
        self.tabs.active = order[0]
        drawn = self.tabs.get_pane(order[0]).size.area > 0
        if not drawn and polls < WARM_UP_MAX_POLLS:
            self.set_timer(WARM_UP_POLL_S, lambda: self._show_tabs_once(order, polls + 1))
            return
        if drawn:
            self.tabs_warmed_up.append(order[0])
        if len(order) > 1:
            self._show_tabs_once(order[1:])
        else:
            self.call_after_refresh(self._finish_start_up)

    def _finish_start_up(self) -> None:
        """After the first frames (their widgets are frozen too): start multiprocessing's resource
        tracker when runs go to a child process (else the first run would start that Python process
        in the instant of its start), collect garbage between frames, and mark the start-up over
        (``started_up``: from now on a key press times only itself)."""
        if self._flow is None:
            start_resource_tracker()
        if self.gc_collector is not None:
            self.gc_collector.start()
            self.set_interval(CHECK_INTERVAL_S, self.gc_collector.tick)
        self.started_up = True

    # ------------------------------------------------------------ state query
    @property
    def running(self) -> bool:
        """Whether the commissioning flow is running (including while it stops)."""
        return not self._flow_done.is_set()

    @property
    def events_received(self) -> int:
        """Flow events received so far (every kind, before coalescing)."""
        return self._inbox.received

    @property
    def arm_state(self) -> str:
        """``idle``, ``moving``, ``stopping`` or ``stopped`` (the UI's view of the arm)."""
        return self._arm_state

    # ---------------------------------------------------------------- actions
    def action_commission(self) -> None:
        if isinstance(self.screen, ConfirmStart):
            return  # already asking
        if self.running:
            self.notify("Commissioning is already running.", severity="warning")
            return
        cfg = self.config
        details = (
            f"mode: {'simulated bench' if cfg.simulated else 'REAL bench'}\n"
            f"sensor: {cfg.sensor_spec or 'default'}\n"
            f"objects: {', '.join(cfg.objects)} x {cfg.poses_per_object} poses\n"
            f"run dir: {cfg.run_dir}"
        )
        self.push_screen(ConfirmStart(details), callback=self._confirmed)

    def _confirmed(self, start: bool | None) -> None:
        """The dialog's answer. A stop key within ``STOP_CANCELS_START_S`` before it cancels a start:
        keys that reach the app together are not handled in order (the stop keys are priority
        bindings, handled as they arrive), and a stop typed right after ``y`` could be handled before
        it (was: "Nothing is moving.", and the arm then moved)."""
        if not start:
            return
        if time.monotonic() - self._stop_key_at < STOP_CANCELS_START_S:
            self.notify("Start cancelled: a stop key came with it; nothing moves.", severity="warning")
            return
        self.start_commissioning()

    def start_commissioning(self) -> None:
        """Start the flow (the confirmation dialog calls this)."""
        if self.running:
            return
        self._reset_views()
        self._runner = self._make_runner()
        self._flow_done.clear()
        self._arm_state = "moving"
        self._bench_open = True
        self._stop_requested = False
        self.result = None
        self.error = None
        self._worker = self.run_worker(
            self._run_flow, name="commissioning", thread=True, exclusive=True, exit_on_error=False
        )
        self._update_bench_panel(None)

    def _make_runner(self) -> FlowRunner:
        if self._flow is None:
            from calibrate.commissioning import run_commissioning

            return ProcessFlowRunner(run_commissioning, self._bench_nice, self._compute_nice)
        return ThreadFlowRunner(self._flow, self._bench_nice, self._compute_nice)

    def _run_flow(self):
        """Worker body: run the flow to its end and return its result."""
        try:
            return self._runner.run(self.config, self._on_flow_event)
        finally:
            self._flow_done.set()

    def action_stop(self) -> None:
        """Stop the arm now: the flow safe-stops, retracts and closes the session file."""
        self._stop_key_at = time.monotonic()
        if isinstance(self.screen, ConfirmStart):
            self.screen.dismiss(False)
            return
        if not self.running:
            self.notify("Nothing is moving.", timeout=2)
            return
        if self._bench_open:
            self._request_stop("STOP: arm stopping and retracting...")
        else:
            self._request_stop("STOP: ending the run (the bench is already closed, the arm is parked)...")

    def _request_stop(self, message: str) -> None:
        self._runner.request_stop()
        self._stop_requested = True
        if self._bench_open and self._arm_state != "stopped":  # a second stop after the safe stop: stays stopped
            self._arm_state = "stopping"
        self.banner.show(message, "warning")
        self._update_bench_panel(None)

    async def action_quit(self) -> None:
        if self.running:
            if not self._quit_requested:
                self.set_timer(QUIT_WAIT_S, self._give_up_quitting)
            self._quit_requested = True
            if self._bench_open:
                self._request_stop("Quitting: stopping the arm and closing the session file first...")
            else:
                self._request_stop("Quitting: ending the run first...")
            return
        self.exit()

    def _give_up_quitting(self) -> None:
        """Quitting waited ``QUIT_WAIT_S`` for a flow that did not end: leave without it."""
        if self.running:
            self._gave_up = True
            self.left_flow_running = self._runner.abandon()  # the worker returns: the app's exit waits for it
            self.exit(return_code=1, message=f"bubble tui: the run did not end within {QUIT_WAIT_S:g} s of quitting; "
                                             f"left it to stop by itself (see {Path(self.config.run_dir) / FLOW_LOG})")

    def action_show_tab(self, tab: str) -> None:
        self.tabs.active = tab
        if not self.started_up:
            self._tab_chosen = tab

    def action_reload_registry(self) -> None:
        self.registry.reload()

    # ------------------------------------------------------- flow -> UI events
    def _on_flow_event(self, event: object) -> None:
        """Called by the runner (not the UI thread) for each event; never blocks."""
        if self._inbox.put(event):
            self.post_message(FlowEventsReady())

    @on(FlowEventsReady)
    def _drain_inbox(self) -> None:
        self.apply_events(self._inbox.drain())

    def apply_events(self, events: list[object]) -> None:
        """Show a batch of (non-snapshot) events, oldest first; redraws each panel once."""
        now = self._clock()
        steps = self.steps
        steps_changed = False
        points: list[TrainingProgress] = []
        for event in events:
            if steps.apply(event, now):
                steps_changed = True
                if isinstance(event, StepFinished) and event.step == Step.COLLECT:
                    self._close_bench_view(collected=event.ok and not event.skipped)
            elif isinstance(event, CollectionProgress):
                self.collection.apply(event)
            elif isinstance(event, TrainingProgress):
                points.append(event)
            elif isinstance(event, ArmSafeStopped):
                self.safe_stop = event
                if self._bench_open:
                    self._arm_state = "stopped"
            elif isinstance(event, FaultRaised):
                self._fault_text = f"FAULT {event.kind}: {event.message}"
                self.banner.show(self._fault_text, "fault")
            elif isinstance(event, Verdict):
                self._verdict_checks = event.checks
                if not self._stop_requested:  # a stopped run's: "NO VERDICT" at its end
                    self.acceptance.show(event.accepted, event.checks, event.report_path)
        self.training.apply(points)
        if steps_changed:
            steps.tick(now)

    def _close_bench_view(self, collected: bool) -> None:
        """The flow has closed the bench (collection over; ``collected``: every pose recorded, not a
        collection skipped or failed): the arm is parked, no more snapshots."""
        snapshot = self._closing_snapshot()
        self._bench_open = False
        self._connected = False
        if self._arm_state == "moving":
            self._arm_state = "idle"
        self._update_bench_panel(snapshot)
        if collected:
            self.collection.complete()

    def _closing_snapshot(self):
        """The snapshot waiting while the bench closes (the flow sends one of the arm as it left it, parked
        or safe-stopped), or None; later snapshots are dropped by ``refresh_live``."""
        return self._inbox.take_snapshot() if self._bench_open else None

    def refresh_live(self) -> None:
        """Timer (``refresh_hz``): the latest bench snapshot's images in the live preview, then in the
        large sensor view when it is shown, then the queued progress, the bench panel and the ETAs, each
        part in a frame of its own. A key press that arrives with the refresh then waits for one part
        of it, not for all (docs/tui.md "Responsiveness")."""
        snapshot = self._inbox.take_snapshot()
        if not self._bench_open:
            # left over from before collection closed the bench: it would bring the link back
            # ("stale (N s)") for the rest of the run
            snapshot = None
        parts = [partial(self._refresh_panels, snapshot)]
        if snapshot is not None:
            self._connected = True
            self._last_snapshot_at = self._clock()
            self._latest_images = (snapshot.ir, snapshot.depth_m)
            parts[:0] = [partial(self.live_sensor.show, *self._latest_images), self._show_sensor_tab_images]
        self._in_frames(parts)

    def _in_frames(self, parts: list[Callable[[], object]]) -> None:
        """Run ``parts[0]`` now, and each later part after the frame that shows the one before it."""
        parts[0]()
        if len(parts) > 1:
            self.call_after_refresh(self._in_frames, parts[1:])

    def _show_sensor_tab_images(self) -> None:
        """The latest snapshot's images in the large sensor view, when its tab is shown."""
        if self.tabs.active == "tab-sensor" and self._latest_images is not None:
            self.sensor.show(*self._latest_images)

    def _refresh_panels(self, snapshot) -> None:
        """The last part of ``refresh_live``: queued progress, the bench panel (``snapshot``: the one
        whose images were just shown, or None) and the ETAs."""
        self._drain_inbox()
        self._update_bench_panel(snapshot)
        self.steps.tick(self._clock())

    @on(TabbedContent.TabActivated)
    def _tab_activated(self, event: TabbedContent.TabActivated) -> None:
        self._show_sensor_tab_images()

    def _update_bench_panel(self, snapshot) -> None:
        age = None if self._last_snapshot_at is None else self._clock() - self._last_snapshot_at
        connected = self._connected and self.running
        self.bench_panel.show(snapshot, age if self.running else None, connected, self._arm_state)
        # the images of the last snapshot stay in the live view: said so once the link is down
        self.live_sensor.border_subtitle = "last reading" if self._latest_images is not None and not connected else ""

    def _reset_views(self) -> None:
        self._inbox.drain()
        self._inbox.take_snapshot()
        self._connected = False
        self._last_snapshot_at = None
        self._fault_text = None
        self._verdict_checks = None
        self.safe_stop = None
        self.banner.show(RUN_HINT, "hint")
        self.steps.reset()
        self.collection.reset()
        self.training.reset()
        self.acceptance.reset()

    # ------------------------------------------------------------- flow end
    def on_worker_state_changed(self, event: Worker.StateChanged) -> None:
        if event.worker is not self._worker or event.state not in (WorkerState.SUCCESS, WorkerState.ERROR):
            return
        self._drain_inbox()
        now = self._clock()
        banner = self.banner
        if event.state == WorkerState.SUCCESS:
            self.result = result = event.worker.result
            checks = result.checks if self._verdict_checks is None else self._verdict_checks
            if result.stopped or result.fault:
                self.steps.interrupt(now, "stopped" if result.stopped else "failed")
            session = Path(result.run_dir) / "session.h5"
            report = str(result.report_path) if Path(result.report_path).is_file() else ""
            if result.stopped:
                kept = (f"Recorded data kept in {session}" if session.is_file() else
                        f"No calibration frames recorded yet; the completed steps are kept in {result.run_dir}")
                banner.show(f"Stopped by operator: {self._arm_outcome()}. {kept}", "warning")
                self.acceptance.show(None, checks, report, "stopped by operator")
            elif result.fault:
                reported = self._fault_text or f"FAULT {result.fault}"
                banner.show(f"{reported} | {self._arm_outcome()} | run rejected; c retries (completed steps are kept)",
                            "fault")
                self.acceptance.show(result.accepted, checks, report, f"hardware fault {result.fault}")
            else:
                verdict = "ACCEPTED" if result.accepted else "REJECTED"
                if result.reason and not result.accepted:
                    verdict += f" ({result.reason})"
                banner.show(f"{verdict}. Report: {result.report_path}", "info" if result.accepted else "fault")
                self.acceptance.show(result.accepted, checks, str(result.report_path))
        else:
            self.error = err = event.worker.error
            self.steps.interrupt(now, "failed")
            if isinstance(err, HardwareFault):
                text = f"FAULT {err.kind}: {err}"
            elif isinstance(err, InputError):
                text = f"Input error: {err}"
            elif isinstance(err, FlowError):  # the flow's class and message, and its log: shown as they are
                text = f"Internal error: {err}"
            else:
                text = f"Internal error: {type(err).__name__}: {err}"
            # the flow safe-stopped the arm before it raised: what that did (not retracted: the pendant)
            banner.show(text if self.safe_stop is None else f"{text} | {self._arm_outcome()}", "fault")
        # stopped: the flow safe-stopped the arm (ArmSafeStopped); a run that ended before the bench
        # opened, or after collection closed it, left the arm parked
        self._arm_state = "stopped" if self.safe_stop is not None else "idle"
        snapshot = self._closing_snapshot()
        self._bench_open = False
        self._update_bench_panel(snapshot)
        self.registry.reload()
        if self._quit_requested:  # the run this quit stopped: exit 130, as a Ctrl-C of bubble commission
            self.exit(return_code=EXIT_INTERRUPTED, message=f"bubble tui: quit during the run, which stopped; its "
                                                            f"files are in {self.config.run_dir}")

    def _arm_outcome(self) -> str:
        """What the run's safe stop did to the arm, for the banner."""
        return "the arm was already parked" if self.safe_stop is None else self.safe_stop.summary()

    def on_unmount(self) -> None:
        """Last line of defence (e.g. the terminal closed): stop the flow and wait for it."""
        if self.running and self._runner is not None:
            self._runner.request_stop()
            if not self._gave_up:
                self._flow_done.wait(QUIT_WAIT_S)
        if self.gc_collector is not None:
            self.gc_collector.stop()
