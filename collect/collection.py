"""The collection run loop shared by ``bubble collect``, ``bubble commission`` and the TUI.

``run_collection(bench, plan, writer, progress_callback, stop_event)`` drives the arm through a
``CollectionPlan`` while a recorder thread streams the bench into a ``SessionWriter``:

* main thread (the caller's): for each object, travel above it (``Arm.travel_to``: a run, fresh or
  resumed, starts wherever the arm was left, so it rises straight up to the travel height before
  moving across), rest at its reference pose for the no-contact frames (phase ``free``, pose id
  -1, the object's index), then for each contact pose: ``approach`` (travel to the pose's
  above-pose, guarded move until contact), ``press`` (to the pose's press force beyond the contact
  force), ``hold``, ``retract`` (back to the above-pose). Moves between objects are phase ``free``
  with object -1.
* recorder thread: takes every camera frame, stamps it with the object / pose / phase that was
  under way at the frame's capture time (``t_host`` on the bench clock; the main thread logs each
  phase start on that clock, so frames that wait in the camera queue keep their true phase) and
  with the arm's pose at that time (interpolated between the samples around it, 125 Hz or faster;
  a frame newer than every sample drained so far takes the latest), and queues it to the
  writer together with the arm state samples and pressure readings that arrived meanwhile. It also reports progress (<= 10 Hz and on every phase
  change) and watches the camera (stall) and the pressure board (unplug, timeout): a fault there
  aborts the arm's running motion at once (``Arm.abort``), which raises it in the main thread.
* progress thread: hands the recorder's reports to ``progress_callback`` (``_ProgressRelay``), so
  that a display that blocks (a terminal paused with Ctrl-S) never holds up the recorder.
* recorder watchdog: a recorder that handled no frame for ``RECORDER_STALL_S`` of bench time (the
  session file's disk stalled, its queue full) is a ``recorder`` fault that stops the arm: the
  camera and the pressure board are watched by the recorder alone (was: the arm pressed on,
  unwatched and unrecorded, until the disk came back).

Faults and interrupts: on a ``HardwareFault`` from any device, a ``KeyboardInterrupt`` or any
other error, the loop calls ``bench.safe_stop()`` (stop the arm, retract when possible), stops the
recorder thread (every frame captured until then is queued to the writer, those still in the
camera's queue included) and re-raises; a Ctrl-C (or
SIGTERM, SIGHUP) during that stop is only acknowledged, so that it neither cuts the retract short
nor hides the fault (``stop_signals.acknowledge_stop``). The caller owns
the writer and closes it (``with SessionWriter(...)``), which keeps every frame. A set
``stop_event`` ends the run the same way but returns normally with ``result.stopped = True``; the
arm watches it (``Arm.stop_on``), so a stop in the middle of a motion halts the arm at once.
"""

from __future__ import annotations

import bisect
import collections
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from collect import session_format as sf
from collect.arm import retract_speed
from collect.errors import RECORDER_FAULT, HardwareFault, InputError, StopRequested
from collect.pose_planner import CollectionPlan, PlanSettings, plan_collection
from collect.session_writer import SessionWriter
from collect.stop_signals import INTERRUPTS, acknowledge_stop, stop_signals_handled
from collect.transforms import interpolate_poses

log = logging.getLogger(__name__)

#: Progress reports per second (at most), besides one on every phase change.
PROGRESS_HZ = 10.0
#: The progress reports' phase of the safe stop's retract after a stop or a fault, which belongs to no
#: pose (its frames are recorded as ``retract`` of pose id -1). Was: reported as ``retract`` of the pose
#: under way, which read as that pose pressed and let go when the stop came during its approach.
STOPPING_PHASE = "stopping"
#: How long the recorder waits for a frame before the camera counts as stalled (s).
FRAME_TIMEOUT_S = 0.5
#: Arm samples kept for stamping frames with the pose at their capture time (~1 s at 500 Hz).
ARM_HISTORY = 512
#: Bench time (s) the recorder may go without handling a frame (or a camera timeout) before it counts
#: as blocked: a ``recorder`` fault stops the arm (``_watch_recorder``). Four camera timeouts.
RECORDER_STALL_S = 4 * FRAME_TIMEOUT_S
#: Progress reports a lagging display may have pending; more drop the oldest (``_ProgressRelay``).
PROGRESS_BACKLOG = 64

#: Camera pose in the TCP frame of a sensor with no spec on record: 93 mm behind the apex, looking
#: along TCP +z ([x,y,z,rx,ry,rz] m + rotation vector, docs/architecture.md).
NOMINAL_CAMERA_IN_TCP = (0.0, 0.0, -0.093, 0.0, 0.0, 0.0)


def object_records(objects) -> list[dict]:
    """The ``SessionWriter`` object dicts of placed bench objects (name, fixture pose, mesh, primitive)."""
    return [
        {
            "name": o.name,
            "fixture_pose": np.asarray(o.fixture_pose, dtype=np.float64),
            "mesh_sha256": o.mesh_sha256,
            "primitive": o.primitive or {},
            "vertices": np.asarray(o.mesh.vertices, dtype=np.float32),
            "faces": np.asarray(o.mesh.faces, dtype=np.int32),
        }
        for o in objects
    ]


def session_metadata(bench, objects) -> dict:
    """Keyword arguments of ``SessionWriter`` for a session recorded on a started ``bench``:
    ``SessionWriter(path, **session_metadata(bench, plan.objects), resume=...)``.

    Simulated benches store their full ``SensorSpec``; a real sensor stores its serial and the
    nominal camera pose (its measured spec lives in the sensor registry)."""
    spec = getattr(getattr(bench, "sim", None), "spec", None)
    return {
        "sensor_serial": bench.sensor_serial,
        "sensor_spec": spec.to_dict() if spec is not None else {"serial": bench.sensor_serial},
        "intrinsics": dict(bench.intrinsics),
        "camera_in_tcp": list(spec.camera_in_tcp) if spec is not None else list(NOMINAL_CAMERA_IN_TCP),
        "simulated": bool(bench.simulated),
        "objects": object_records(objects),
        "host_clock_start": bench.started_at,
    }


def plan_bench_collection(bench, settings: PlanSettings) -> CollectionPlan:
    """The pose plan over ``bench``'s objects, within its safety limits, at its arm's motion settings."""
    return plan_collection(bench.objects, bench.limits, settings, bench.arm.settings)


def remaining_stops(plan: CollectionPlan, completed_pose_ids, referenced) -> list[tuple]:
    """What a run of ``plan`` still has to record, given the pose ids a file holds complete and the
    plan object indices ``referenced`` whose no-contact reference it holds: ``(stop, poses left,
    whether the reference is recorded)`` for every object stop with anything left (empty: done)."""
    stops = [(stop, [p for p in plan.poses_of(stop.object_index) if p.pose_id not in completed_pose_ids],
              stop.object_index in referenced) for stop in plan.stops]
    return [(stop, poses, has_reference) for stop, poses, has_reference in stops if poses or not has_reference]


def open_collection_writer(path, bench, plan: CollectionPlan, resume: bool) -> SessionWriter:
    """The ``SessionWriter`` of a collection: ``bench``'s metadata and ``plan``'s settings (root attr
    ``collection_plan``; a resumed file must hold the same plan, else ``InputError``)."""
    return SessionWriter(path, **session_metadata(bench, plan.objects), resume=resume,
                         collection_plan=plan.describe())


@dataclass
class CollectionResult:
    """What a run did. ``frames``: frames queued to the writer by this run; ``dropped``: frames
    missing from the camera's sequence numbers (a timestamp that does not increase is a
    ``camera-clock`` fault of the camera driver); ``duration_s``: bench-clock time of the run."""

    frames: int = 0
    dropped: int = 0
    poses_done: list[int] = field(default_factory=list)
    poses_without_contact: list[int] = field(default_factory=list)
    duration_s: float = 0.0
    stopped: bool = False


class _ProgressRelay(threading.Thread):
    """Calls ``callback(**report)`` in its own thread, in order, for each report ``post``-ed by the
    recorder, which never waits on it: a display that blocks (a terminal paused with Ctrl-S, whose
    writes then wait) delays only itself (was: the recorder waited in the callback, the camera and the
    pressure board unwatched while the arm pressed on). Over ``PROGRESS_BACKLOG`` pending reports the
    oldest are dropped. An exception of the callback ends the relay, is kept in ``error`` and handed
    to ``on_error`` at once (the recorder's, which stops the arm: was, at the recorder's next frame,
    0.13 s later on a loaded machine), and the recorder raises it."""

    def __init__(self, callback: Callable[..., None], on_error: Callable[[BaseException], None]):
        super().__init__(name="collection-progress", daemon=True)
        self.callback = callback
        self.on_error = on_error
        self.error: BaseException | None = None
        self._pending: collections.deque = collections.deque(maxlen=PROGRESS_BACKLOG)
        self._wake = threading.Condition()
        self._closing = False

    def post(self, report: dict) -> None:
        with self._wake:
            self._pending.append(report)
            self._wake.notify()

    def run(self) -> None:
        while True:
            with self._wake:
                while not self._pending and not self._closing:
                    self._wake.wait()
                if not self._pending:
                    return
                report = self._pending.popleft()
            try:
                self.callback(**report)
            except BaseException as err:  # noqa: BLE001 - raised by the recorder
                self.error = err
                self.on_error(err)
                return

    def close(self, timeout_s: float = 1.0) -> None:
        """Deliver the pending reports and end, waiting at most ``timeout_s`` for a blocked display
        (its thread then delivers them once the display takes them)."""
        with self._wake:
            self._closing = True
            self._wake.notify()
        if self.is_alive():
            self.join(timeout_s)


@dataclass(frozen=True)
class _Stamp:
    """What the arm is doing now: plan object index (-1 = none), pose id, phase value, pose index."""

    object_index: int = -1
    pose_id: int = -1
    phase: int = sf.PHASE_FREE
    pose_index: int = -1


class _Recorder(threading.Thread):
    """Drains camera frames, arm samples and pressure readings into the writer (see module doc)."""

    def __init__(self, bench, plan: CollectionPlan, writer: SessionWriter, progress_callback, result: CollectionResult):
        super().__init__(name="collection-recorder", daemon=True)
        self.bench = bench
        self.plan = plan
        self.writer = writer
        self.progress = _ProgressRelay(progress_callback, self.stop_on) if progress_callback is not None else None
        self.result = result
        self.stamp = _Stamp()  # the latest stamp (what the arm is doing now)
        self._timeline_t: list[float] = [-np.inf]  # bench-clock start time of each stamp
        self._timeline: list[_Stamp] = [self.stamp]
        self._timeline_lock = threading.Lock()
        self._recent_arm: collections.deque = collections.deque(maxlen=ARM_HISTORY)
        self.error: BaseException | None = None
        self.halt = threading.Event()
        self._last_seq: int | None = None
        self._last_report = 0.0
        self._reported_stamp: _Stamp | None = None
        self.beat = bench.clock()  # bench time (s) at which the loop last began: _watch_recorder
        self.halted_at = np.inf  # bench time (s) of the halt (_end_recording): the frames to drain
        self._error_lock = threading.Lock()

    def stop_on(self, err: BaseException) -> None:
        """Keep ``err`` as the recorder's error unless it has one and, if kept and a fault, stop the
        running motion with it (``arm.abort``). An exception other than a device fault (a frame of
        another shape, a failing progress callback) becomes a ``recorder`` fault: the arm must not go
        on unrecorded and unwatched (was: the phase ran to its end, then a traceback)."""
        if isinstance(err, Exception) and not isinstance(err, HardwareFault):
            log.debug("recorder thread failed", exc_info=err)
            wrapped = HardwareFault(RECORDER_FAULT, f"recorder: stopped recording ({type(err).__name__}: {err})")
            wrapped.__cause__, err = err, wrapped
        if self.fail(err) and isinstance(err, HardwareFault):
            self.bench.arm.abort(err)  # the running motion stops now and raises it

    def fail(self, err: BaseException) -> bool:
        """Keep ``err`` as the recorder's error unless it has one; whether it was kept."""
        with self._error_lock:
            if self.error is not None:
                return False
            self.error = err
            return True

    def set_stamp(self, stamp: _Stamp, t: float) -> None:
        """``stamp`` is under way from bench-clock time ``t`` (s) on."""
        with self._timeline_lock:
            self._timeline_t.append(t)
            self._timeline.append(stamp)
            self.stamp = stamp

    def _stamp_at(self, t: float) -> _Stamp:
        with self._timeline_lock:
            i = max(bisect.bisect_right(self._timeline_t, t) - 1, 0)
            stamp = self._timeline[i]
            del self._timeline_t[:i], self._timeline[:i]  # frames arrive in time order
            return stamp

    def _arm_pose_at(self, t: float) -> np.ndarray:
        """TCP pose (6,) at bench time ``t``: between the two arm samples around it
        (``collect.transforms.interpolate_poses``; was: the nearest one, up to half a sample period
        off), else the sample nearest it (samples are in time order)."""
        after = None
        for sample in reversed(self._recent_arm):
            if sample.t <= t:
                if after is None:  # newer than every sample drained so far
                    return sample.tcp_pose
                return interpolate_poses(t, [sample.t, after.t], [sample.tcp_pose, after.tcp_pose])[0]
            after = sample
        return after.tcp_pose if after is not None else self.bench.arm.state().tcp_pose

    def run(self) -> None:
        try:
            while not self.halt.is_set():
                self.beat = self.bench.clock()
                if self.progress is not None and self.progress.error is not None:
                    raise self.progress.error
                frame = self.bench.camera.get_frame(FRAME_TIMEOUT_S)
                self._write_streams()
                self._write_frame(frame)
                self._check_pressure()
                self._report()
            self._drain_frames(self.halted_at)
        except BaseException as err:  # noqa: BLE001 - handed to the main thread
            self.stop_on(err)
        finally:
            try:
                self._write_streams()
            except BaseException as err:  # noqa: BLE001
                self.fail(err)

    def _check_pressure(self) -> None:
        """The pressure board's fault checks. On its fault the arm is stopped at once, then the frames
        the camera captured until the fault was found are recorded: the camera still works (was: those
        a recorder lagging on a loaded machine had not taken yet were dropped, up to its queue's 0.18 s)."""
        try:
            self.bench.pressure.check()
        except HardwareFault as fault:
            found_at = self.bench.clock()
            if self.fail(fault):
                self.bench.arm.abort(fault)  # the running motion stops now and raises it
            self._drain_frames(found_at)
            raise

    def _drain_frames(self, until: float) -> None:
        """After the halt (or a pressure fault): record the frames the camera captured until bench time
        ``until`` (s) that are still in its queue, a recorder that lagged behind on a loaded machine
        (was: dropped, and with them the frames of a fault's last moments: a protective stop's retract
        had none on file). Ends at the first later frame, or when none comes within ``FRAME_TIMEOUT_S``."""
        while True:
            try:
                frame = self.bench.camera.get_frame(FRAME_TIMEOUT_S)
            except HardwareFault:  # none left: a camera silent now is nothing the run still needs
                return
            if frame.t_host > until:
                return
            self._write_streams()  # the arm samples around it (was: none after the halt, a stale pose)
            self._write_frame(frame)

    def write_remaining_streams(self) -> None:
        """After the thread ended: queue the arm samples and pressure readings still pending."""
        try:
            self._write_streams()
        except HardwareFault:  # the writer failed; its close() raises that failure (said once, by the run)
            pass

    def _write_frame(self, frame) -> None:
        stamp = self._stamp_at(frame.t_host)
        if self._last_seq is not None and frame.seq != self._last_seq + 1:
            self.result.dropped += max(0, frame.seq - self._last_seq - 1)
        self._last_seq = frame.seq
        object_index = self.writer.object_indices[stamp.object_index] if stamp.object_index >= 0 else -1
        self.writer.append_frame(
            frame.ir, frame.depth, frame.t_device, frame.t_host, frame.seq, object_index, stamp.pose_id,
            stamp.phase, self._arm_pose_at(frame.t_host), true_depth=frame.true_depth,
        )
        self.result.frames += 1

    def _write_streams(self) -> None:
        for sample in self.bench.arm.drain_states():
            self.writer.append_arm(sample.t, sample.tcp_pose, sample.tcp_wrench)
            self._recent_arm.append(sample)
        for reading in self.bench.pressure.drain():
            self.writer.append_pressure(reading.t, reading.hpa)

    def _report(self, force: bool = False) -> None:
        if self.progress is None:
            return
        now = time.monotonic()
        stamp = self.stamp
        if not force and stamp == self._reported_stamp and now - self._last_report < 1.0 / PROGRESS_HZ:
            return
        self._last_report, self._reported_stamp = now, stamp
        arm = self.bench.arm.state()
        reading = self.bench.pressure.latest()
        name = self.plan.objects[stamp.object_index].name if stamp.object_index >= 0 else ""
        stopping = stamp.phase == sf.PHASE_RETRACT and stamp.pose_id < 0  # the safe stop's (``_safe_stop``)
        self.progress.post(dict(
            object_name=name,
            pose_index=stamp.pose_index,
            poses_per_object=self.plan.settings.poses_per_object,
            phase=STOPPING_PHASE if stopping else sf.PHASE_NAMES[stamp.phase],
            frames=self.writer.n_frames,
            force_n=float(np.linalg.norm(arm.tcp_wrench[:3])) if arm is not None else 0.0,
            pressure_hpa=float(reading.hpa) if reading is not None else float("nan"),
        ))


def _watch_recorder(recorder: _Recorder) -> None:
    """Until the recorder halts: a recorder whose loop has not begun again for ``RECORDER_STALL_S``
    of bench time (blocked in the writer's full queue: the session file's disk stalled) fails with a
    ``recorder`` fault that stops the arm (``Arm.abort``), as a camera or pressure-board fault would."""
    bench = recorder.bench
    while not recorder.halt.wait(RECORDER_STALL_S / 8):
        blocked_s = bench.clock() - recorder.beat
        if blocked_s > RECORDER_STALL_S:
            fault = HardwareFault(RECORDER_FAULT, f"recorder: blocked for {blocked_s:.1f} s, no frame recorded "
                                                  "(is the session file's disk stalled?)")
            if recorder.fail(fault):
                bench.arm.abort(fault)
            return


def run_collection(
    bench,
    plan: CollectionPlan,
    writer: SessionWriter,
    progress_callback: Callable[..., None] | None = None,
    stop_event: threading.Event | None = None,
) -> CollectionResult:
    """Run ``plan`` on ``bench`` (a ``collect.bench.Bench``), recording into ``writer``.

    ``progress_callback(object_name, pose_index, poses_per_object, phase, frames, force_n,
    pressure_hpa)`` is called with keyword arguments from a thread of its own (the fields of
    ``calibrate.commission_events.CollectionProgress``; ``_ProgressRelay``); should it block, the
    recording goes on, and its reports wait (the oldest dropped).
    Poses already completed in the file (``writer.completed_pose_ids``, after ``resume``) and
    reference frames already recorded (``writer.referenced_objects``) are skipped; with nothing
    left, nothing moves and nothing is recorded.
    Raises what the bench raised (``HardwareFault``, ``KeyboardInterrupt``) after a safe stop.
    """
    result = CollectionResult()
    recorder = _Recorder(bench, plan, writer, progress_callback, result)
    stop_event = stop_event or threading.Event()
    arm, s, m = bench.arm, plan.settings, plan.motion
    arm.stop_on(stop_event)  # a stop mid-motion halts the arm within one state sample
    t_start = arm.state().t

    def enter(stamp: _Stamp) -> None:
        if recorder.error is not None:
            raise recorder.error
        if stop_event.is_set():
            raise StopRequested("collection: stopped by the operator")
        recorder.set_stamp(stamp, bench.clock())

    referenced = {oi for oi, file_index in enumerate(writer.object_indices) if file_index in writer.referenced_objects}
    stops = remaining_stops(plan, writer.completed_pose_ids, referenced)
    if not stops:
        return result
    if recorder.progress is not None:
        recorder.progress.start()
    recorder.start()
    threading.Thread(target=_watch_recorder, args=(recorder,), name="collection-recorder-watchdog",
                     daemon=True).start()
    try:
        for stop, poses, has_reference in stops:
            oi = stop.object_index
            enter(_Stamp())
            arm.travel_to(stop.travel_pose, m.travel_speed, m.accel)  # a run's first move starts anywhere
            arm.move_to(stop.reference_pose, m.travel_speed, m.accel)
            if not has_reference:
                enter(_Stamp(oi, -1, sf.PHASE_FREE))
                arm.hold(s.reference_s)
            for pose in poses:
                k = pose.index_in_object
                enter(_Stamp(oi, pose.pose_id, sf.PHASE_APPROACH, k))
                arm.move_to(pose.above_pose, m.travel_speed, m.accel)
                contact = arm.move_until_contact(
                    speed=m.approach_speed, force_threshold_n=m.contact_force_n, max_travel_m=pose.approach_travel_m
                )
                if contact is not None:
                    enter(_Stamp(oi, pose.pose_id, sf.PHASE_PRESS, k))
                    arm.press(force_n=press_target_n(contact, pose.press_force_n, s.max_press_force_n),
                              speed=m.press_speed)
                    enter(_Stamp(oi, pose.pose_id, sf.PHASE_HOLD, k))
                    arm.hold(s.hold_s)
                else:
                    log.warning("pose %d on %s: no contact within %.1f mm", pose.pose_id, stop.name,
                                1e3 * pose.approach_travel_m)
                    result.poses_without_contact.append(pose.pose_id)
                enter(_Stamp(oi, pose.pose_id, sf.PHASE_RETRACT, k))
                arm.retract(retract_speed(m))
                if contact is not None:
                    result.poses_done.append(pose.pose_id)
            enter(_Stamp())
            arm.move_to(stop.travel_pose, m.travel_speed, m.accel)
        enter(_Stamp())
    except StopRequested:
        result.stopped = True
        _safe_stop(bench, recorder)
    except BaseException as err:
        # a fault's stop: a signal now is only acknowledged (a Ctrl-C's own stop acknowledges repeats
        # already), until the recording has ended (was: a Ctrl-C there replaced the fault with exit 130)
        with stop_signals_handled(acknowledge_stop, INTERRUPTS):
            _safe_stop(bench, recorder)
            _end_recording(recorder)
        if isinstance(err, HardwareFault) and recorder.error is not None and err is not recorder.error \
                and arm.fault is recorder.error:
            # the device fault came first and the arm's error followed from it: report the cause (not
            # when the arm's own fault came first, and the camera failed during its safe stop)
            raise recorder.error from err
        raise
    finally:
        _end_recording(recorder)
        result.duration_s = float(arm.state().t - t_start)
    if recorder.error is not None and not result.stopped:
        raise recorder.error
    return result


def press_target_n(contact, added_n: float, cap_n: float) -> float:
    """Force (N) a press aims for: the force along the pressing axis at first contact (``contact``,
    an ``ArmState``) plus ``added_n``, at most ``cap_n``."""
    return min(max(contact.pressing_force_n(), 0.0) + added_n, cap_n)


def _end_recording(recorder: _Recorder) -> None:
    """Stop the recorder thread, once it has recorded the frames captured until now, and queue what
    it left (e.g. the safe-stop retract after the camera failed); safe to repeat."""
    if not recorder.halt.is_set():
        recorder.halted_at = recorder.bench.clock()
    recorder.halt.set()
    recorder.join()
    recorder.write_remaining_streams()
    if recorder.progress is not None:
        recorder.progress.close()


def _safe_stop(bench, recorder: _Recorder) -> None:
    """Stop and retract the arm; never raises. Frames keep recording while the recorder runs (not
    after a camera or pressure-board fault, which ended it), as ``retract`` of no contact pose: a
    pose or a reference cut short is then not complete, and a resume records it again."""
    stamp = recorder.stamp
    recorder.set_stamp(_Stamp(stamp.object_index, -1, sf.PHASE_RETRACT, stamp.pose_index), bench.clock())
    try:
        bench.safe_stop()
    except (HardwareFault, InputError, OSError, RuntimeError) as err:
        log.error("safe stop incomplete: %s", err)
