"""Safety limits of the bench arm, checked before any motion command reaches the robot.

Two kinds of violation, two exception types:

* ``SafetyViolation`` (a subclass of ``InputError``): a *requested* motion breaks a limit
  (target outside the workspace box, speed/acceleration above the caps, tool tilted too far,
  press force above the force limit). Requests come from the user's configuration through the
  pose planner, so the command line reports them like any bad input (one line, exit 2), and
  nothing is sent to the robot.
* ``HardwareFault('force-limit' | 'force-spike', ...)``: the *measured* force exceeded the
  limit while moving (see ``collect.arm.Arm``); the arm stops and retracts.

Poses are ``[x, y, z, rx, ry, rz]`` (m + rotation vector) in the robot base frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from collect.errors import InputError
from collect.numbers import real_number, real_numbers


#: Upper bounds of the limits themselves: a ``limits`` setting above one is refused when the bench
#: config is built (a typo such as ``max_tilt_deg: 1000`` must not switch a check off). They are what
#: a UR e-Series arm pressing a ~5 kPa soft bubble (a few tens of N over its ~50 cm^2 at full
#: contact) may sensibly be allowed, well inside the controller's own safety configuration:
#: * TCP speed 1 m/s: below the UR "Default" safety preset's 1.5 m/s tool speed; the bench's moves
#:   are short (a box of well under 1 m) and from 1 m/s the stopL (4 m/s^2) still stops in 12.5 cm.
#: * TCP acceleration 2.5 m/s^2: Universal Robots' advice for moves without nuisance protective
#:   stops (the URScript default is 1.2 m/s^2), and below that stopL deceleration.
#: * force 150 N: the UR "Default" preset's force limit; the simulated controller (like a real one
#:   so configured) goes into protective stop above it, far beyond what the bubble survives.
#: * tilt 90 deg: the pressing axis (TCP +z) may at most lie horizontal; beyond that the sensor
#:   would press upwards, away from the fixture plate.
MAX_TCP_SPEED_M_S = 1.0
MAX_TCP_ACCEL_M_S2 = 2.5
MAX_FORCE_LIMIT_N = 150.0
MAX_TILT_DEG = 90.0
#: Largest distance (m) of a workspace box corner coordinate from the robot base: the reach of the
#: largest UR arm (UR20, 1.75 m) with room to spare. A box in millimetres (``[-350, -350, -100]``)
#: or a typo is refused instead of switching the workspace check off.
MAX_WORKSPACE_COORD_M = 2.0
#: Largest rotation vector norm (rad) a pose may hold: one turn. A longer one is the same rotation
#: written in degrees (``[0, 180, 0]``) or a typo, never what was meant.
MAX_ROTATION_RAD = 2.0 * np.pi
#: Largest orientation step (deg) between the poses at which a move's tilt is checked.
TILT_PATH_STEP_DEG = 1.0
#: field -> (upper bound, unit) of the scalar limits
LIMIT_BOUNDS = {
    "max_speed_m_s": (MAX_TCP_SPEED_M_S, "m/s"),
    "max_accel_m_s2": (MAX_TCP_ACCEL_M_S2, "m/s^2"),
    "force_limit_n": (MAX_FORCE_LIMIT_N, "N"),
    "max_tilt_deg": (MAX_TILT_DEG, "deg"),
}


def check_within_bounds(who: str, settings, bounds: dict[str, tuple[float, str]]) -> None:
    """``InputError`` ``"{who}: NAME must be a positive number"`` / ``"... must be within (0, BOUND]
    UNIT"`` for the first field of ``settings`` named in ``bounds`` (name -> (bound, unit)) that is not."""
    for name, (bound, unit) in bounds.items():
        value = getattr(settings, name)
        if not (real_number(value) and value > 0):
            raise InputError(f"{who}: {name} must be a positive number, got {value!r}")
        if value > bound:
            raise InputError(f"{who}: {name} must be within (0, {bound:g}] {unit}, got {value!r}")


class SafetyViolation(InputError):
    """A motion request that breaks a ``SafetyLimits`` limit; never sent to the robot."""


def tool_z_axis(pose) -> np.ndarray:
    """Unit z axis of the TCP frame of ``pose`` (6,) expressed in the base frame, (3,)."""
    return Rotation.from_rotvec(np.asarray(pose, dtype=float)[3:6]).apply([0.0, 0.0, 1.0])


def rotation_vector_ok(pose) -> bool:
    """Whether the rotation vector of ``pose`` (6,) is at most ``MAX_ROTATION_RAD`` long (finite)."""
    r = np.abs(np.asarray(pose, dtype=float)[3:6])
    return bool(np.all(r <= MAX_ROTATION_RAD) and np.linalg.norm(r) <= MAX_ROTATION_RAD)  # no overflow of 1e300**2


def tilt_deg(pose) -> float:
    """Angle in degrees between the TCP pressing axis (+z) of ``pose`` (6,) (m + rotation vector, base
    frame) and straight down (base -z)."""
    cos = float(np.clip(-tool_z_axis(pose)[2], -1.0, 1.0))
    return float(np.degrees(np.arccos(cos)))


@dataclass(frozen=True)
class SafetyLimits:
    """Limits every arm motion must respect.

    workspace_min/max: corners (3,) m of the axis-aligned box in the base frame that the TCP
    may occupy (the membrane apex). A linear move stays inside if both ends do (the box is convex).
    None: fitted around the bench's objects (``collect.bench.workspace_limits``); a pose is not
    checked against a box with a corner unset (``InputError``).
    max_speed_m_s, max_accel_m_s2: caps on the TCP speed and acceleration of any move.
    force_limit_n: largest contact force (N) a press may request or the arm may measure.
    max_tilt_deg: largest angle between the pressing axis and base -z.
    Each of these four is a positive number at most its ``LIMIT_BOUNDS`` bound (``InputError``).
    """

    workspace_min: tuple[float, float, float] | None = None
    workspace_max: tuple[float, float, float] | None = None
    max_speed_m_s: float = 0.25
    max_accel_m_s2: float = 1.0
    force_limit_n: float = 25.0
    max_tilt_deg: float = 30.0

    def __post_init__(self):
        for name in ("workspace_min", "workspace_max"):
            if getattr(self, name) is not None and not real_numbers(getattr(self, name), 3):
                raise InputError(f"safety: {name} must be 3 numbers [x, y, z] (m), got {getattr(self, name)!r}")
        for name in ("workspace_min", "workspace_max"):
            corner = getattr(self, name)
            if corner is not None and max(abs(float(v)) for v in corner) > MAX_WORKSPACE_COORD_M:
                raise InputError(f"safety: {name} {list(corner)} must lie within {MAX_WORKSPACE_COORD_M:g} m of the "
                                 "robot base in x, y and z (metres, not millimetres)")
        if self.has_workspace and not all(lo < hi for lo, hi in zip(self.workspace_min, self.workspace_max)):
            raise InputError(f"safety: workspace box min {self.workspace_min} must be below max {self.workspace_max}")
        check_within_bounds("safety", self, LIMIT_BOUNDS)

    @property
    def has_workspace(self) -> bool:
        """Whether both corners of the workspace box are set."""
        return self.workspace_min is not None and self.workspace_max is not None

    def _box(self) -> tuple[np.ndarray, np.ndarray]:
        """The workspace box's corners (3,), (3,) m; ``InputError`` while a corner is unset."""
        if not self.has_workspace:
            raise InputError("safety: the workspace box is not set (fit it around the bench's objects with "
                             "collect.bench.workspace_limits, or give workspace_min and workspace_max)")
        return np.asarray(self.workspace_min, dtype=float), np.asarray(self.workspace_max, dtype=float)

    def room_along(self, position, direction, up_to_m: float) -> float:
        """How far (m, at most ``up_to_m``) the TCP at ``position`` (3,) m may move along the unit
        ``direction`` (3,) and stay inside the workspace box (0 at or beyond its wall)."""
        p, d = np.asarray(position, dtype=float), np.asarray(direction, dtype=float)
        room = float(up_to_m)
        for x, dx, lo, hi in zip(p, d, *self._box()):
            if dx > 0:
                room = min(room, (hi - x) / dx)
            elif dx < 0:
                room = min(room, (lo - x) / dx)
        return max(room, 0.0)

    def check_pose(self, pose) -> np.ndarray:
        """Validate a target pose; returns it as (6,) float64 or raises ``SafetyViolation``."""
        try:
            p = np.asarray(pose, dtype=float)
        except (TypeError, ValueError):  # text, a mapping, ragged lists
            p = None
        if p is None or p.shape != (6,) or not np.all(np.isfinite(p)):
            raise SafetyViolation(f"safety: pose must be 6 finite numbers [x,y,z,rx,ry,rz], got {pose!r}")
        if not rotation_vector_ok(p):
            raise SafetyViolation(f"safety: the rotation vector {np.round(p[3:], 4).tolist()} of pose is longer than "
                                  f"{MAX_ROTATION_RAD:.4g} rad (one turn): a rotation vector is in radians")
        lo, hi = self._box()
        if np.any(p[:3] < lo) or np.any(p[:3] > hi):
            raise SafetyViolation(
                f"safety: target position {np.round(p[:3], 4).tolist()} m is outside the workspace box "
                f"{np.round(lo, 4).tolist()}..{np.round(hi, 4).tolist()} m"
            )
        tilt = tilt_deg(p)
        if tilt > self.max_tilt_deg:
            raise SafetyViolation(f"safety: tool tilt {tilt:.1f} deg exceeds the limit {self.max_tilt_deg:.1f} deg")
        return p

    def check_motion(self, speed_m_s: float, accel_m_s2: float) -> None:
        """Validate the speed (m/s) and acceleration (m/s^2) of a move."""
        if not (np.isfinite(speed_m_s) and 0 < speed_m_s <= self.max_speed_m_s):
            raise SafetyViolation(f"safety: speed {speed_m_s} m/s is outside (0, {self.max_speed_m_s}] m/s")
        if not (np.isfinite(accel_m_s2) and 0 < accel_m_s2 <= self.max_accel_m_s2):
            raise SafetyViolation(f"safety: acceleration {accel_m_s2} m/s^2 is outside (0, {self.max_accel_m_s2}] m/s^2")

    def check_force(self, force_n: float) -> None:
        """Validate a requested contact force or force threshold (N)."""
        if not (np.isfinite(force_n) and 0 < force_n <= self.force_limit_n):
            raise SafetyViolation(f"safety: force {force_n} N is outside (0, {self.force_limit_n}] N")

    def check_move(self, target_pose, speed_m_s: float, accel_m_s2: float) -> np.ndarray:
        """Validate a linear move's target pose, speed and acceleration (its way: ``check_path``);
        returns the pose (6,)."""
        self.check_motion(speed_m_s, accel_m_s2)
        return self.check_pose(target_pose)

    def check_path(self, from_pose, to_pose) -> None:
        """Validate the tilt along a linear move from ``from_pose`` to ``to_pose`` (6,) each: the
        orientation turns about one axis at a constant rate (a slerp), and on the way it may tilt
        further than at either end (two poses 29 deg off vertical on opposite sides, 160 deg of yaw
        apart, pass 37 deg). Checked every ``TILT_PATH_STEP_DEG``; a move from a pose already beyond
        the limit may tilt no further than it starts (the way back from it stays allowed)."""
        a, b = np.asarray(from_pose, dtype=float), np.asarray(to_pose, dtype=float)
        ends = Rotation.from_rotvec(np.stack([a[3:6], b[3:6]]))
        angle = np.degrees((ends[0].inv() * ends[1]).magnitude())
        steps = np.linspace(0.0, 1.0, int(np.ceil(angle / TILT_PATH_STEP_DEG)) + 1)
        down = Slerp([0.0, 1.0], ends)(steps).apply([0.0, 0.0, 1.0])[:, 2]  # pressing axis, base z
        worst = float(np.degrees(np.arccos(np.clip(-down.max(), -1.0, 1.0))))  # the axis furthest from down
        allowed = max(self.max_tilt_deg, tilt_deg(a))
        if worst > allowed + 1e-6:
            raise SafetyViolation(f"safety: the move tilts the tool {worst:.1f} deg on the way (its ends "
                                  f"{tilt_deg(a):.1f} and {tilt_deg(b):.1f} deg), beyond the limit "
                                  f"{self.max_tilt_deg:.1f} deg")
