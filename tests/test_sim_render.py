"""Rendering of the simulated bubble: dots, IR, ToF artifacts, sensor variation, determinism."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest

from collect.session_format import DEPTH_UNIT_M
from hw_mocks.bubble_sim import BubbleSim
from hw_mocks.objects import fixture_plate, load_object
from hw_mocks.preview import press_pose
from hw_mocks.sensor_spec import draw_sensor

FAR = [0.45, 0.0, 0.4, np.pi, 0.0, 0.0]


@pytest.fixture(scope="module")
def plate():
    return fixture_plate([load_object(n) for n in ("mug", "box")])


def test_tof_at_rest_is_plausible(plate):
    spec = draw_sensor(3)
    sim = BubbleSim(spec, plate)
    frame = sim.frame(FAR, 0.0, np.random.default_rng(0))
    assert frame.ir.dtype == np.uint16 and frame.depth.dtype == np.uint16
    assert frame.ir.shape == frame.depth.shape == (spec.height, spec.width)
    valid = frame.depth > 0
    assert not valid[~sim.membrane_mask].any()  # housing is invalid
    assert valid[sim.membrane_mask].mean() > 0.8
    # ~0.05 mm noise on bright (undotted) membrane near the axis, after removing the sensor's bias.
    err = frame.depth * DEPTH_UNIT_M - frame.state.true_depth
    albedo = sim.membrane_albedo(frame.state)
    h, w = sim.rest_depth.shape
    centre = np.zeros_like(valid)
    centre[h // 3 : 2 * h // 3, w // 3 : 2 * w // 3] = True
    bright = valid & centre & (albedo > 0.9 * spec.membrane_albedo)
    assert 0.02e-3 < np.std(err[bright]) < 0.1e-3
    # On the dark dots the ToF is noisier (noise grows as amplitude falls).
    dark = valid & centre & (albedo < 0.3)
    assert np.std(err[dark]) > 2 * np.std(err[bright])


def test_dots_move_with_the_membrane(plate):
    spec = draw_sensor(4)
    sim = BubbleSim(spec, plate)
    mug = plate[0]
    pose = press_pose(mug.top_point(), 0.010)
    pose[0] += 0.025  # contact on the dome flank, where the material moves across the image
    state = sim.solve(pose, 0.0)
    assert state.contact.sum() > 100
    flow = np.linalg.norm(state.material_flow, axis=-1)
    assert flow[state.contact].mean() > 0.5  # px
    rest = sim.solve(FAR, 0.0)
    assert np.abs(rest.material_flow).max() < 1e-6
    moved = np.abs(sim.membrane_albedo(state) - sim.texture)
    assert moved[state.contact].mean() > 0.02  # the pattern seen in the dent has changed
    far = sim.membrane_mask & (flow < 0.01)
    assert moved[far].max() < 0.02  # ...and nowhere the material stays put
    # Pressed at the apex, the membrane is drawn into the dent from all sides.
    central = sim.solve(press_pose(mug.top_point(), 0.008), 0.0)
    cy, cx = np.argwhere(central.contact).mean(axis=0).astype(int)
    assert central.material_flow[cy, cx - 30, 0] > 0.3 and central.material_flow[cy, cx + 30, 0] < -0.3
    assert central.material_flow[cy - 25, cx, 1] > 0.3 and central.material_flow[cy + 25, cx, 1] < -0.3
    # A sensor without dots has a uniform membrane.
    plain = BubbleSim(draw_sensor(4, "no-dots"), plate)
    assert np.ptp(plain.texture[plain.membrane_mask]) == 0


def test_dropouts_where_amplitude_saturates(plate):
    spec = dataclasses.replace(draw_sensor(5), emitter_amplitude=60000.0)
    sim = BubbleSim(spec, plate)
    state = sim.solve(press_pose(plate[1].top_point(), 0.012), 0.0)
    amplitude, _ = sim.clean_amplitude(state)
    ir, depth = sim.render(state, np.random.default_rng(1))
    saturated = sim.membrane_mask & (amplitude >= spec.saturation_amplitude)
    assert saturated.sum() > 50
    assert (depth[saturated] == 0).all()
    assert ir[saturated].mean() > 0.9 * spec.saturation_amplitude
    unsaturated_valid = (depth > 0) & sim.membrane_mask
    assert unsaturated_valid.sum() > 5000


def test_flying_pixels_at_contact_edges(plate):
    spec = draw_sensor(6)
    sim = BubbleSim(spec, plate)
    state = sim.solve(press_pose(plate[1].top_point(), 0.014), 0.0)  # box pressed deep: steep dent walls
    filled = np.where(sim.membrane_mask, state.true_depth, sim.housing_depth).astype(np.float32)
    kernel = np.ones((3, 3), np.uint8)
    spread = cv2.dilate(filled, kernel) - cv2.erode(filled, kernel) - sim.tof.rest_spread
    walls = sim.tof.valid_fov & (spread > spec.flying_pixel_jump_m)
    assert walls.sum() > 50
    amplitude, incidence = sim.clean_amplitude(state)
    ordinary = sim.tof.valid_fov & ~walls & (amplitude < spec.saturation_amplitude) & (amplitude > spec.min_amplitude)
    ordinary &= incidence > spec.min_incidence_cos
    errors, dropped = [], []
    for k in range(4):
        _, depth = sim.render(state, np.random.default_rng(k))
        err = np.abs(depth * DEPTH_UNIT_M - state.true_depth - sim.tof.bias)
        errors.append((np.median(err[walls & (depth > 0)]), np.median(err[ordinary & (depth > 0)])))
        dropped.append(((depth == 0) & walls).mean() / walls.mean())
    wall_err, ordinary_err = np.mean(errors, axis=0)
    assert wall_err > 2 * ordinary_err  # flying pixels mix near and far depths
    assert 0.1 < np.mean(dropped) < 0.5  # and some are rejected by the camera (0)
    # At rest nothing is flagged: the dome's own slope is not an edge.
    rest = np.where(sim.membrane_mask, sim.rest_depth, sim.housing_depth).astype(np.float32)
    assert not (cv2.dilate(rest, kernel) - cv2.erode(rest, kernel) - sim.tof.rest_spread > 0).any()


def test_two_seeds_give_different_sensors(plate):
    a, b = BubbleSim(draw_sensor(1), plate), BubbleSim(draw_sensor(2), plate)
    assert a.spec.serial != b.spec.serial and a.spec.dot_seed != b.spec.dot_seed
    both = a.membrane_mask & b.membrane_mask
    assert np.abs(a.rest_depth - b.rest_depth)[both].mean() > 2e-4
    ira = a.frame(FAR, 0.0, np.random.default_rng(0)).ir.astype(float)
    irb = b.frame(FAR, 0.0, np.random.default_rng(0)).ir.astype(float)
    assert np.abs(ira - irb)[both].mean() > 1000


def test_same_seed_gives_the_same_frames(plate):
    frames = []
    for _ in range(2):
        sim = BubbleSim(draw_sensor(9), plate, seed=3)
        pose = press_pose(plate[0].top_point(), 0.004)
        frames.append([sim.frame(pose, 0.0), sim.frame(FAR, 0.1)])
    for f1, f2 in zip(*frames):
        assert np.array_equal(f1.ir, f2.ir) and np.array_equal(f1.depth, f2.depth)
        assert np.array_equal(f1.state.true_depth, f2.state.true_depth)


def test_dead_pixels_are_stuck(plate):
    spec = draw_sensor(11, "dead-pixels")
    sim = BubbleSim(spec, plate)
    rows, cols = np.asarray(spec.dead_pixels).T
    for k, pose in enumerate((FAR, press_pose(plate[0].top_point(), 0.006))):
        frame = sim.frame(pose, 0.0, np.random.default_rng(k))
        assert (frame.ir[rows, cols] == spec.dead_pixel_ir).all()
        assert (frame.depth[rows, cols] == round(spec.dead_pixel_depth_m / DEPTH_UNIT_M)).all()
    assert 30 <= len(spec.dead_pixels) <= 80
