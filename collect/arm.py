"""Arm driver: the pressing motions of the bench over ur_rtde-shaped interfaces.

``Arm`` drives any pair of objects with the ur_rtde method names and argument orders it uses:
``rtde_control.RTDEControlInterface`` / ``rtde_receive.RTDEReceiveInterface`` for a real UR
e-Series, or ``hw_mocks.fake_rtde.FakeRTDEControl`` / ``FakeRTDEReceive`` for the twin.

Calls made (the twin implements exactly these, a test checks them against the installed ur_rtde):
control ``moveL(pose, speed, acceleration, asynchronous)``, ``stopL(a, asynchronous)``,
``zeroFtSensor()``, ``setWatchdog(min_frequency)``, ``getStepTime()``, ``disconnect()``; receive
``getActualTCPPose()``, ``getActualTCPForce()``, ``getActualTCPSpeed()``, ``getSafetyStatusBits()``,
``getTimestamp()``, ``isConnected()``, ``disconnect()``. ur_rtde raises ``RuntimeError`` from a
call whose reconnect failed (the robot unreachable): every call is made through ``_LinkGuard``,
which turns that into ``HardwareFault('arm-disconnected')``, and ``stop`` never raises.

Poses are ``[x, y, z, rx, ry, rz]`` (m + rotation vector) of the TCP (the membrane apex) in the
base frame; wrenches ``[Fx, Fy, Fz, Tx, Ty, Tz]`` (N, N m) on the sensor in the base frame.
The pressing axis is the TCP +z axis.

A monitor thread samples pose and wrench at ``state_hz`` (125-500 Hz) on the bench clock, keeps
the arm stream for the recorder (``drain_states``), and watches two things in every sample:
the robot's safety stops (``getSafetyStatusBits``: a protective stop is
``HardwareFault('protective-stop')``, an emergency or safeguard stop, a safety violation or fault
``HardwareFault('safety-stop')``) and the measured force against ``SafetyLimits.force_limit_n``.
Each sample also kicks the controller's watchdog (``setWatchdog`` at ``watchdog_hz``, set when the
monitor starts and again before every move: ur_rtde restarts the control program when it
reconnects by itself, and a program stop removes every watchdog): should this host hang or the
link die mid-move, the robot stops by itself
instead of finishing an asynchronous move unsupervised. The kick is ``getStepTime()``, not
ur_rtde's ``kickWatchdog()``: the watchdog watches the command register, which any command
updates, and the control script that ur_rtde 1.6 uploads has no branch for ``kickWatchdog``'s
command (99). It takes 99 for an ordinary command that never reports done, and then leaves every
later ordinary command (``moveL``, ``zeroFtSensor``, ``stopL``) unprocessed until the host gives
up on it (3-300 s; read from the script in ``librtde.so.1.6``; the twin models it).
``getStepTime`` is one of the script's real-time commands, processed whatever else runs and
without a handshake to clear. A link that dies without closing its
socket leaves ur_rtde returning its last state with ``isConnected()`` still true: a controller
clock (``getTimestamp``) that has not moved for ``STALE_STATE_S`` of the bench clock is
``HardwareFault('arm-disconnected')`` too, not a force check on frozen values.
Over the limit it sends ``stopL`` at once and records ``HardwareFault('force-spike')`` when the
force jumped past the limit within one sample (by more than half the limit: a collision or a
sensor spike) or ``HardwareFault('force-limit')`` when it ramped up; the running motion raises
it. The first fault is sticky (``fault``, raised by every later motion), but the force stays
watched after it: once the force has fallen below ``FORCE_REARM_FRACTION`` of the limit, a new
excursion over the limit stops the arm again and is recorded as the latest fault. ``retract``
moves away after any recorded fault, a force fault included (the force is then still over the
limit), and ends on a new one on the way (a collision while retracting after a camera stall, say);
not after a protective stop, which only the operator can clear on the teach pendant.

A run's first move starts wherever the arm was left, maybe low beside an object: ``travel_to``
rises straight up to the travel height before moving across. A contact move zeroes the force
sensor, so it first checks that the bubble is free: a force already above
``MotionSettings.max_preload_n`` is ``HardwareFault('preload')`` (nothing zeroed, nothing moved).

The operator's stop (``stop_on(event)``: the stop key, Ctrl-C, a watchdog) is watched at every
sample as well: once the event is set the running motion sends ``stopL`` within one sample and
raises ``StopRequested``, and no motion but ``retract`` starts while it stays set.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np

from collect.errors import HOST_STALLED_FAULT, HardwareFault, InputError, StopRequested
from collect.frozen_heap import freeze_heap, thaw_heap
from collect.loop_thread import LoopThread
from collect.numbers import real_number
from collect.safety import (MAX_FORCE_LIMIT_N, MAX_TCP_ACCEL_M_S2, MAX_TCP_SPEED_M_S, SafetyLimits,
                            check_within_bounds, tool_z_axis)
from collect.transforms import linear_path_m, rotation_between_rad

#: Deceleration (m/s^2) of stopL when the arm must stop: short stopping distance, not a planned move.
STOP_DECEL_M_S2 = 4.0
#: A move counts as finished when the TCP is this close to the target (m, rad) and slower than this (m/s).
ARRIVAL_TOL_M = 2e-4
ARRIVAL_TOL_RAD = 2e-3
ARRIVAL_SPEED_M_S = 2e-3
#: Extra seconds (bench clock) allowed beyond the planned duration of a move before ``arm-timeout``,
#: and a real-time backstop (this many times the budget) for a simulated clock that runs slow.
MOVE_TIMEOUT_MARGIN_S = 2.0
REAL_TIME_SLACK = 10.0
#: After a force excursion the monitor watches for a new one once the force has fallen below this
#: fraction of the limit (hysteresis: sensor noise at the limit is not a string of new faults).
FORCE_REARM_FRACTION = 0.8
#: A retract stops when the force rises this fraction of the limit above the force it started with,
#: when that is over the limit (the hysteresis above keeps the monitor from seeing a collision then).
RETRACT_FORCE_RISE_FRACTION = 0.15
#: Slowest kick rate the controller's watchdog accepts (Hz; ``setWatchdog``), at most half the
#: monitor's rate: without a kick for 0.5 s (a hung host, a dead link) the robot stops its move. Not
#: shorter: a loaded host may hold the monitor thread back a tenth of a second.
WATCHDOG_HZ = 2.0
#: ``getSafetyStatusBits()`` bits that halt the robot (ur_rtde; bits 0 and 1 are normal and
#: reduced mode), with their names.
SAFETY_STOP_BITS = {2: "protective stop", 3: "recovery mode", 4: "safeguard stop", 5: "system emergency stop",
                    6: "robot emergency stop", 7: "emergency stop", 8: "safety violation", 9: "safety fault",
                    10: "stopped due to safety"}
PROTECTIVE_STOP_BIT = 2
#: The controller publishes its state at 125-500 Hz: a controller time (``getTimestamp``) that has
#: not moved for this long (s, bench clock) is a dead link.
STALE_STATE_S = 0.25
#: Longest wait (s, real time) for another thread's command to the robot to return before a command
#: or a stop gives up on the control link: ur_rtde waits up to 300 s for the "done" of a command
#: (``stopL`` too), which a dead link that keeps its socket never brings.
CONTROL_WAIT_S = 2.0


def safety_stops(bits: int) -> list[str]:
    """Names of the halting safety states set in ``getSafetyStatusBits()``'s ``bits`` (empty: it may move)."""
    return [name for bit, name in SAFETY_STOP_BITS.items() if int(bits) >> bit & 1]


def safety_stop_fault(bits: int, where: str) -> HardwareFault:
    """The fault of a robot halted by ``bits`` (``safety_stops`` not empty); ``where`` leads the
    message, e.g. "arm: robot is in"."""
    if int(bits) >> PROTECTIVE_STOP_BIT & 1:
        return HardwareFault("protective-stop", f"{where} protective stop; clear it on the teach pendant")
    return HardwareFault("safety-stop", f"{where} a safety stop ({', '.join(safety_stops(bits))}); release the "
                                        "emergency stop or close the safeguard, then reset it on the teach pendant")


class _LinkGuard:
    """An ur_rtde interface whose calls raise ``HardwareFault('arm-disconnected')`` where ur_rtde
    raises ``RuntimeError`` (its reconnect to an unreachable robot failed; was: a traceback that
    took the place of the run's fault, and a monitor that died with it)."""

    def __init__(self, interface):
        self._interface = interface

    def __getattr__(self, name: str):
        method = getattr(self._interface, name)

        def guarded(*args, **kwargs):
            try:
                return method(*args, **kwargs)
            except RuntimeError as err:
                raise HardwareFault("arm-disconnected",
                                    f"arm: {name} failed, the robot cannot be reached ({err})") from None

        return guarded


@dataclass(frozen=True)
class ArmState:
    """One sample of the arm: ``t`` s on the bench clock, ``tcp_pose`` (6,) m + rotvec, ``tcp_wrench`` (6,) N, N m."""

    t: float
    tcp_pose: np.ndarray
    tcp_wrench: np.ndarray

    def pressing_force_n(self, axis=None) -> float:
        """Contact force (N) opposing motion along the unit ``axis`` (3,) in the base frame
        (default: the pressing axis, TCP +z)."""
        axis = tool_z_axis(self.tcp_pose) if axis is None else axis
        return float(-np.dot(self.tcp_wrench[:3], axis))


#: Most monitor samples per second of real time: a simulated clock running fast is sampled at
#: ``state_hz`` of its time up to this rate (``Arm``).
MAX_MONITOR_WALL_HZ = 1000.0
#: Arm state sampling rates accepted (Hz). The guarded approach, the press to a force and the force
#: limit act on these samples while the asynchronous moveL runs on between them, so the rate bounds
#: how far a move overshoots a force: at the approach's 0.05 m/s, 0.4 mm a sample at 125 Hz (a
#: simulated box press peaked at 6.4 N; at 10 Hz, 16 N past a 15 N cap; at 2 Hz, 92 N).
STATE_HZ_RANGE = (125.0, 500.0)

#: Deepest press (m) a ``motion.max_press_depth_m`` may allow: 30 mm, about the height of the
#: bubble's dome (30-50 mm; ``bubble sim preview --press-mm`` stops there too); deeper, the object
#: meets the rigid frame behind the membrane.
MAX_PRESS_DEPTH_M = 0.03
#: Longest guarded approach (``max_contact_travel_m``) and retract (``retract_m``), m: 10 cm, a few
#: times the 5 cm and 3 cm defaults; a contact this far off means a wrong plate pose, not a far object.
MAX_CONTACT_TRAVEL_M = 0.10
MAX_RETRACT_M = 0.10
#: field -> (upper bound, unit) of every ``MotionSettings`` value. The speeds, the acceleration and
#: the forces share the bounds of ``SafetyLimits`` (see ``collect.safety``); a bench's own limits,
#: usually lower, are then checked against each motion when the arm is built (``check_motion_settings``).
MOTION_BOUNDS = {
    "travel_speed": (MAX_TCP_SPEED_M_S, "m/s"),
    "approach_speed": (MAX_TCP_SPEED_M_S, "m/s"),
    "press_speed": (MAX_TCP_SPEED_M_S, "m/s"),
    "accel": (MAX_TCP_ACCEL_M_S2, "m/s^2"),
    "contact_force_n": (MAX_FORCE_LIMIT_N, "N"),
    "max_preload_n": (MAX_FORCE_LIMIT_N, "N"),
    "max_contact_travel_m": (MAX_CONTACT_TRAVEL_M, "m"),
    "max_press_depth_m": (MAX_PRESS_DEPTH_M, "m"),
    "retract_m": (MAX_RETRACT_M, "m"),
}


@dataclass(frozen=True)
class MotionSettings:
    """Speeds (m/s), acceleration (m/s^2), force (N) and distances (m) of the pressing motions: the
    arm's defaults and the speeds of every collection motion (a bench's ``motion`` settings)."""

    travel_speed: float = 0.25
    approach_speed: float = 0.05  # guarded approach, until the contact force
    press_speed: float = 0.02
    accel: float = 1.0
    contact_force_n: float = 0.4  # force that ends the guarded approach
    #: force (N) above which a contact move finds the bubble already touching something (read
    #: against the previous zero, before zeroing): well above the contact force, so that the F/T
    #: sensor's drift and payload error after a reorientation do not trip it
    max_preload_n: float = 2.0
    max_contact_travel_m: float = 0.05
    max_press_depth_m: float = 0.015
    retract_m: float = 0.03

    def __post_init__(self):
        check_within_bounds("motion", self, MOTION_BOUNDS)  # every field has its bound there


def move_duration_s(distance_m: float, speed: float, accel: float) -> float:
    """Duration (s) of a trapezoidal move over ``distance_m`` with the given speed cap and acceleration."""
    if distance_m <= 0:
        return 0.0
    if distance_m < speed * speed / accel:  # triangular profile
        return 2.0 * np.sqrt(distance_m / accel)
    return distance_m / speed + speed / accel


def backoff_direction(wrench, min_force_n: float) -> np.ndarray | None:
    """Unit direction (3,) in the base frame that moves the sensor away from what pushes on it: the
    force of ``wrench`` (6,) N, N m, its downward part (base -z, toward the plate) dropped. None when
    that force is at most ``min_force_n`` N (nothing is touched, or only pulled down on)."""
    force = np.asarray(wrench, dtype=float)[:3].copy()
    force[2] = max(force[2], 0.0)
    magnitude = float(np.linalg.norm(force))
    return force / magnitude if magnitude > min_force_n else None


def retract_speed(settings: MotionSettings) -> float:
    """Speed (m/s) of ``Arm.retract`` (after each press and in the safe stop): twice the approach speed."""
    return 2.0 * settings.approach_speed


def check_motion_settings(settings: MotionSettings, limits: SafetyLimits) -> None:
    """Every speed of ``settings`` (the retract's included), its acceleration and its contact force
    against ``limits``; ``SafetyViolation`` otherwise."""
    for speed in (settings.travel_speed, settings.approach_speed, settings.press_speed, retract_speed(settings)):
        limits.check_motion(speed, settings.accel)
    limits.check_force(settings.contact_force_n)
    limits.check_force(settings.max_preload_n)


class Arm:
    """Pressing motions with safety checks over ur_rtde-shaped ``control`` / ``receive`` objects.

    clock: seconds on the bench clock (``time.monotonic`` for real hardware, the simulated clock
    for the twin); every ``ArmState.t`` is on it. ``state_hz``: monitor samples per second of that
    clock: a clock with a ``speed`` (the simulated one, ``speed`` x real time) is sampled that much
    more often in real time, up to ``MAX_MONITOR_WALL_HZ`` (was: ``state_hz`` of real time, so at
    ``--sim-speed 4`` a quarter of the samples, and presses overshot their force: 9.3 N for 6.4 N).
    """

    def __init__(self, control, receive, limits: SafetyLimits, *, settings: MotionSettings = MotionSettings(),
                 clock: Callable[[], float] = time.monotonic, state_hz: float = 125.0):
        lo, hi = STATE_HZ_RANGE
        if not (real_number(state_hz) and lo <= state_hz <= hi):
            raise InputError(f"arm: state rate {state_hz!r} Hz is outside {lo:g}..{hi:g} Hz")
        check_motion_settings(settings, limits)
        self._ctl = _LinkGuard(control)
        self._rcv = _LinkGuard(receive)
        self.watchdog_hz = min(WATCHDOG_HZ, state_hz / 2.0)
        self.limits = limits
        self.settings = settings
        self.clock = clock
        #: real seconds between samples: the bench clock's period at its speed
        self._wall_period = max(1.0 / (state_hz * float(getattr(clock, "speed", 1.0))), 1.0 / MAX_MONITOR_WALL_HZ)
        self._ctl_lock = threading.Lock()
        self._cond = threading.Condition()
        self._latest: ArmState | None = None
        self._stream: list[ArmState] = []
        self._fault: HardwareFault | None = None  # the first recorded fault (sticky)
        self._latest_fault: HardwareFault | None = None  # the last recorded fault (ends a retract)
        self._retract_pose: np.ndarray | None = None
        self._retracting = False  # a retract is under way (``abort`` does not stop it)
        self._stop_request: threading.Event | None = None
        self._monitor_loop = LoopThread(self._monitor, "arm-monitor")
        self._monitor_ended = False  # the monitor thread returned (a fault, or close)
        self._monitor_stops_arm = False  # it returned on a fault, and sends the stop itself
        self._kicked_at: float | None = None  # time.monotonic() of the watchdog's last kick (or arming)
        #: longest time (s, host clock, as the robot's watchdog counts) the watchdog went without a kick
        self.longest_kick_gap_s = 0.0
        self._heap_frozen = False  # this arm froze the heap (``collect.frozen_heap``) and thaws it on close

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> None:
        """Start the monitor thread (idempotent); blocks until the first sample is in. Raises the
        fault the monitor ended on when it returned by itself (a lost link, a failed read): no motion
        is sent without it (was: sent, unwatched, and raised only at its first sample, unstopped)."""
        if self._monitor_loop.running:
            with self._cond:  # the monitor records its end and its fault together (``_end_monitor``)
                ended, fault = self._monitor_ended, self._latest_fault
            if ended:
                raise fault or HardwareFault("arm-monitor", "arm: the state monitor has ended")
            return
        if not self._heap_frozen:  # before the watchdog runs: no full garbage collection outlasts its 0.5 s
            freeze_heap()
            self._heap_frozen = True
        with self._commanding():
            self._arm_watchdog()
            self._kicked_at = time.monotonic()
        self._monitor_ended = self._monitor_stops_arm = False
        self._monitor_loop.start()
        self._next_sample(timeout_s=2.0)

    def close(self) -> None:
        """Stop the monitor and disconnect both interfaces; the heap this arm froze is thawed."""
        self._monitor_loop.stop()
        if self._heap_frozen:
            thaw_heap()
            self._heap_frozen = False
        for iface in (self._ctl, self._rcv):
            iface.disconnect()

    # ------------------------------------------------------------------ monitoring
    def _read(self) -> ArmState:
        t = self.clock()  # stamped next to the pose read: the wrench read after it may wait on a lock
        pose = np.asarray(self._rcv.getActualTCPPose(), dtype=np.float64)
        wrench = np.asarray(self._rcv.getActualTCPForce(), dtype=np.float64)
        return ArmState(t, pose, wrench)

    def _monitor(self) -> None:
        try:
            self._watch()
        except HardwareFault as fault:  # the link lost mid-sample
            self._stop_apart()
            self._end_monitor(fault)
        except Exception as err:  # a dead monitor must not leave a motion unsupervised
            self._stop_apart()
            self._end_monitor(HardwareFault("arm-monitor", f"arm: state monitor failed ({type(err).__name__}: {err})"))
        finally:
            self._end_monitor(None)

    def _stop_apart(self) -> None:
        """The monitor's stop, from a thread of its own: on a dead link its stopL waits for a "done" that
        never comes (ur_rtde: 300 s). Returns once that thread holds the command lock (or has given up
        on it, ``CONTROL_WAIT_S``): every command after it queues behind it and gives up in turn (was:
        a motion's or the safe stop's stopL that took the lock first waited out the 300 s)."""
        queued = threading.Event()
        threading.Thread(target=self._send_stop, args=(queued,), name="arm-stop", daemon=True).start()
        queued.wait()

    def _end_monitor(self, fault: HardwareFault | None) -> None:
        """Record that the monitor has ended, on ``fault`` (None: asked to stop; else it sends the stop
        itself), in one step with the fault: a motion that sees the fault sees the monitor gone, and
        sends nothing (was: recorded apart, and a retract started between the two sent its moveL to be
        watched by no one). The motions waiting for a sample raise the fault."""
        with self._cond:
            if fault is not None:
                self._set_fault(fault)
                self._monitor_stops_arm = True
            self._monitor_ended = True
            self._cond.notify_all()

    def _watch(self) -> None:
        next_t = time.monotonic()
        prev_force = 0.0
        limit = self.limits.force_limit_n
        was_stopped = False  # a safety stop in the previous sample
        over_limit = False  # within the last excursion over the force limit (until re-armed)
        controller_t, controller_t_since = None, self.clock()  # the controller's clock, and since when (bench clock)
        while not self._monitor_loop.stop_event.is_set():
            if not self._rcv.isConnected():  # _monitor records it and stops the arm
                raise HardwareFault("arm-disconnected", "arm: lost the RTDE connection to the robot")
            now_t = self._rcv.getTimestamp()
            if now_t != controller_t:
                controller_t, controller_t_since = now_t, self.clock()
            elif self.clock() - controller_t_since > STALE_STATE_S:
                raise HardwareFault("arm-disconnected", f"arm: the robot's state has not changed for {STALE_STATE_S:g} "
                                                        "s (its clock stopped): the link is dead")
            with self._commanding():
                self._ctl.getStepTime()  # the watchdog's kick (module docstring)
                self._note_kick()
            sample = self._read()
            force = float(np.linalg.norm(sample.tcp_wrench[:3]))
            bits = self._rcv.getSafetyStatusBits()
            stopped = bool(safety_stops(bits))
            if stopped and not was_stopped:
                self._set_fault(safety_stop_fault(bits, "arm: robot is in"))
            elif not stopped and force > limit and not over_limit:
                self.stop()
                jumped = force - prev_force > 0.5 * limit
                kind = "force-spike" if jumped else "force-limit"
                self._set_fault(HardwareFault(
                    kind, f"arm: measured force {force:.1f} N exceeds the limit {limit:.1f} N "
                          f"({'sudden jump' if jumped else 'ramped up'}); arm stopped"))
            was_stopped = stopped
            over_limit = force > limit or (over_limit and force > FORCE_REARM_FRACTION * limit)
            prev_force = force
            with self._cond:
                if self._latest is None or sample.t > self._latest.t:  # a paused (simulated) clock adds nothing
                    self._stream.append(sample)
                self._latest = sample
                self._cond.notify_all()
            next_t += self._wall_period
            delay = next_t - time.monotonic()
            if delay > 0:
                self._monitor_loop.stop_event.wait(delay)
            else:
                next_t = time.monotonic()

    def _set_fault(self, fault: HardwareFault, latest: bool = True) -> None:
        """Record ``fault``: the first one is sticky (``fault``); ``latest``: also the arm's own latest,
        which ends a retract (not another device's, ``abort``)."""
        with self._cond:
            if self._fault is None:
                self._fault = fault
            if latest:
                self._latest_fault = fault
            self._cond.notify_all()

    def _next_sample(self, timeout_s: float = 1.0) -> ArmState:
        with self._cond:
            seen = self._latest
            self._cond.wait_for(lambda: self._latest is not seen or self._monitor_ended, timeout=timeout_s)
            if self._latest is not seen:
                return self._latest
            if self._monitor_ended and self._latest_fault is not None:  # it ended on a lost link
                raise self._latest_fault
            raise HardwareFault("arm-timeout", f"arm: no state sample from the robot within {timeout_s} s")

    @property
    def running(self) -> bool:
        """Whether the monitor thread runs."""
        return self._monitor_loop.running

    @property
    def fault(self) -> HardwareFault | None:
        """The first fault the monitor recorded (sticky), or None."""
        return self._fault

    def abort(self, fault: HardwareFault) -> None:
        """Record ``fault`` from another device (camera stall, serial loss) and stop the arm: the
        running motion raises it at its next sample (within 1/state_hz). A retract under way goes on
        (was: stopped, leaving the bubble pressed on its object for a camera that went silent): only
        the arm's own faults end it."""
        with self._cond:  # the stop under the lock: a retract cannot start between the check and the stopL
            self._set_fault(fault, latest=False)
            if not self._retracting:
                self.stop()

    def check(self) -> None:
        """Raise the recorded fault, if any, then ``StopRequested`` if the operator's stop is set."""
        if self._fault is not None:
            raise self._fault
        if self._stop_request is not None and self._stop_request.is_set():
            raise StopRequested("arm: stopped by the operator")

    def stop_on(self, request: threading.Event | None) -> None:
        """Stop every motion but ``retract`` once ``request`` is set (the operator's stop), from now on; None: never."""
        self._stop_request = request

    def state(self) -> ArmState:
        """Latest sample ``(t, tcp_pose, tcp_wrench)`` (read directly when the monitor is not running
        or has no sample yet: its start failed, and the safe stop after it needs a pose)."""
        with self._cond:
            latest = self._latest
        return self._read() if latest is None or not self._monitor_loop.running else latest

    def drain_states(self) -> list[ArmState]:
        """Every sample since the previous call (the arm stream for the recorder)."""
        with self._cond:
            out, self._stream = self._stream, []
        return out

    # ------------------------------------------------------------------ motions
    def stop(self) -> None:
        """Start decelerating the TCP to rest (asynchronous stopL); safe to call at any time, from any
        thread, and never raises: a stop the robot cannot be sent (the link is gone) is recorded as
        the arm's fault, and the controller's watchdog stops the robot."""
        self._send_stop(threading.Event())

    def _send_stop(self, queued: threading.Event) -> None:
        """``stop``; sets ``queued`` once it holds the command lock, or has given up on it."""
        try:
            with self._commanding():
                queued.set()
                self._ctl.stopL(STOP_DECEL_M_S2, True)
        except HardwareFault as fault:
            self._set_fault(fault)
        finally:
            queued.set()

    @contextmanager
    def _commanding(self) -> Iterator[None]:
        """Hold ``_ctl_lock`` (one command to the robot at a time) for the with-block; raises
        ``HardwareFault('arm-disconnected')`` when another thread's command has held it for
        ``CONTROL_WAIT_S`` (blocked on a dead link; was: every later command, the stop included,
        waited on it)."""
        if not self._ctl_lock.acquire(timeout=CONTROL_WAIT_S):
            raise HardwareFault("arm-disconnected", f"arm: a command to the robot has not returned for "
                                                    f"{CONTROL_WAIT_S:g} s: the control link is blocked (the "
                                                    "controller's watchdog stops the robot)")
        try:
            yield
        finally:
            self._ctl_lock.release()

    def _arm_watchdog(self) -> None:
        """Arm the controller's watchdog at ``watchdog_hz`` (``setWatchdog``); under ``_ctl_lock``.
        Raises the refusal (``_refused``) where ur_rtde returns False (the control script refused or
        timed out)."""
        if not self._ctl.setWatchdog(self.watchdog_hz):
            raise self._refused("arm: the robot refused to arm its watchdog (setWatchdog); is its control script "
                                "running?")

    def _note_kick(self) -> None:
        """Count the time since the watchdog's previous kick (``longest_kick_gap_s``); under ``_ctl_lock``."""
        now = time.monotonic()
        if self._kicked_at is not None:
            self.longest_kick_gap_s = max(self.longest_kick_gap_s, now - self._kicked_at)
        self._kicked_at = now

    def _refused(self, message: str) -> HardwareFault:
        """The fault of a command the robot refused: ``arm-refused`` with ``message``, unless the
        watchdog ran out (``_stalled_or``)."""
        return self._stalled_or(HardwareFault("arm-refused", message))

    def _stalled_or(self, fault: HardwareFault) -> HardwareFault:
        """``host-stalled`` (this computer's, judged neither way) in place of ``fault`` once the watchdog
        has gone without a kick for longer than it allows, which shut the robot's control program down
        (a computer that froze, a link that paused): the robot braked the move under way and refuses
        the next command. Else ``fault`` (was: ``arm-refused``, or ``arm-timeout`` for the braked move,
        and the sensor of a run on a computer that froze for a second registered as rejected)."""
        allowed_s = 1.0 / self.watchdog_hz
        if self._kicked_at is not None:  # a gap still open: the monitor has not kicked since the freeze
            self.longest_kick_gap_s = max(self.longest_kick_gap_s, time.monotonic() - self._kicked_at)
        if self.longest_kick_gap_s > allowed_s:
            return HardwareFault(HOST_STALLED_FAULT, f"arm: the robot stopped its control program: this computer did "
                                                     f"not reach it for {self.longest_kick_gap_s:.2f} s, over its "
                                                     f"{allowed_s:g} s watchdog (a computer too busy or frozen, or a "
                                                     "link that paused); nothing judged")
        return fault

    def _send_move(self, target: np.ndarray, speed: float, accel: float, check_faults: bool) -> None:
        """Send the move unless (``check_faults``) a fault or the operator's stop is recorded: the check
        and the moveL under the lock that orders commands, so that a stop of a fault recorded meanwhile
        (``abort``, from another thread) is sent after the move, never before it (was: the check outside
        it, and a stopL could precede the moveL it should have stopped)."""
        with self._commanding():
            if check_faults:
                self.check()
            # armed again before each move (was: once, and a program ur_rtde restarted as it reconnected
            # by itself ran every later move without a watchdog)
            self._arm_watchdog()
            self._note_kick()
            accepted = self._ctl.moveL(target.tolist(), speed, accel, True)
        if not accepted:
            if check_faults:
                self.check()
            raise self._refused(f"arm: robot refused moveL to {np.round(target, 4).tolist()}")

    def _run_move(self, target, speed: float, accel: float, *, guard: Callable[[ArmState], bool] | None = None,
                  ignore_faults: bool = False, on_sent: Callable[[], None] | None = None) -> tuple[ArmState, bool]:
        """Validate, send and supervise one linear move.

        ``guard(sample) -> True`` stops the move early (guarded move). Returns the final sample and
        whether the guard fired. Raises the monitor's fault, and ``HardwareFault('arm-timeout')``
        when the move takes far longer than planned. ``ignore_faults`` (the retract): the fault
        recorded before the move (and the operator's stop) do not end it; a protective stop or a new
        fault on the way (a collision) do. ``on_sent()`` runs once the robot has accepted the move.
        """
        target = self.limits.check_move(target, speed, accel)
        self.start()
        start = self.state()
        self.limits.check_path(start.tcp_pose, target)  # the tilt on the way (sent nothing yet)
        budget = move_duration_s(linear_path_m(start.tcp_pose, target), speed, accel) + MOVE_TIMEOUT_MARGIN_S
        known_fault = self._latest_fault
        self._send_move(target, speed, accel, check_faults=not ignore_faults)
        if on_sent is not None:
            on_sent()
        try:
            return self._supervise(target, guard, ignore_faults, known_fault, budget)
        except BaseException:  # whatever ends the move (was: a lost sample left it running unwatched)
            with self._cond:
                stopped = self._monitor_stops_arm
            if not stopped:  # (on a dead link, this thread's stopL would wait out ur_rtde's 300 s)
                self.stop()
            raise

    def _supervise(self, target: np.ndarray, guard, ignore_faults: bool, known_fault: HardwareFault | None,
                   budget: float) -> tuple[ArmState, bool]:
        """``_run_move``'s watch of the move it sent, sample by sample (the stop is the caller's)."""
        t_end = self.clock() + budget
        t_end_real = time.monotonic() + REAL_TIME_SLACK * budget
        while True:
            sample = self._next_sample()
            if not ignore_faults:
                self.check()
            elif safety_stops(bits := self._rcv.getSafetyStatusBits()):  # the robot holds still: no finish
                raise safety_stop_fault(bits, "arm: during the move the robot went into")
            elif self._latest_fault is not known_fault:  # the arm was stopped there (a collision)
                raise self._latest_fault
            if guard is not None and guard(sample):
                self.stop()
                return self._settle(), True
            if (np.linalg.norm(sample.tcp_pose[:3] - target[:3]) < ARRIVAL_TOL_M
                    and rotation_between_rad(sample.tcp_pose, target) < ARRIVAL_TOL_RAD
                    and np.linalg.norm(self._rcv.getActualTCPSpeed()[:3]) < ARRIVAL_SPEED_M_S):
                return sample, False
            if self.clock() > t_end or time.monotonic() > t_end_real:
                raise self._stalled_or(HardwareFault("arm-timeout", f"arm: move did not finish within {budget:.1f} s"))

    def _settle(self) -> ArmState:
        """Wait until the TCP is at rest after a stop; returns the sample at rest."""
        t_end = self.clock() + 1.0
        while True:
            sample = self._next_sample()
            if np.linalg.norm(self._rcv.getActualTCPSpeed()[:3]) < ARRIVAL_SPEED_M_S or self.clock() > t_end:
                return sample

    def move_to(self, pose, speed: float | None = None, accel: float | None = None) -> ArmState:
        """Linear move of the TCP to ``pose`` (6,); returns the sample on arrival."""
        sample, _ = self._run_move(pose, speed or self.settings.travel_speed, accel or self.settings.accel)
        return sample

    def travel_to(self, pose, speed: float | None = None, accel: float | None = None) -> ArmState:
        """Move to ``pose`` (6,), a pose at a safe travel height above the objects, from wherever the
        TCP is (the first move of a run, which may start low beside an object): straight up (base +z,
        orientation kept) to the height of ``pose`` when the TCP is below it, then the linear move.
        The path never runs below the lower of its two ends, where a straight line from a low pose
        could sweep the bubble through an object. The target is validated before anything moves.
        Returns the sample on arrival."""
        speed, accel = speed or self.settings.travel_speed, accel or self.settings.accel
        target = self.limits.check_move(pose, speed, accel)
        rise = self.state().tcp_pose.copy()
        if rise[2] < target[2] - ARRIVAL_TOL_M:
            rise[2] = target[2]
            self.limits.check_path(rise, target)  # both legs checked before the rise (was: the second after it)
            self.move_to(rise, speed, accel)
        return self.move_to(target, speed, accel)

    def move_until_contact(self, direction=None, speed: float | None = None, force_threshold_n: float | None = None,
                           max_travel_m: float | None = None) -> ArmState | None:
        """Guarded linear move along ``direction`` (3,) in the base frame (default: the pressing axis).

        Zeroes the force sensor first, remembers the start pose as the retract pose, and stops as
        soon as the contact force reaches ``force_threshold_n`` (N). The zero needs a free membrane:
        when the force read now (relative to the previous zero; its magnitude, which bounds the
        force along ``direction`` too) is above ``settings.max_preload_n``, the bubble touches
        something, and ``HardwareFault('preload')`` is raised with nothing zeroed and nothing moved.
        Returns the sample at contact, or None when nothing was touched within ``max_travel_m`` (m).
        """
        s = self.settings
        speed = speed or s.approach_speed
        threshold = force_threshold_n or s.contact_force_n
        travel = max_travel_m or s.max_contact_travel_m
        self.limits.check_force(threshold)
        start = self.state()
        axis = tool_z_axis(start.tcp_pose) if direction is None else np.asarray(direction, dtype=float)
        norm = np.linalg.norm(axis)
        if axis.shape != (3,) or not norm > 0:
            raise InputError(f"arm: contact direction must be a non-zero 3-vector, got {direction!r}")
        axis = axis / norm
        target = start.tcp_pose.copy()
        target[:3] += axis * travel
        self.limits.check_move(target, speed, s.accel)
        preload = float(np.linalg.norm(start.tcp_wrench[:3]))
        if preload > s.max_preload_n:
            raise HardwareFault(
                "preload", f"arm: the sensor already feels {preload:.2f} N ({start.pressing_force_n(axis):.2f} N along "
                           f"the approach) before a contact move, above the {s.max_preload_n:.2f} N a free bubble may "
                           f"read (motion max_preload_n): the bubble touches something; force sensor not zeroed, "
                           f"arm not moved")
        with self._commanding():
            zeroed = self._ctl.zeroFtSensor()
        if not zeroed:  # the approach would stop on the old zero's offset (up to max_preload_n)
            raise self._refused("arm: the robot refused to zero its force sensor (zeroFtSensor); arm not moved")
        self._retract_pose = start.tcp_pose.copy()
        sample, touched = self._run_move(target, speed, s.accel,
                                         guard=lambda smp: smp.pressing_force_n(axis) >= threshold)
        return sample if touched else None

    def press(self, depth_m: float | None = None, force_n: float | None = None, speed: float | None = None) -> ArmState:
        """Press along the pressing axis from the current pose, by ``depth_m`` or until ``force_n``.

        Exactly one of ``depth_m`` (m, at most ``settings.max_press_depth_m``) and ``force_n``
        (N, at most the force limit) is given. A press to a force stops at the force, after
        ``settings.max_press_depth_m``, or where the pressing axis leaves the workspace box (a low
        object near the plate), whichever comes first. Returns the sample at the end of the press.
        """
        if (depth_m is None) == (force_n is None):
            raise InputError("arm: press needs exactly one of depth_m and force_n")
        s = self.settings
        start = self.state()
        axis = tool_z_axis(start.tcp_pose)
        target = start.tcp_pose.copy()
        guard = None
        if depth_m is not None:
            if not (np.isfinite(depth_m) and 0 < depth_m <= s.max_press_depth_m):
                raise InputError(f"arm: press depth {depth_m} m is outside (0, {s.max_press_depth_m}] m")
            target[:3] += axis * depth_m
        else:
            self.limits.check_force(force_n)
            depth = self.limits.room_along(start.tcp_pose[:3], axis, s.max_press_depth_m)
            if depth <= 0:
                return start
            target[:3] += axis * depth
            guard = lambda smp: smp.pressing_force_n(axis) >= force_n  # noqa: E731
        sample, _ = self._run_move(target, speed or s.press_speed, s.accel, guard=guard)
        return sample

    def hold(self, seconds: float) -> ArmState:
        """Stay in place for ``seconds`` (bench clock) while the monitor watches force and safety."""
        if not (np.isfinite(seconds) and seconds >= 0):
            raise InputError(f"arm: hold time {seconds} s must be >= 0")
        t_end = self.clock() + seconds
        while True:
            sample = self._next_sample()
            self.check()
            if sample.t >= t_end:
                return sample

    def retract(self, speed: float | None = None) -> ArmState:
        """Move away from the object, to the pose where the last contact move began.

        Without a remembered pose (e.g. a force fault while travelling, the bubble's side against an
        object) it backs off ``settings.retract_m`` along the measured contact force (``backoff_direction``:
        never toward the plate) if that force is above ``settings.max_preload_n`` (what finds the bubble
        touching something; below it the F/T sensor's drift since its last zero would move the arm
        30 mm through free air at the end of every run: was ``contact_force_n``), and only as far
        as the workspace box allows; otherwise it stays put. Moves away after any fault, a force fault
        included (the fault already recorded does not stop it); a new fault on the way (a collision
        over the force limit) stops it there and is raised, and so is ``HardwareFault('protective-stop')``
        when the robot is in protective stop or goes into it on the way. A retract that starts over
        the force limit (after a force fault, where the monitor waits for the force to fall before
        it watches again) stops with ``HardwareFault('force-limit')`` when the force rises
        ``RETRACT_FORCE_RISE_FRACTION`` of the limit above where it started. Other devices' faults
        (``abort``) do not stop it. The remembered pose is used once the robot accepted the move: a
        retract that a fault ended is not sent along the same path again (was: the safe stop's
        retract drove on into the collision, the force unwatched in the monitor's hysteresis); the
        next one backs off along the force.
        """
        if safety_stops(bits := self._rcv.getSafetyStatusBits()):
            raise safety_stop_fault(bits, "arm: cannot retract, robot is in")
        now = self.state()
        remembered = self._retract_pose is not None
        if remembered:
            target = self._retract_pose
        else:
            away = backoff_direction(now.tcp_wrench, self.settings.max_preload_n)
            if away is None:
                return now
            target = now.tcp_pose.copy()
            target[:3] += away * self.limits.room_along(now.tcp_pose[:3], away, self.settings.retract_m)
        limit = self.limits.force_limit_n
        start_n = float(np.linalg.norm(now.tcp_wrench[:3]))
        stop_n = max(limit, start_n + RETRACT_FORCE_RISE_FRACTION * limit)
        rose_n: list[float] = []  # the force that stopped it

        def force_rose(smp: ArmState) -> bool:
            force = float(np.linalg.norm(smp.tcp_wrench[:3]))
            if force > stop_n:
                rose_n.append(force)
            return bool(rose_n)

        with self._cond:
            self._retracting = True
        try:
            forget = (lambda: setattr(self, "_retract_pose", None)) if remembered else None
            sample, rose = self._run_move(target, speed or retract_speed(self.settings), self.settings.accel,
                                          guard=force_rose, ignore_faults=True, on_sent=forget)
        finally:
            with self._cond:
                self._retracting = False
        if rose:
            fault = HardwareFault("force-limit", f"arm: the force rose to {rose_n[0]:.1f} N while retracting (from "
                                                 f"{start_n:.1f} N; limit {limit:.1f} N): something is in the way; "
                                                 f"arm stopped")
            self._set_fault(fault)
            raise fault
        return sample
