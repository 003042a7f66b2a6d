"""Twin of a UR e-Series arm behind ur_rtde: ``FakeRTDEControl`` and ``FakeRTDEReceive``.

They implement exactly the ur_rtde methods that ``collect.arm.Arm`` calls, with the same names,
argument orders and defaults as ``rtde_control.RTDEControlInterface`` /
``rtde_receive.RTDEReceiveInterface`` (``tests/test_drivers_rtde_signatures.py`` checks them
against the driver's calls and the installed ur_rtde). Only the constructors differ: they take
the simulated controller (``SimURController``) instead of a robot IP.

The simulated controller moves the TCP along analytic trapezoidal profiles on the simulated
clock (position linear, orientation slerped, speed and acceleration bounded as requested),
so there is no control thread: every RTDE call evaluates the state at the current simulated time.
The wrench comes from the shared bubble scene (``SimBench.wrench``: the physics thread's latest
membrane solutions interpolated to the current pose, plus an injected force spike), minus the
offset stored by ``zeroFtSensor``. The controller enters protective stop when a force read finds
the raw force above ``protective_force_n``, or at any call once the fault schedule injects
``protective-stop``; it then holds the TCP still and refuses motion (``moveL`` returns False), as
a real UR does until the operator unlocks it on the pendant. Its watchdog (``setWatchdog``) runs
on the host's clock, as the real controller's runs in real time: once armed, a move still under
way when no kick came for ``1 / min_frequency`` s is braked to rest and later moves are refused
(ur_rtde's "shutdown the control").
"""

from __future__ import annotations

import threading
import time

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from collect.transforms import linear_path_m

#: ``getSafetyStatusBits`` of a robot in normal mode (bit 0) and in protective stop (bits 2 and 10,
#: "stopped due to safety").
SAFETY_BITS_NORMAL = 1 << 0
SAFETY_BITS_PROTECTIVE_STOP = 1 << 2 | 1 << 10
#: Deceleration (m/s^2) with which the watchdog brakes a move.
WATCHDOG_DECEL_M_S2 = 4.0


class _Profile:
    """1-D trapezoidal motion over ``distance`` m from speed ``v0`` to rest, cruise ``vmax``, accel ``a``."""

    def __init__(self, distance: float, v0: float, vmax: float, a: float):
        self.distance = distance
        self.v0 = v0 if distance > 0 else 0.0
        self.a = a
        if distance <= 0:
            self.a_dec, self.vp, self.t1, self.t2, self.t3 = a, 0.0, 0.0, 0.0, 0.0
        elif v0 * v0 / (2 * a) >= distance:  # must brake at once (harder if needed) and stop at the end
            self.a_dec = v0 * v0 / (2 * distance)
            self.vp, self.t1, self.t2 = v0, 0.0, 0.0
            self.t3 = v0 / self.a_dec
        else:
            self.a_dec = a
            vp = min(max(vmax, v0), np.sqrt((2 * a * distance + v0 * v0) / 2))
            self.vp = vp
            self.t1 = (vp - v0) / a
            d1 = (vp * vp - v0 * v0) / (2 * a)
            d3 = vp * vp / (2 * a)
            self.t2 = (distance - d1 - d3) / vp if vp > 0 else 0.0
            self.t3 = vp / a
        self.duration = self.t1 + self.t2 + self.t3

    def at(self, t: float) -> tuple[float, float]:
        """Distance (m) travelled and speed (m/s) at ``t`` s after the start."""
        if t <= 0:
            return 0.0, self.v0
        if t >= self.duration:
            return self.distance, 0.0
        if t < self.t1:
            return self.v0 * t + 0.5 * self.a * t * t, self.v0 + self.a * t
        d1 = self.v0 * self.t1 + 0.5 * self.a * self.t1 ** 2
        if t < self.t1 + self.t2:
            return d1 + self.vp * (t - self.t1), self.vp
        tau = t - self.t1 - self.t2
        d2 = self.vp * self.t2
        return d1 + d2 + self.vp * tau - 0.5 * self.a_dec * tau * tau, self.vp - self.a_dec * tau


class _LinearMove:
    """A linear TCP move from ``start`` to ``end`` (6,) following a ``_Profile`` from ``t0`` (s, sim clock).

    ``s_from`` is where along the path (m) the profile starts: a stop re-plans the rest of the
    path from the current point.
    """

    def __init__(self, start: np.ndarray, end: np.ndarray, t0: float, speed: float, accel: float,
                 s_from: float = 0.0, v0: float = 0.0, s_to: float | None = None):
        self.start, self.end = start, end
        rots = Rotation.from_rotvec(np.stack([start[3:6], end[3:6]]))
        self._slerp = Slerp([0.0, 1.0], rots)
        self.length = linear_path_m(start, end)
        self.t0, self.s_from = t0, s_from
        s_to = self.length if s_to is None else s_to
        self.profile = _Profile(max(s_to - s_from, 0.0), v0, speed, accel)
        self.t_end = t0 + self.profile.duration

    def state(self, t: float) -> tuple[np.ndarray, float, np.ndarray]:
        """Pose (6,), path position (m) and TCP velocity (6,) at time ``t``."""
        ds, v = self.profile.at(t - self.t0)
        s = self.s_from + ds
        u = s / self.length if self.length > 0 else 1.0
        pose = np.empty(6)
        pose[:3] = self.start[:3] + (self.end[:3] - self.start[:3]) * u
        pose[3:6] = self._slerp([min(max(u, 0.0), 1.0)]).as_rotvec()[0]
        velocity = np.zeros(6)
        if self.length > 0:
            velocity[:3] = (self.end[:3] - self.start[:3]) / self.length * v
        return pose, s, velocity

    def done(self, t: float) -> bool:
        return t - self.t0 >= self.profile.duration

    def stopping(self, t: float, decel: float) -> "_LinearMove":
        """The same path from time ``t``, braking at ``decel`` m/s^2 to rest."""
        _, s, _ = self.state(t)
        v = self.profile.at(t - self.t0)[1]
        s_to = min(s + v * v / (2 * decel), self.length)
        return _LinearMove(self.start, self.end, t, max(v, 1e-9), decel, s_from=s, v0=v, s_to=s_to)


class SimURController:
    """The simulated UR controller shared by ``FakeRTDEControl`` and ``FakeRTDEReceive``.

    scene: the ``hw_mocks.sim_bench.SimBench`` (clock ``now()``, ``wrench(pose, t)``,
    ``fault_active(kind, t)``). initial_pose (6,) m + rotvec. protective_force_n: raw force (N)
    above which the controller protective-stops on its own.
    """

    def __init__(self, scene, initial_pose, protective_force_n: float = 150.0):
        self.scene = scene
        self.protective_force_n = protective_force_n
        self._lock = threading.RLock()
        pose = np.asarray(initial_pose, dtype=np.float64)
        self._move = _LinearMove(pose, pose, scene.now(), 1.0, 1.0)
        self._ft_offset = np.zeros(6)
        self._protective = False
        self._watchdog_s: float | None = None  # longest time between kicks (host clock), once armed
        self._kicked = time.monotonic()
        self.watchdog_fired = False  # the control was shut down: moves are refused

    def moving_until(self) -> float:
        """Simulated time (s) at which the current move ends (lock-free: read by the clock)."""
        return self._move.t_end

    def pose_at(self, t: float) -> np.ndarray:
        """TCP pose (6,) at simulated time ``t`` along the current move (for the camera twin)."""
        with self._lock:
            return self._move.state(t)[0]

    def _freeze(self, t: float, pose: np.ndarray) -> None:
        self._protective = True
        self._move = _LinearMove(pose, pose, t, 1.0, 1.0)

    def _update(self) -> tuple[float, np.ndarray, np.ndarray]:
        """Advance to now: returns (t, pose (6,), velocity (6,)); applies a scheduled protective stop
        and the watchdog."""
        with self._lock:
            t = self.scene.now()
            pose, _, velocity = self._move.state(t)
            if not self._protective and self.scene.fault_active("protective-stop", t):
                self._freeze(t, pose)
                velocity = np.zeros(6)
            if (self._watchdog_s is not None and not self.watchdog_fired
                    and time.monotonic() - self._kicked > self._watchdog_s):
                self.watchdog_fired = True
                if not self._move.done(t):
                    self._move = self._move.stopping(t, WATCHDOG_DECEL_M_S2)
            return t, pose, velocity

    def _raw_wrench(self) -> np.ndarray:
        """Raw wrench (6,) at the current pose; protective-stops above ``protective_force_n``."""
        with self._lock:
            t, pose, _ = self._update()
            wrench = np.asarray(self.scene.wrench(pose, t), dtype=np.float64)
            if not self._protective and np.linalg.norm(wrench[:3]) > self.protective_force_n:
                self._freeze(t, pose)
            return wrench

    # control side
    def move_linear(self, pose, speed: float, accel: float) -> bool:
        """Start a trapezoidal linear move to ``pose`` (6,) m + rotvec at ``speed`` m/s, ``accel``
        m/s^2 from where the TCP is now; False (nothing moves) during a protective stop."""
        with self._lock:
            t, current, _ = self._update()
            if self._protective or self.watchdog_fired:
                return False
            self._move = _LinearMove(current, np.asarray(pose, dtype=np.float64), t, speed, accel)
            return True

    def wait_move(self) -> None:
        """Block (real time) until the current move has finished or a protective stop ended it."""
        while True:
            t, *_ = self._update()
            with self._lock:
                if self._move.done(t):
                    return
            time.sleep(0.002)

    def stop_linear(self, decel: float) -> None:
        with self._lock:
            t, *_ = self._update()
            if not self._move.done(t):
                self._move = self._move.stopping(t, decel)

    def zero_ft(self) -> None:
        with self._lock:
            self._ft_offset = self._raw_wrench().copy()

    def set_watchdog(self, min_frequency: float) -> None:
        with self._lock:
            self._watchdog_s, self._kicked = 1.0 / min_frequency, time.monotonic()

    def command_received(self) -> None:
        """A command updated the register the watchdog watches (any command is a kick)."""
        with self._lock:
            self._update()  # a watchdog that ran out before this kick has fired
            self._kicked = time.monotonic()

    # receive side
    def tcp_pose(self) -> list[float]:
        return self._update()[1].tolist()

    def tcp_speed(self) -> list[float]:
        return self._update()[2].tolist()

    def tcp_force(self) -> list[float]:
        return (self._raw_wrench() - self._ft_offset).tolist()

    def safety_status_bits(self) -> int:
        self._update()
        return SAFETY_BITS_PROTECTIVE_STOP if self._protective else SAFETY_BITS_NORMAL


class FakeRTDEControl:
    """``rtde_control.RTDEControlInterface`` twin over a ``SimURController``.

    It keeps the command handshake of the control script ur_rtde 1.6 uploads: an ordinary command
    runs only while the script is not marked as executing one; the host clears that mark after the
    command reports done. ``kickWatchdog``'s command (99) has no branch in that script: it marks
    the script as executing without ever reporting done, so every later ordinary command is left
    unprocessed and ur_rtde returns False once it gives up (here at once). Real-time commands
    (``getStepTime``) run whatever the mark. Every command kicks the watchdog."""

    #: s per control cycle of an e-Series controller (500 Hz), what ``getStepTime`` reports
    STEP_TIME_S = 0.002

    def __init__(self, controller: SimURController):
        self._c = controller
        self._connected = True
        self._stuck = False  # the script took a command it never reports done

    def _ordinary(self) -> bool:
        """An ordinary command reaches the script: whether it runs."""
        self._c.command_received()
        return self._connected and not self._stuck

    def moveL(self, pose: list[float], speed: float = 0.25, acceleration: float = 1.2,
              asynchronous: bool = False) -> bool:
        if not self._ordinary() or not self._c.move_linear(pose, speed, acceleration):
            return False
        if not asynchronous:
            self._c.wait_move()
        return True

    def stopL(self, a: float = 10.0, asynchronous: bool = False) -> None:
        if not self._ordinary():
            return
        self._c.stop_linear(a)
        if not asynchronous:
            self._c.wait_move()

    def zeroFtSensor(self) -> bool:
        if not self._ordinary():
            return False
        self._c.zero_ft()
        return True

    def setWatchdog(self, min_frequency: float = 10.0) -> bool:
        if not self._ordinary():
            return False
        self._c.set_watchdog(min_frequency)
        return True

    def kickWatchdog(self) -> bool:
        self._c.command_received()
        self._stuck = True
        return True

    def getStepTime(self) -> float:
        self._c.command_received()
        return self.STEP_TIME_S

    def disconnect(self) -> None:
        self._connected = False


class FakeRTDEReceive:
    """``rtde_receive.RTDEReceiveInterface`` twin over a ``SimURController``."""

    def __init__(self, controller: SimURController):
        self._c = controller
        self._connected = True

    def getActualTCPPose(self) -> list[float]:
        return self._c.tcp_pose()

    def getActualTCPSpeed(self) -> list[float]:
        return self._c.tcp_speed()

    def getActualTCPForce(self) -> list[float]:
        return self._c.tcp_force()

    def getSafetyStatusBits(self) -> int:
        return self._c.safety_status_bits()

    def getTimestamp(self) -> float:
        return self._c.scene.now()

    def isConnected(self) -> bool:
        return self._connected

    def disconnect(self) -> None:
        self._connected = False
