"""Physics of the simulated bubble: contact, pressure, gas law, wrench, leak, warm start."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from hw_mocks.bubble_sim import BubbleSim
from hw_mocks.objects import BenchObject, fixture_plate, load_object
from hw_mocks.obstacle import object_depth
from hw_mocks.preview import press_pose
from hw_mocks.sensor_spec import draw_sensor
from collect.transforms import invert, pose_to_matrix


@pytest.fixture(scope="module")
def spec():
    return draw_sensor(7)


@pytest.fixture(scope="module")
def plate():
    return fixture_plate([load_object(n) for n in ("mug", "box", "fingers")])


@pytest.fixture(scope="module")
def probe():
    """A 10 mm radius sphere on a post: the 'small rounded probe' of the real-bubble reference."""
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=0.010)
    sphere.apply_translation([0.0, 0.0, 0.030])
    return fixture_plate([BenchObject("probe", sphere)])[0]


def test_zero_press_gives_rest_shape(spec, plate):
    sim = BubbleSim(spec, plate)
    box = plate[1]
    for pose in (press_pose(box.top_point(), -0.010), [0.45, 0.0, 0.4, np.pi, 0.0, 0.0]):
        state = sim.solve(pose, 0.0)
        assert np.array_equal(state.true_depth, sim.rest_depth)
        assert not state.contact.any() and state.object_index == -1
        assert state.pressure_hpa == pytest.approx(spec.rest_pressure_pa / 100, abs=1e-9)
        assert np.all(state.wrench == 0)
    valid = sim.rest_depth[sim.membrane_mask]
    assert 0.055 <= valid.min() and valid.max() <= 0.1
    assert not sim.membrane_mask[[0, 0, -1, -1], [0, -1, 0, -1]].any()  # corners see the housing
    assert sim.membrane_mask.mean() > 0.6


def test_indentation_is_local_and_never_through_the_object(spec, plate):
    sim = BubbleSim(spec, plate)
    box = plate[1]
    pose = press_pose(box.top_point(), 0.008)
    state = sim.solve(pose, 0.0)
    assert state.object_index == 1 and state.contact.sum() > 200
    # Object depth along every full-resolution ray, computed independently of the solver.
    obj_from_cam = invert(box.object_to_base()) @ pose_to_matrix(pose) @ sim.dome.tcp_from_cam
    obj = object_depth(box.heightmap, obj_from_cam, sim.grid.rays, sim.rest_depth.astype(np.float64))
    mask = sim.membrane_mask
    assert np.all(state.true_depth[mask] <= obj[mask] + 2e-5)
    lowered = mask & (sim.rest_depth - state.true_depth > 1e-4)
    # Lowered pixels lie within ~3 dent decay lengths of the contact (physical distance on the membrane).
    pts = sim.grid.rays * sim.rest_depth[..., None]
    to_contact = cKDTree(pts[state.contact][:, :2])
    assert to_contact.query(pts[lowered][:, :2])[0].max() < 0.03
    # Away from the contact the free membrane bulges out (deeper than rest), never in.
    away = to_contact.query(pts[mask][:, :2])[0] > 0.03
    change = (state.true_depth - sim.rest_depth)[mask][away]
    assert change.min() >= -1e-6 and change.max() > 2e-4


def test_deeper_press_raises_pressure_and_force(spec, plate):
    sim = BubbleSim(spec, plate)
    top = plate[0].top_point()
    pressures, forces = [], []
    for press in (0.002, 0.005, 0.008, 0.012):
        state = sim.solve(press_pose(top, press), 0.0)
        pressures.append(state.pressure_hpa)
        forces.append(state.wrench[2])
        assert abs(state.wrench[0]) < 0.05 * state.wrench[2] and abs(state.wrench[1]) < 0.05 * state.wrench[2]
    assert np.all(np.diff(pressures) > 0) and np.all(np.diff(forces) > 0)
    assert forces[0] > 0  # pressing from above pushes the sensor up (+z base)
    assert 3.0 < forces[1] < 40.0 and 1.0 < pressures[1] - spec.rest_pressure_pa / 100 < 40.0


def test_gas_law_and_real_bubble_reference(spec, probe):
    sim = BubbleSim(spec, [probe])
    state = sim.solve(press_pose(probe.top_point(), 0.005), 0.0)
    p = state.pressure_hpa * 100
    # Isothermal: P (V0 + dV) = P0 V0 for a sealed bubble.
    assert p * (spec.gas_volume_m3 + state.net_volume_change_m3) == pytest.approx(
        spec.rest_pressure_pa * spec.gas_volume_m3, rel=1e-9
    )
    dp_hpa = state.pressure_hpa - spec.rest_pressure_pa / 100
    dent_cm3 = state.dent_volume_m3 * 1e6
    # Real Soft-bubble reference (docs/simulator.md), within 30 %.
    assert dp_hpa / dent_cm3 == pytest.approx(1.9, rel=0.3)
    assert 1 + state.net_volume_change_m3 / state.dent_volume_m3 == pytest.approx(0.75, rel=0.3)
    assert state.wrench[2] / dp_hpa == pytest.approx(1.0, rel=0.3)
    assert state.wrench[2] == pytest.approx(4.6, rel=0.3)


def test_off_centre_press_gives_torque_about_the_tcp(spec, probe):
    sim = BubbleSim(spec, [probe])
    top = probe.top_point()
    y_tcp = -0.02  # the probe touches the dome flank 20 mm along TCP -y (base +y: rotvec [pi,0,0])
    drop = spec.dome_height_m * (y_tcp / spec.dome_semi_y_m) ** 2
    pose = np.array([top[0], top[1] - 0.02, top[2] - 0.005 - drop, np.pi, 0.0, 0.0])
    state = sim.solve(pose, 0.0)
    f, tau = state.wrench[:3], state.wrench[3:]
    assert f[2] > 1.0
    assert f[1] < -0.2 * f[2]  # the flank is inclined: the reaction pushes the sensor to base -y
    # Small contact patch: torque ~ (centre of the patch - TCP) x force.
    pts_cam = sim.grid.rays[state.contact] * state.true_depth[state.contact][:, None]
    base_from_cam = pose_to_matrix(pose) @ sim.dome.tcp_from_cam
    centre = (pts_cam @ base_from_cam[:3, :3].T + base_from_cam[:3, 3]).mean(axis=0) - pose[:3]
    assert np.linalg.norm(tau - np.cross(centre, f)) < 0.1 * np.linalg.norm(tau)
    assert tau[0] > 0


def test_leak_loses_pressure_over_time(plate):
    leaky = BubbleSim(draw_sensor(7, "leak"), plate)
    sealed = BubbleSim(draw_sensor(7), plate)
    far = [0.45, 0.0, 0.4, np.pi, 0.0, 0.0]
    drop = leaky.solve(far, 0.0).pressure_hpa - leaky.solve(far, 60.0).pressure_hpa
    assert drop > 1.0
    assert sealed.solve(far, 0.0).pressure_hpa == sealed.solve(far, 60.0).pressure_hpa
    # The deflating membrane sags towards the camera.
    sagged = leaky.solve(far, 60.0)
    assert (sagged.true_depth < leaky.rest_depth - 1e-5).sum() > 1000


def test_warm_start_matches_a_cold_solve(spec, plate):
    top = plate[2].top_point()
    warm = BubbleSim(spec, plate)
    for press in np.linspace(0.0, 0.007, 8):
        state = warm.solve(press_pose(top, press), 0.0)
    cold = BubbleSim(spec, plate).solve(press_pose(top, 0.007), 0.0)
    rise = cold.pressure_hpa - spec.rest_pressure_pa / 100
    assert state.pressure_hpa == pytest.approx(cold.pressure_hpa, abs=0.01 * rise)
    assert np.abs(state.true_depth - cold.true_depth).max() < 1e-5
    assert state.wrench[2] == pytest.approx(cold.wrench[2], rel=0.01)
    assert warm.solve(press_pose(top, 0.007), 0.0) is state  # same pose: cached



def test_a_free_bubble_reads_its_rest_depth_up_to_the_rim():
    """Was: where no object was, the clamp's placeholder depth was 40 mm off the membrane too (rest
    depth 0 there); interpolated across the rim it made a false contact and a 10 mm dip at rest on
    some sensors (seed 8: pixel (48, 20))."""
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.010)
    sphere.apply_translation([0, 0, 0.03])
    probe = fixture_plate([BenchObject("probe", sphere)])[0]
    sim = BubbleSim(draw_sensor(8), [probe])
    free = sim.solve(press_pose(probe.top_point(), -0.02), 0.0)
    mask = sim.membrane_mask
    assert np.abs(free.true_depth - sim.rest_depth)[mask].max() < 1e-6 and not free.contact.any()


def test_a_no_dots_sensor_is_the_same_sensor_without_its_dots():
    """Was: the dot coverage was not drawn for it, and every later draw shifted: another sensor."""
    healthy, no_dots = draw_sensor(1).to_dict(), draw_sensor(1, "no-dots").to_dict()
    differ = sorted(k for k in healthy if healthy[k] != no_dots[k])
    assert differ == ["defect", "dot_coverage", "serial"] and no_dots["dot_coverage"] == 0.0  # its serial names the defect
