"""Pose planner on the real built-in objects and mesh files: reproducible, within limits, reachable."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from collect.errors import InputError
from collect.pose_planner import PlanSettings, plan_collection
from collect.safety import SafetyLimits, tilt_deg, tool_z_axis
from hw_mocks.objects import fixture_plate, load_object

BUILTINS = ("mug", "wine_glass", "box", "fingers")
#: a 1.2 m box around the robot's base, the plate inside it
BOX = SafetyLimits(workspace_min=(-0.6, -0.6, 0.0), workspace_max=(0.6, 0.6, 0.6))


@pytest.fixture(scope="module")
def plate():
    return fixture_plate([load_object(name) for name in BUILTINS])


def test_plan_is_reproducible_and_varies_with_seed(plate):
    a = plan_collection(plate, BOX, PlanSettings(poses_per_object=3, seed=7))
    b = plan_collection(plate, BOX, PlanSettings(poses_per_object=3, seed=7))
    c = plan_collection(plate, BOX, PlanSettings(poses_per_object=3, seed=8))
    first = np.array([p.above_pose for p in a.poses])
    np.testing.assert_array_equal(first, np.array([p.above_pose for p in b.poses]))
    assert np.abs(first - np.array([p.above_pose for p in c.poses])).max() > 1e-3


def test_poses_press_the_upper_surface_within_limits(plate):
    settings = PlanSettings(poses_per_object=8, seed=1)
    plan = plan_collection(plate, BOX, settings)
    assert [p.pose_id for p in plan.poses] == list(range(4 * 8))
    assert [s.name for s in plan.stops] == list(BUILTINS)
    tilts = []
    for pose in plan.poses:
        obj = plate[pose.object_index]
        lo, hi = obj.bounds_base()
        assert np.all(pose.contact_point >= lo - 1e-6) and np.all(pose.contact_point <= hi + 1e-6)
        assert pose.contact_point[2] > hi[2] - 0.026  # upper part of the object
        assert pose.surface_normal[2] > np.cos(np.radians(26))
        assert pose.above_pose[2] == pytest.approx(hi[2] + settings.clearance_m)
        tilt = tilt_deg(pose.above_pose)
        assert tilt == pytest.approx(pose.tilt_deg, abs=1e-6) and tilt <= 15.0
        tilts.append(tilt)
        # the pressing axis from the above pose runs through the contact point
        axis = tool_z_axis(pose.above_pose)
        offset = pose.contact_point - pose.above_pose[:3]
        assert np.linalg.norm(np.cross(axis, offset)) < 1e-9 and np.dot(axis, offset) > 0
        assert pose.approach_travel_m == pytest.approx(np.dot(axis, offset) + settings.approach_margin_m)
        assert settings.press_force_n[0] <= pose.press_force_n <= settings.press_force_n[1]
    assert max(tilts) > 8.0  # tilts are actually drawn, not all straight down
    for stop in plan.stops:
        assert tilt_deg(stop.reference_pose) < 1e-6
        assert stop.reference_pose[2] == pytest.approx(plate[stop.object_index].bounds_base()[1, 2] + 0.02)
    # the sub-minute calibration set: 4 objects x 8 poses within 60 s of arm time
    assert 30.0 < plan.estimated_duration_s() <= 60.0
    assert plan.describe()["objects"] == list(BUILTINS)


def test_mesh_file_plans_and_unreachable_mesh_is_rejected(tmp_path):
    column = trimesh.creation.cylinder(radius=0.03, height=0.3)
    column.apply_translation([0, 0, 0.15])
    path = tmp_path / "column.stl"
    column.export(path)
    placed = fixture_plate([load_object(path)])
    plan = plan_collection(placed, BOX, PlanSettings(poses_per_object=2))
    assert plan.stops[0].name == "column" and len(plan.poses) == 2
    low_ceiling = SafetyLimits(workspace_min=BOX.workspace_min, workspace_max=(0.6, 0.6, 0.25))
    with pytest.raises(InputError, match="object 'column' cannot be reached safely: .*outside the workspace"):
        plan_collection(placed, low_ceiling, PlanSettings(poses_per_object=2))


def test_bad_plans(plate):
    with pytest.raises(InputError, match="no objects"):
        plan_collection([], BOX)
    with pytest.raises(InputError, match="unique"):
        plan_collection([plate[0], plate[0]], BOX)
    with pytest.raises(InputError, match="force"):
        plan_collection(plate, SafetyLimits(BOX.workspace_min, BOX.workspace_max, force_limit_n=10.0), PlanSettings(max_press_force_n=15.0))
    with pytest.raises(InputError, match="poses per object"):
        PlanSettings(poses_per_object=0)


def test_a_negative_seed_and_an_approach_beyond_the_contact_travel_setting_are_refused(plate):
    """Was: a negative seed was numpy's ValueError after the real bench had connected; and
    ``motion.max_contact_travel_m`` was ignored (the arm was sent the plan's 14-20 mm approach)."""
    from collect.arm import MotionSettings

    with pytest.raises(InputError, match="plan seed must be a whole number >= 0, got -1"):
        PlanSettings(seed=-1)
    with pytest.raises(InputError, match=r"the guarded approach to mug \(pose 1/2\) is 1\d\.\d mm, longer than "
                                         r"motion.max_contact_travel_m 5 mm"):
        plan_collection(plate, BOX, PlanSettings(poses_per_object=2), MotionSettings(max_contact_travel_m=0.005))
