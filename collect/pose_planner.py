"""Random contact poses on the fixture-plate objects: where and how the arm presses the bubble.

For each object, ``plan_collection`` draws K contact poses (seeded, reproducible):

* a contact point on the object's upper surface (``obj.top_surface_points``: upward-facing cells
  near the top of the object's height field, real meshes included);
* a pressing axis (TCP +z) tilted from straight down by up to ``max_tilt_deg`` towards a random
  direction, and a random yaw of the sensor about the vertical in [-90, 90) deg (the bubble's
  footprint is symmetric under a half turn); an object's poses run in order of yaw, so that the
  arm turns the sensor by at most half a turn per object (reorienting is slow: see
  ``collect.transforms.ROTATION_M_PER_RAD``);
* a press force drawn in ``press_force_n``, added to the force at first contact (the press stops
  at that force, at ``max_press_force_n``, or at the arm's maximum press depth): safe on any
  shape, flat or pointed, and always a real press even when the guarded approach overshoots.

The motion of one pose (``collect.collection`` runs it): travel to ``above_pose`` (the pressing
axis through the contact point, ``clearance_m`` above the object's top), approach along the axis
until contact (guarded by the contact force, at most ``approach_travel_m``), press to the target
force, hold ``hold_s``, retract to ``above_pose``. Before an object's first pose the arm rests at
``reference_pose`` (untilted, ``reference_clearance_m`` above the object) for ``reference_s`` to
record no-contact reference frames. Moves between objects go through ``travel_z``.

Every pose is checked against the arm's ``SafetyLimits`` (workspace box, tilt, force limit,
speeds) at plan time: a mesh that cannot be reached safely raises ``InputError`` before the arm
moves. Poses are ``(6,) [x, y, z, rx, ry, rz]`` m + rotation vector of the TCP (the membrane
apex) in the base frame.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from collect.arm import MotionSettings, check_motion_settings, move_duration_s, retract_speed
from collect.errors import InputError
from collect.numbers import whole_number
from collect.safety import SafetyLimits
from collect.transforms import linear_path_m

#: TCP orientation pressing straight down (TCP +z along base -z), yaw 0.
DOWN = Rotation.from_rotvec([np.pi, 0.0, 0.0])
#: Most contact poses per object a plan takes (1000 presses of one object are hours of bench time).
MAX_POSES_PER_OBJECT = 1000


@dataclass(frozen=True)
class PlanSettings:
    """Knobs of the collection plan. Distances m, times s, forces N (the speeds are the bench's
    ``MotionSettings``).

    With the default motion settings, the defaults fit 4 objects x 8 poses into under 60 s of arm
    time (see ``estimated_duration_s``).
    """

    poses_per_object: int = 8
    seed: int = 0
    max_tilt_deg: float = 15.0
    press_force_n: tuple[float, float] = (2.0, 6.0)  # force added by the press beyond first contact
    max_press_force_n: float = 15.0  # cap of the total contact force of a press
    clearance_m: float = 0.006  # above-pose height over the object's top
    approach_margin_m: float = 0.008  # extra guarded travel past the planned contact point
    reference_clearance_m: float = 0.02
    travel_clearance_m: float = 0.03  # travel height over the tallest object between objects
    hold_s: float = 0.25
    reference_s: float = 0.4

    def __post_init__(self):
        if not whole_number(self.seed):
            raise InputError(f"plan seed must be a whole number >= 0, got {self.seed!r}")
        if not 1 <= int(self.poses_per_object) <= MAX_POSES_PER_OBJECT:
            raise InputError(f"poses per object must be 1..{MAX_POSES_PER_OBJECT}, got {self.poses_per_object}")
        lo, hi = self.press_force_n
        if not 0 < lo <= hi:
            raise InputError(f"press force range must satisfy 0 < min <= max, got {self.press_force_n}")
        if not 0 <= self.max_tilt_deg <= 45:
            raise InputError(f"max tilt must be 0..45 deg, got {self.max_tilt_deg}")


@dataclass(frozen=True)
class ContactPose:
    """One planned press. Points (3,) m and poses (6,) m + rotvec in the base frame."""

    pose_id: int  # session-wide contact pose index (object_index * poses_per_object + index_in_object)
    object_index: int  # index into ``CollectionPlan.objects``
    index_in_object: int  # k: the pose's place among its object's poses, 0..poses_per_object-1
    object_name: str
    contact_point: np.ndarray  # (3,) planned first-contact point on the object surface
    surface_normal: np.ndarray  # (3,) unit, at the contact point
    tilt_deg: float  # angle of the pressing axis from straight down
    yaw_deg: float  # rotation of the sensor about the vertical, before the tilt (see pressing_rotation)
    press_force_n: float  # force the press adds beyond the force at first contact
    above_pose: np.ndarray  # (6,) start and end of the press, clear above the object
    approach_travel_m: float  # guarded approach length along the pressing axis from above_pose


@dataclass(frozen=True)
class ObjectStop:
    """Per-object waypoints: ``reference_pose`` (6,) for the no-contact frames, ``travel_pose`` (6,)
    at the travel height above it."""

    object_index: int
    name: str
    reference_pose: np.ndarray
    travel_pose: np.ndarray


@dataclass(frozen=True)
class CollectionPlan:
    """Everything ``run_collection`` needs: objects (in session order), stops, poses, the plan's
    settings and the motion settings it runs at."""

    objects: list  # placed bench objects (name, mesh, fixture_pose, primitive, mesh_sha256, ...)
    stops: list[ObjectStop]
    poses: list[ContactPose]
    settings: PlanSettings = field(default_factory=PlanSettings)
    motion: MotionSettings = field(default_factory=MotionSettings)

    def poses_of(self, object_index: int) -> list[ContactPose]:
        """The contact poses on object ``object_index`` (its place in ``objects``), in plan order."""
        return [p for p in self.poses if p.object_index == object_index]

    def describe(self) -> dict:
        """JSON-serializable summary stored in the session (``collection_plan`` attribute)."""
        settings = asdict(self.settings)
        settings["press_force_n"] = list(settings["press_force_n"])
        return {
            "objects": [o.name for o in self.objects],
            "mesh_sha256": [o.mesh_sha256 for o in self.objects],
            "settings": settings,
            "motion": asdict(self.motion),
        }

    def estimated_duration_s(self) -> float:
        """Planned arm time (s) of the whole run: moves at their speed caps plus holds.

        Approaches and presses are counted to their planned ends (contact at the planned point,
        press depth ``press_force_n / 1.5 N/mm``, a conservative membrane stiffness)."""
        s, m = self.settings, self.motion
        total = 0.0
        position = None
        for stop in self.stops:
            if position is not None:
                total += _move_s(position, stop.travel_pose, m.travel_speed, m.accel)
            total += _move_s(stop.travel_pose, stop.reference_pose, m.travel_speed, m.accel) + s.reference_s
            position = stop.reference_pose
            for pose in self.poses_of(stop.object_index):
                total += _move_s(position, pose.above_pose, m.travel_speed, m.accel)
                reach = pose.approach_travel_m - s.approach_margin_m
                press = min(pose.press_force_n / 1500.0, m.max_press_depth_m)
                total += move_duration_s(reach, m.approach_speed, m.accel)
                total += move_duration_s(press, m.press_speed, m.accel) + s.hold_s
                total += move_duration_s(reach + press, retract_speed(m), m.accel)
                position = pose.above_pose
            total += _move_s(position, stop.travel_pose, m.travel_speed, m.accel)
            position = stop.travel_pose
        return total


def _move_s(a: np.ndarray, b: np.ndarray, speed: float, accel: float) -> float:
    """Duration (s) of a linear move between poses ``a`` and ``b`` (6,), reorientation included."""
    return move_duration_s(linear_path_m(a, b), speed, accel)


def pressing_rotation(tilt_deg: float, tilt_direction_rad: float, yaw_rad: float) -> Rotation:
    """TCP orientation whose +z is straight down tilted by ``tilt_deg`` towards the horizontal
    direction ``tilt_direction_rad`` (from base +x), after a yaw of ``yaw_rad`` about the vertical."""
    tilt_axis = np.array([-np.sin(tilt_direction_rad), np.cos(tilt_direction_rad), 0.0])
    tilt = Rotation.from_rotvec(tilt_axis * np.radians(tilt_deg))
    return tilt * Rotation.from_rotvec([0.0, 0.0, yaw_rad]) * DOWN


def check_unique_names(names: list[str]) -> None:
    """Raise ``InputError`` when an object name repeats: a session, its plan and its reference
    frames key their objects by name."""
    duplicates = sorted({n for n in names if names.count(n) > 1})
    if duplicates:
        raise InputError(f"object names must be unique, got {', '.join(duplicates)} twice")


def check_object_names(names) -> None:
    """Raise ``InputError`` for an unknown object or a bad mesh file among ``names`` (built-in names or
    mesh paths), or for two that load under one name (``check_unique_names``): checked before a run."""
    from hw_mocks.objects import load_object

    check_unique_names([load_object(name).name for name in names])


def plan_collection(objects: list, limits: SafetyLimits, settings: PlanSettings = PlanSettings(),
                    motion: MotionSettings = MotionSettings()) -> CollectionPlan:
    """Plan reference stops and ``settings.poses_per_object`` contact poses for each placed object,
    run at the speeds of ``motion`` and pressing at most ``motion.max_press_depth_m``.

    ``objects``: bench objects already mounted on the fixture plate (``hw_mocks.objects.fixture_plate``),
    with ``name``, ``top_surface_points(n, rng)``, ``top_point()``, ``bounds_base()``.
    Raises ``InputError`` (``SafetyViolation``) when an object cannot be reached safely.
    """
    if not objects:
        raise InputError("no objects to collect on: give --objects and/or --object-mesh")
    check_unique_names([o.name for o in objects])
    s = settings
    check_motion_settings(motion, limits)
    limits.check_force(s.max_press_force_n)
    if s.max_tilt_deg > limits.max_tilt_deg:
        raise InputError(f"plan tilt {s.max_tilt_deg} deg exceeds the arm's limit {limits.max_tilt_deg} deg")
    travel_z = max(float(o.bounds_base()[1, 2]) for o in objects) + s.travel_clearance_m
    deepest_press = f" (the deepest press, {motion.max_press_depth_m * 1e3:.3g} mm past the first touch: motion.max_press_depth_m)"
    rng = np.random.default_rng(s.seed)
    stops, poses = [], []
    for index, obj in enumerate(objects):
        top_z = float(obj.bounds_base()[1, 2])
        centre = obj.top_point()
        reference = np.concatenate([[centre[0], centre[1], top_z + s.reference_clearance_m], DOWN.as_rotvec()])
        travel = reference.copy()
        travel[2] = max(travel_z, reference[2])
        for pose in (reference, travel):
            _check_reachable(limits, obj.name, pose)
        stops.append(ObjectStop(index, obj.name, reference, travel))
        points, normals = obj.top_surface_points(s.poses_per_object, rng)
        tilts = rng.uniform(0.0, s.max_tilt_deg, s.poses_per_object)
        tilt_directions = rng.uniform(0.0, 2 * np.pi, s.poses_per_object)
        yaws = np.sort(rng.uniform(-np.pi / 2, np.pi / 2, s.poses_per_object))
        for k in range(s.poses_per_object):
            tilt, yaw = float(tilts[k]), float(yaws[k])
            rot = pressing_rotation(tilt, tilt_directions[k], yaw)
            axis = rot.apply([0.0, 0.0, 1.0])  # pressing direction, points down
            # above_pose on the pressing axis through the contact point, clearance over the top
            back = (top_z + s.clearance_m - points[k, 2]) / -axis[2]
            above = np.concatenate([points[k] - axis * back, rot.as_rotvec()])
            approach = back + s.approach_margin_m
            if approach > motion.max_contact_travel_m:  # the arm would be sent further than the setting allows
                raise InputError(
                    f"plan: the guarded approach to {obj.name} (pose {k + 1}/{s.poses_per_object}) is "
                    f"{approach * 1e3:.1f} mm, longer than "
                    f"motion.max_contact_travel_m {motion.max_contact_travel_m * 1e3:.3g} mm; raise that setting")
            # targets the arm is sent to: the guarded approach's end and the deepest press
            approach_end, deepest = above.copy(), above.copy()
            approach_end[:3] += axis * approach
            deepest[:3] += axis * (back + motion.max_press_depth_m)
            for pose, target in ((above, ""), (approach_end, ""), (deepest, deepest_press)):
                _check_reachable(limits, obj.name, pose, target)
            poses.append(
                ContactPose(
                    pose_id=index * s.poses_per_object + k,
                    object_index=index,
                    index_in_object=k,
                    object_name=obj.name,
                    contact_point=points[k].copy(),
                    surface_normal=normals[k].copy(),
                    tilt_deg=tilt,
                    yaw_deg=float(np.degrees(yaw)),
                    press_force_n=float(rng.uniform(*s.press_force_n)),
                    above_pose=above,
                    approach_travel_m=float(approach),
                )
            )
    return CollectionPlan(list(objects), stops, poses, s, motion)


def _check_reachable(limits: SafetyLimits, name: str, pose: np.ndarray, target: str = "") -> None:
    """``limits.check_pose(pose)``, its error naming the object ``name`` and the ``target`` the pose is."""
    try:
        limits.check_pose(pose)
    except InputError as err:
        raise type(err)(f"object '{name}' cannot be reached safely: {err}{target}") from None
