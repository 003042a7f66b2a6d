"""The simulated bench shared by the three twins: clock, bubble scene, arm controller, faults.

``SimBench`` owns
* a ``SimClock`` (real time by default, ``speed`` times faster for tests);
* the ``BubbleSim`` scene (one sensor, the objects on the fixture plate);
* the simulated UR controller (``hw_mocks.fake_rtde.SimURController``) whose TCP trajectory
  places the bubble in the scene;
* the latest membrane solutions, shared by the twins;
* the fault schedule (``--sim-fault KIND@SECONDS``).

Physics budget: a solve costs ~10-50 ms (more on a loaded machine), far too slow for the arm's
125-500 Hz state reads, so nobody solves on demand. A physics thread (the "bubble") re-solves the
membrane at most ``spec.fps`` times a second (real time) when the pose moved, or every
``REST_REFRESH_S`` at rest (slow effects such as a leak), at the pose the arm's planned trajectory
reaches ``LOOKAHEAD_S`` later. Lock-step: while the arm moves, simulated time may not run more than
``LOOKAHEAD_S`` past the latest solution; on a slow or loaded machine the simulated clock slows
down instead of the physics falling behind the arm. Readers never block on a solve but one:
* the camera twin renders each frame, while the arm moves, from the stored solution made for the
  time nearest the frame's (of the latest two: the latest is made for up to ``LOOKAHEAD_S``
  ahead), and at rest from the latest, except where the arm has come to rest short of the pose
  that solution was made for (a guarded move or a stop ended the move early): it first solves at
  the rest pose (``frame_solution``);
* the arm's wrench and the board's pressure are the latest two solutions interpolated to the
  current pose along the direction of motion (extrapolated at most ``EXTRAPOLATE_MAX`` solve steps
  beyond), so a press ramps smoothly between solves and a stop short of the look-ahead pose
  interpolates back.
Pacing: the streaming twins (camera frames, pressure lines) announce the simulated time of their
next message (``pace``); simulated time may not run more than ``PACE_SLACK_S`` past the earliest
one, so a twin starved of CPU slows the simulation down instead of raising a false
``camera-stall`` or ``serial-timeout`` (a twin whose fault is injected keeps its pace: it skips
its messages but keeps time).
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
from dataclasses import dataclass

import numpy as np

from collect.errors import InputError
from collect.loop_thread import LoopThread
from collect.numbers import real_number

log = logging.getLogger(__name__)

#: Fault kinds ``--sim-fault`` accepts.
FAULT_KINDS = ("camera-stall", "serial-garbage", "serial-unplug", "pressure-frozen", "protective-stop", "force-spike")
#: How long each fault lasts once injected (s of simulated time); None = until the end.
FAULT_DURATION_S = {
    "camera-stall": None,
    "serial-garbage": 0.3,
    "serial-unplug": None,
    "pressure-frozen": None,
    "protective-stop": None,
    "force-spike": 0.25,
}
#: Force (N, base +z, i.e. pushing the sensor up) that ``force-spike`` adds to the wrench.
FORCE_SPIKE_N = 80.0
#: Re-solve period at rest (s of simulated time), see the module doc.
REST_REFRESH_S = 0.25
#: Pose change (m, rad) below which the latest solution still counts as "at this pose".
POSE_TOL_M = 2e-5
POSE_TOL_RAD = 2e-4
#: How far ahead (s) along the arm's planned trajectory the physics solves, and how far simulated
#: time may run past the latest solution while the arm moves (time pauses beyond: lock-step).
LOOKAHEAD_S = 0.03
#: Farthest extrapolation of the wrench/pressure, in units of the last solve step, and the shortest
#: step (m) worth extrapolating along (shorter steps would amplify the solver's tolerance).
EXTRAPOLATE_MAX = 2.0
EXTRAPOLATE_MIN_STEP_M = 1e-4
#: How far (s) simulated time may run past the next message a streaming twin owes (see Pacing).
PACE_SLACK_S = 0.1


@dataclass(frozen=True)
class SimFault:
    """A scheduled fault: ``kind`` (one of ``FAULT_KINDS``) starting at ``at_s`` s of simulated time."""

    kind: str
    at_s: float

    @property
    def duration_s(self) -> float | None:
        return FAULT_DURATION_S[self.kind]

    def active(self, t: float) -> bool:
        """Whether the fault is in effect at simulated time ``t``."""
        return t >= self.at_s and (self.duration_s is None or t < self.at_s + self.duration_s)

    def __str__(self) -> str:
        return f"{self.kind}@{self.at_s:g}"


def parse_sim_fault(text: str) -> SimFault:
    """Parse ``KIND@SECONDS`` (e.g. ``camera-stall@12.5``, ``force-spike@1e1``); raises ``InputError``
    for anything else: no ``@``, an unknown kind, seconds that are no number, or not finite and >= 0
    (was: exponents refused as malformed, and 400 digits taken as inf, a fault that never came)."""
    kind, at, seconds_text = str(text).partition("@")
    kind, seconds_text = kind.strip(), seconds_text.strip()
    if not at or not kind or not seconds_text:
        raise InputError(f"--sim-fault '{text}': expected KIND@SECONDS, e.g. camera-stall@12.5")
    if kind not in FAULT_KINDS:
        raise InputError(f"--sim-fault '{text}': unknown fault '{kind}' (one of {', '.join(FAULT_KINDS)})")
    try:
        seconds = float(seconds_text)
    except ValueError:
        seconds = float("nan")
    if not (real_number(seconds) and seconds >= 0.0):
        raise InputError(f"--sim-fault '{text}': SECONDS must be a number of seconds >= 0, got '{seconds_text}'")
    return SimFault(kind, seconds)


#: Speed factors of the simulated clock (1 = real time): lower gives a busy machine time to keep up.
SIM_SPEED_RANGE = (0.1, 100.0)


def check_sim_speed(speed) -> None:
    """Raise InputError unless ``speed`` is a number within ``SIM_SPEED_RANGE``."""
    lo, hi = SIM_SPEED_RANGE
    if not (real_number(speed) and lo <= speed <= hi):
        raise InputError(f"simulation speed {speed!r} must be within {lo:g}..{hi:g}")


class SimClock:
    """Simulated time in seconds since creation, running ``speed`` times faster than real time.

    ``limit`` (set by ``SimBench``): a lock-free callable giving the latest simulated time the
    clock may show, or None. When the clock would pass it, simulated time pauses (the pause is
    remembered, so time never jumps) until the limit moves on.
    """

    def __init__(self, speed: float = 1.0):
        check_sim_speed(speed)
        self.speed = float(speed)
        self._t0 = time.monotonic()
        self._paused = 0.0
        self._last = 0.0
        self._lock = threading.Lock()
        self.limit = None

    def now(self) -> float:
        limit = self.limit() if self.limit is not None else None
        with self._lock:
            t = (time.monotonic() - self._t0) * self.speed - self._paused
            if limit is not None and t > limit:
                self._paused += t - max(limit, self._last)
                t = max(limit, self._last)
            self._last = max(t, self._last)
            return self._last

    def __call__(self) -> float:
        return self.now()

    def sleep_until(self, t_sim: float, stop: threading.Event | None = None) -> bool:
        """Sleep until simulated time ``t_sim``; returns False when ``stop`` was set meanwhile."""
        while True:
            delay = (t_sim - self.now()) / self.speed
            if delay <= 0:
                return not (stop is not None and stop.is_set())
            if stop is None:
                time.sleep(min(delay, 0.05))
            elif stop.wait(min(delay, 0.05)):
                return False


@dataclass(frozen=True)
class _Solved:
    """One membrane solution: TCP ``pose`` (6,), simulated time ``t`` s, ``MembraneState``."""

    pose: np.ndarray
    t: float
    state: object


def _same_pose(a: np.ndarray, b: np.ndarray) -> bool:
    return bool(np.all(np.abs(a[:3] - b[:3]) < POSE_TOL_M) and np.all(np.abs(a[3:] - b[3:]) < POSE_TOL_RAD))


class SimBench:
    """One simulated bench: ``spec`` (SensorSpec), ``objects`` (placed BenchObjects), ``seed``,
    ``faults`` (SimFault list), ``speed`` (clock factor), ``start_pose`` (6,) the TCP pose the arm
    starts at (default: ``home_pose``, the safe pose above the middle of the plate; e.g. low beside
    an object, where a previous run left it), ``protective_force_n`` (N) of the simulated robot.
    Poses are m + rotation vector in the base frame.
    """

    def __init__(self, spec, objects, *, seed: int = 0, faults=(), speed: float = 1.0, start_pose=None,
                 protective_force_n: float = 150.0):
        from hw_mocks.bubble_sim import BubbleSim
        from hw_mocks.fake_rtde import SimURController

        self.spec = spec
        self.objects = list(objects)
        self.faults = list(faults)
        self.clock = SimClock(speed)
        self.sim = BubbleSim(spec, self.objects, seed)
        self.home_pose = default_home_pose(self.objects)
        self._lock = threading.Lock()
        self._solve_lock = threading.Lock()  # one solve at a time: the physics thread's or a frame's
        self.arm = SimURController(self, self.home_pose if start_pose is None else start_pose, protective_force_n)
        self._solved: list[_Solved] = []  # the last two solutions, oldest first
        self.solves = 0
        self.physics_failed = False
        self._paces: dict[str, float] = {}
        self._earliest_pace: float | None = None
        self._pace_lock = threading.Lock()
        self._solve_now()
        self.clock.limit = self._time_limit
        self._loop = LoopThread(self._physics, "sim-physics")

    def start(self) -> None:
        """Start the physics thread (idempotent)."""
        self._loop.start()

    def devices_streaming(self) -> None:
        """The bench's drivers read every twin from now on (``collect.bench.Bench.start``): a short
        fault (``FAULT_DURATION_S``) that would have ended by now starts now instead, as no driver could
        have seen it (was: lost without a word: ``--sim-fault force-spike@0.5`` at ``--sim-speed 20``
        came and went while the bench opened, and the run was accepted)."""
        now = self.now()
        for i, fault in enumerate(self.faults):
            if fault.duration_s is not None and fault.at_s + fault.duration_s <= now:
                self.faults[i] = dataclasses.replace(fault, at_s=now)
                log.warning("simulated bench: --sim-fault %s starts at %.2f s of simulated time instead: the bench's "
                            "devices were not read before then", fault, now)

    def stop(self) -> None:
        """Stop the physics thread; log each scheduled fault the run ended before (was: nothing said, and a
        ``--sim-fault camera-stall@100`` on a 4-second run looked like a fault that did not trip)."""
        if self._loop.running:  # (not after the physics thread failed: that failure is the run's fault)
            now = self.now()
            for fault in self.faults:
                if fault.at_s > now:
                    log.warning("simulated bench: --sim-fault %s did not happen: the bench closed at %.1f s of "
                                "simulated time (the seconds count from the bench's opening)", fault, now)
        self._loop.stop()

    def _solve_now(self) -> None:
        """Solve at the pose the arm's trajectory reaches ``LOOKAHEAD_S`` from now."""
        with self._solve_lock:
            t = self.now() + LOOKAHEAD_S
            pose = self.arm.pose_at(t)
            state = self.sim.solve(pose, t)
            with self._lock:
                self._solved = (self._solved + [_Solved(pose, t, state)])[-2:]
                self.solves += 1

    def pace(self, twin: str, t: float | None) -> None:
        """Streaming ``twin`` owes its next message at simulated time ``t`` s (None: it stopped)."""
        with self._pace_lock:
            if t is None:
                self._paces.pop(twin, None)
            else:
                self._paces[twin] = float(t)
            self._earliest_pace = min(self._paces.values(), default=None)

    def _time_limit(self) -> float | None:
        """The latest simulated time the clock may show, or None. While the arm moves, simulated
        time may not pass the latest solution by more than ``LOOKAHEAD_S`` (on a slow or loaded
        machine the simulation slows down instead of the wrench lagging the pose), nor the
        earliest streaming twin's next message by more than ``PACE_SLACK_S``. Lock-free (called
        by the clock)."""
        limits = []
        solved = self._solved[-1]
        if not self.physics_failed and solved.t < self.arm.moving_until():
            limits.append(solved.t + LOOKAHEAD_S)
        earliest_pace = self._earliest_pace
        if earliest_pace is not None:
            limits.append(earliest_pace + PACE_SLACK_S)
        return min(limits, default=None)

    def _physics(self) -> None:
        period_real = 1.0 / (float(self.spec.fps) * self.clock.speed)
        while not self._loop.stop_event.is_set():
            started = time.monotonic()
            t = self.now()
            last = self.latest()
            limit = self._time_limit()
            held = limit is not None and t >= limit - 1e-6
            if held or t - last.t >= REST_REFRESH_S or not _same_pose(last.pose, self.arm.pose_at(t + LOOKAHEAD_S)):
                try:
                    self._solve_now()
                except Exception:  # keep the bench alive: time must not stay paused on a dead solver
                    log.exception("simulated bubble: membrane solve failed; physics stopped")
                    self.physics_failed = True
                    return
            self._loop.stop_event.wait(max(0.0, period_real - (time.monotonic() - started)))

    def now(self) -> float:
        """Simulated time (s)."""
        return self.clock.now()

    def fault_active(self, kind: str, t: float | None = None) -> bool:
        """Whether a scheduled fault of ``kind`` is in effect at ``t`` (default: now)."""
        t = self.now() if t is None else t
        return any(f.kind == kind and f.active(t) for f in self.faults)

    def tcp_pose(self, t: float | None = None) -> np.ndarray:
        """TCP pose (6,) of the simulated arm at simulated time ``t`` (default: now)."""
        return self.arm.pose_at(self.now() if t is None else t)

    def latest(self) -> _Solved:
        """The latest membrane solution (pose, t, state)."""
        with self._lock:
            return self._solved[-1]

    def frame_solution(self, t: float | None = None) -> _Solved:
        """The membrane solution a camera frame taken at simulated time ``t`` (s; default now) shows.

        While the arm moves: of the latest two, the one made for the time nearest ``t`` (was: the
        latest, made for up to ``LOOKAHEAD_S`` ahead: during a 20 mm/s press the frames showed the
        membrane 0.17 mm deeper than the arm's pose at their time, median, up to 0.45). At rest: the
        latest, or, when the arm has come to rest short of the pose that solution was made for (a
        guarded move or a stop ended the move early), one solved at the rest pose first. Was: the
        first one or two frames of such a hold showed the membrane pressed up to the look-ahead
        deeper than the arm was (a dent of 677 pixels where the arm's pose gives 474), and the pose
        check's errors against the true pose were 0.6-0.75 mm there instead of 0.1 mm."""
        t = self.now() if t is None else t
        at_rest = self.arm.moving_until() <= t
        with self._lock:  # (at rest the nearest could be one from before the stop: a solve more per stop)
            solved = self._solved[-1] if at_rest else min(self._solved, key=lambda s: abs(s.t - t))
        if not self.physics_failed and at_rest and not _same_pose(solved.pose, self.arm.pose_at(t)):
            try:
                self._solve_now()
            except Exception:  # as in the physics thread: the frame shows the latest solution
                log.exception("simulated bubble: membrane solve failed; physics stopped")
                self.physics_failed = True
            solved = self.latest()
        return solved

    def _extrapolated(self, pose, value) -> np.ndarray:
        """``value(state)`` of the latest solution extrapolated to ``pose`` (6,) along the last step."""
        with self._lock:
            solved = list(self._solved)
        v2 = np.array(value(solved[-1].state), dtype=np.float64)  # a copy: callers add to it
        if len(solved) < 2:
            return v2
        step = solved[-1].pose[:3] - solved[0].pose[:3]
        norm2 = float(step @ step)
        if norm2 < EXTRAPOLATE_MIN_STEP_M ** 2:
            return v2
        s = float((np.asarray(pose, dtype=np.float64)[:3] - solved[-1].pose[:3]) @ step) / norm2
        v1 = np.asarray(value(solved[0].state), dtype=np.float64)
        return v2 + float(np.clip(s, -1.0, EXTRAPOLATE_MAX)) * (v2 - v1)

    def wrench(self, pose, t: float) -> np.ndarray:
        """Wrench (6,) N, N m on the sensor in the base frame at ``pose``, time ``t``, with any force spike."""
        w = self._extrapolated(pose, lambda st: st.wrench)
        if self.fault_active("force-spike", t):
            w[2] += FORCE_SPIKE_N
        return w

    def pressure_hpa(self, t: float) -> float:
        """Absolute bubble pressure (hPa) at time ``t`` with the TCP where the arm has it."""
        return float(self._extrapolated(self.tcp_pose(t), lambda st: st.pressure_hpa))


def default_home_pose(objects) -> np.ndarray:
    """TCP pose ``(6,)`` (m + rotvec, base frame) above the middle of the placed ``objects``, 80 mm over
    the tallest, pressing axis down."""
    from hw_mocks.objects import PLATE_X, PLATE_Z

    if objects:
        lo = np.min([o.bounds_base()[0] for o in objects], axis=0)
        hi = np.max([o.bounds_base()[1] for o in objects], axis=0)
        xy, top = 0.5 * (lo[:2] + hi[:2]), hi[2]
    else:
        xy, top = np.array([PLATE_X, 0.0]), PLATE_Z
    return np.array([xy[0], xy[1], top + 0.08, np.pi, 0.0, 0.0])
