"""Proximity pose estimation: shapes' signed distances, the analytic Jacobian, and the fit."""

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from calibrate.pose_estimation import (
    Cylinder,
    PRIOR_WEIGHT,
    GridSDF,
    Pose,
    ProximityPoseEstimator,
    align_symmetry,
    matrix_to_quat,
    orientation_error,
    point_residuals,
    position_error,
    quat_to_matrix,
    shape_from_object,
)
from collect.errors import InputError

CYL = Cylinder(radius=0.04, height=0.1, center=(0.0, 0.0, 0.05))


def _pose(rotvec, t) -> Pose:
    transform = np.eye(4)
    transform[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    transform[:3, 3] = t
    return Pose.from_matrix(transform)


def _side_and_rim_patch(rng, n=1500):
    """Points on the cylinder's side near its top rim and on the top cap edge (object frame)."""
    n_side = n * 2 // 3
    ang = rng.uniform(-0.6, 0.6, n)
    side = np.stack([0.04 * np.cos(ang[:n_side]), 0.04 * np.sin(ang[:n_side]),
                     rng.uniform(0.075, 0.1, n_side)], axis=1)
    rad = rng.uniform(0.025, 0.04, n - n_side)
    cap = np.stack([rad * np.cos(ang[n_side:]), rad * np.sin(ang[n_side:]), np.full(n - n_side, 0.1)], axis=1)
    return np.concatenate([side, cap])


def test_cylinder_signed_distance_values_and_gradients():
    pts = np.array([
        [0.05, 0.0, 0.05],  # 1 cm outside the side wall
        [0.0, 0.0, 0.13],  # 3 cm above the top cap
        [0.0, 0.0, -0.02],  # 2 cm below the bottom cap
        [0.07, 0.0, 0.14],  # outside the top rim: corner region, 3-4-5 triangle
        [0.035, 0.0, 0.05],  # inside, 5 mm from the wall
        [0.0, 0.0, 0.098],  # inside, 2 mm from the top
    ])
    phi, grad = CYL.signed_distance(pts)
    np.testing.assert_allclose(phi, [0.01, 0.03, 0.02, 0.05, -0.005, -0.002], atol=1e-12)
    np.testing.assert_allclose(grad, [[1, 0, 0], [0, 0, 1], [0, 0, -1], [0.6, 0, 0.8], [1, 0, 0], [0, 0, 1]],
                               atol=1e-12)


@pytest.mark.parametrize("region", ["side", "cap", "inside", "corner"])
def test_point_jacobian_matches_finite_differences(region):
    rng = np.random.default_rng(1)
    pose = _pose([0.3, -0.2, 0.5], [0.01, -0.02, 0.09])
    obj = {
        "side": lambda: np.stack([0.043 * np.ones(50), rng.uniform(-0.01, 0.01, 50), rng.uniform(0.02, 0.08, 50)], 1),
        "cap": lambda: np.stack([rng.uniform(-0.02, 0.02, 50), rng.uniform(-0.02, 0.02, 50), 0.103 * np.ones(50)], 1),
        "inside": lambda: np.stack([rng.uniform(-0.01, 0.01, 50), rng.uniform(0.03, 0.035, 50), rng.uniform(0.03, 0.07, 50)], 1),
        "corner": lambda: np.stack([0.045 + rng.uniform(0, 0.005, 50), rng.uniform(-0.002, 0.002, 50), rng.uniform(0.104, 0.11, 50)], 1),
    }[region]()
    points = obj @ quat_to_matrix(pose.quaternion).T + pose.position
    # a non-unit quaternion exercises the normalization inside the residual
    theta = np.concatenate([pose.position + 1e-3, 1.3 * pose.quaternion + 0.01])
    _, jac = point_residuals(theta, points, CYL)
    eps = 1e-7
    numeric = np.stack([
        (point_residuals(theta + eps * e, points, CYL, False)[0]
         - point_residuals(theta - eps * e, points, CYL, False)[0]) / (2 * eps)
        for e in np.eye(7)], axis=1)
    np.testing.assert_allclose(jac, numeric, atol=1e-6)
    # scaling the quaternion does not move the residuals: the Jacobian is orthogonal to q
    np.testing.assert_allclose(jac[:, 3:] @ theta[3:], 0.0, atol=1e-10)


def test_estimator_jacobian_includes_norm_and_prior_rows():
    rng = np.random.default_rng(2)
    est = ProximityPoseEstimator(CYL, prior_weight=0.1, norm_weight=2.0)
    prior = _pose([0.1, 0.2, 0.3], [0.0, 0.0, 0.1])
    points = rng.normal(0, 0.03, (40, 3)) + [0, 0, 0.1]
    theta = prior.theta() * 1.1 + 0.01
    jac = est._jacobian(theta, points, prior.theta())
    eps = 1e-7
    numeric = np.stack([(est._residuals(theta + eps * e, points, prior.theta())
                         - est._residuals(theta - eps * e, points, prior.theta())) / (2 * eps)
                        for e in np.eye(7)], axis=1)
    np.testing.assert_allclose(jac, numeric, atol=1e-6)


def test_quaternion_matrix_round_trip():
    rot = Rotation.from_rotvec([0.4, -1.1, 2.0]).as_matrix()
    q = matrix_to_quat(rot)
    assert q[0] >= 0 and abs(np.linalg.norm(q) - 1) < 1e-12
    np.testing.assert_allclose(quat_to_matrix(q), rot, atol=1e-12)


def test_fit_recovers_pose_from_perturbed_prior_with_noise():
    rng = np.random.default_rng(3)
    true = _pose([0.3, -0.2, 0.5], [0.01, -0.02, 0.09])
    obj = _side_and_rim_patch(rng)
    points = obj @ quat_to_matrix(true.quaternion).T + true.position + rng.normal(0, 1e-4, obj.shape)
    prior = _pose(Rotation.from_matrix(quat_to_matrix(true.quaternion)).as_rotvec() + [0.03, -0.02, 0.04],
                  true.position + [0.002, -0.0015, 0.002])
    assert position_error(prior, true) > 2.5e-3 and orientation_error(prior, true) > 1e-4
    fit = ProximityPoseEstimator(CYL).fit(points, prior)
    assert fit.success and fit.n_points + fit.n_outliers == 1500 and fit.n_outliers < 10
    assert position_error(fit.pose, true) < 3e-4  # side + rim constrain all but the spin about the axis
    axis_true = quat_to_matrix(true.quaternion)[:, 2]
    axis_fit = quat_to_matrix(fit.pose.quaternion)[:, 2]
    assert np.degrees(np.arccos(min(1.0, axis_true @ axis_fit))) < 0.2
    assert fit.rms_m < 1.5e-4  # the noise level


def test_side_patch_fixes_axis_line_and_leaves_symmetric_directions_at_prior():
    rng = np.random.default_rng(4)
    ang = rng.uniform(-0.5, 0.5, 800)
    obj = np.stack([0.04 * np.cos(ang), 0.04 * np.sin(ang), rng.uniform(0.04, 0.06, 800)], 1)
    prior = _pose([0.0, 0.0, 0.05], [0.001, 0.002, 0.003])  # spin about the axis, shift along it
    fit = ProximityPoseEstimator(CYL).fit(obj, prior)
    rot = quat_to_matrix(fit.pose.quaternion)
    axis_at_patch = rot @ [0.0, 0.0, 0.05] + fit.pose.position  # on the axis, level with the patch
    # the axis line where the patch is: observed and corrected (the prior was 2.2 mm off) ...
    assert np.hypot(*axis_at_patch[:2]) < 3e-5
    # ... its direction is seen through a 2 cm long patch only: within 1 degree ...
    assert np.degrees(np.arccos(rot[2, 2])) < 1.0
    # ... the shift along the axis and the spin about it are not seen: they stay at the prior
    assert abs(axis_at_patch[2] - 0.053) < 1e-4
    assert orientation_error(fit.pose, prior) < 1e-4


def test_prior_keeps_noisy_fits_of_a_shallow_side_patch_from_wandering():
    """A 1 cm wide patch on the 4 cm radius side barely fixes the axis's position across itself:
    with ToF-like depth noise (0.25 mm) the default prior keeps every fit within 0.6 mm of the
    truth (modulo the symmetry), a 100x weaker one lets some wander by 1.5 mm and more."""
    true = _pose([0.0, 0.0, 0.0], [0.0, 0.0, 0.0])
    prior = _pose([0.02, -0.02, 0.03], [0.001, -0.0015, 0.001])
    errors = {}
    for weight in (1e-2, PRIOR_WEIGHT):
        rng = np.random.default_rng(5)
        errors[weight] = []
        for _ in range(10):
            ang = rng.uniform(-0.12, 0.12, 1500)
            obj = np.stack([0.04 * np.cos(ang), 0.04 * np.sin(ang), rng.uniform(0.04, 0.06, 1500)], 1)
            obj[:, 0] += rng.normal(0, 2.5e-4, 1500)
            fit = ProximityPoseEstimator(CYL, prior_weight=weight).fit(obj, prior)
            assert fit.success
            errors[weight].append(position_error(align_symmetry(CYL, fit.pose, true), true))
    assert max(errors[PRIOR_WEIGHT]) < 6e-4
    assert max(errors[1e-2]) > 1.5e-3


def test_fit_rejects_bad_points():
    est = ProximityPoseEstimator(CYL)
    prior = _pose([0, 0, 0], [0, 0, 0])
    with pytest.raises(InputError, match="too few"):
        est.fit(np.zeros((5, 3)), prior)
    pts = np.random.default_rng(0).normal(size=(100, 3))
    pts[3, 1] = np.nan
    with pytest.raises(InputError, match="NaN"):
        est.fit(pts, prior)


def test_grid_sdf_of_mesh_matches_cylinder_and_fits_the_same_pose():
    mesh = trimesh.creation.cylinder(radius=0.04, height=0.1, sections=128)
    mesh.apply_translation([0, 0, 0.05])
    grid = shape_from_object({"type": "mesh"}, mesh.vertices, mesh.faces)
    assert isinstance(grid, GridSDF)
    np.testing.assert_allclose(grid.center, CYL.center, atol=1e-12)  # the mesh's bounding-box centre
    rng = np.random.default_rng(5)
    probe = np.concatenate([_side_and_rim_patch(rng, 300) * [1.1, 1.1, 1.05],
                            rng.uniform([-0.1, -0.1, -0.05], [0.1, 0.1, 0.2], (300, 3))])
    phi_grid, grad_grid = grid.signed_distance(probe)
    phi_cyl, _ = CYL.signed_distance(probe)
    near = np.abs(phi_cyl) < 0.005  # inside the band: nearest surface sample
    np.testing.assert_allclose(phi_grid[near], phi_cyl[near], atol=1e-3)
    mid = np.abs(phi_cyl) < 0.02  # beyond the band: grid distance to the band
    np.testing.assert_allclose(phi_grid[mid], phi_cyl[mid], atol=2.5e-3)
    far = phi_cyl > 0.03
    assert np.all(phi_grid[far] > 0.02)

    true = _pose([0.2, 0.1, -0.3], [0.0, 0.01, 0.1])
    obj = _side_and_rim_patch(rng)
    points = obj @ quat_to_matrix(true.quaternion).T + true.position
    prior = _pose([0.22, 0.08, -0.28], [0.0015, 0.009, 0.1015])
    fit = ProximityPoseEstimator(grid).fit(points, prior)
    assert position_error(fit.pose, true) < 1e-3


def test_shape_from_object_cylinder_and_errors():
    cyl = shape_from_object({"type": "cylinder", "radius": 0.04, "height": 0.1})
    assert cyl == CYL
    with pytest.raises(InputError):
        shape_from_object({"type": "cylinder", "radius": -1, "height": 0.1})
    with pytest.raises(InputError):
        shape_from_object({"type": "torus"})


def test_tilted_axis_cylinder_matches_canonical_and_jacobian():
    lying = Cylinder(radius=0.041, height=0.095, center=(0.0, 0.0, 0.08), axis=(1.0, 0.0, 0.0))
    upright = Cylinder(radius=0.041, height=0.095)
    rng = np.random.default_rng(6)
    pts = rng.uniform(-0.08, 0.08, (200, 3))
    # lying cylinder = upright one turned +z -> +x, then raised to its centre
    to_upright = Rotation.from_rotvec([0, -np.pi / 2, 0]).as_matrix()  # maps +x to +z
    phi_l, grad_l = lying.signed_distance(pts + [0, 0, 0.08])
    phi_u, grad_u = upright.signed_distance(pts @ to_upright.T)
    np.testing.assert_allclose(phi_l, phi_u, atol=1e-12)
    np.testing.assert_allclose(grad_l @ to_upright.T, grad_u, atol=1e-12)
    theta = _pose([0.1, 0.2, -0.1], [0.0, 0.0, 0.05]).theta()
    _, jac = point_residuals(theta, pts, lying)
    eps = 1e-7
    numeric = np.stack([(point_residuals(theta + eps * e, pts, lying, False)[0]
                         - point_residuals(theta - eps * e, pts, lying, False)[0]) / (2 * eps)
                        for e in np.eye(7)], axis=1)
    np.testing.assert_allclose(jac, numeric, atol=1e-6)


def test_position_error_at_a_point_adds_the_lever_arm_of_a_turn():
    true = _pose([0.3, -0.2, 0.5], [0.01, -0.02, 0.09])
    # turned by 0.01 rad about the x axis through the cylinder's centre (0, 0, 0.05), 50 mm above the origin
    turn = Rotation.from_rotvec([0.01, 0.0, 0.0]).as_matrix()
    about_center = np.eye(4)
    about_center[:3, :3] = turn
    about_center[:3, 3] = np.array(CYL.center) - turn @ CYL.center
    turned = Pose.from_matrix(true.matrix() @ about_center)
    assert position_error(turned, true, CYL.center) < 1e-12
    assert abs(position_error(turned, true) - 0.05 * 2 * np.sin(0.005)) < 1e-9  # at the origin
    assert orientation_error(turned, true) > 1e-5


def test_align_symmetry_removes_spin_and_slide_only():
    true = _pose([0.3, -0.2, 0.5], [0.01, -0.02, 0.09])
    center, axis = np.array(CYL.center), np.array([0.0, 0.0, 1.0])
    sym = np.eye(4)
    spin = Rotation.from_rotvec(0.4 * axis).as_matrix()
    sym[:3, :3] = spin
    sym[:3, 3] = center - spin @ center + 0.007 * axis
    equivalent = Pose.from_matrix(true.matrix() @ sym)
    assert position_error(equivalent, true) > 5e-3
    aligned = align_symmetry(CYL, equivalent, true)
    assert position_error(aligned, true) < 1e-12 and orientation_error(aligned, true) < 1e-12
    # an observable offset (radial) survives the alignment
    off = Pose(equivalent.position + quat_to_matrix(true.quaternion) @ [0.002, 0, 0], equivalent.quaternion)
    assert abs(position_error(align_symmetry(CYL, off, true), true) - 0.002) < 1e-9
    grid_like = object()
    assert align_symmetry(grid_like, off, true) is off


def test_outliers_are_dropped_and_the_fit_refined():
    rng = np.random.default_rng(7)
    true = _pose([0.3, -0.2, 0.5], [0.01, -0.02, 0.09])
    obj = _side_and_rim_patch(rng)
    obj[:60] *= [1.15, 1.15, 1.0]  # flying pixels: 6 mm off the side wall
    points = obj @ quat_to_matrix(true.quaternion).T + true.position + rng.normal(0, 5e-5, obj.shape)
    prior = _pose(Rotation.from_matrix(quat_to_matrix(true.quaternion)).as_rotvec() + [0.02, 0.0, -0.02],
                  true.position + [0.001, 0.001, -0.001])
    robust = ProximityPoseEstimator(CYL).fit(points, prior)
    plain = ProximityPoseEstimator(CYL, outlier_k=0).fit(points, prior)
    assert robust.n_outliers >= 60 and plain.n_outliers == 0
    assert position_error(robust.pose, true) < 3e-4 and position_error(plain.pose, true) > 1e-3


def test_a_few_gross_outliers_do_not_lead_the_first_solve_astray():
    # a ToF patch of a shallow side contact holds a few stray pixels 30-40 mm from the object (noise
    # past the contact threshold elsewhere on the membrane, runs/bp22): in plain least squares they
    # outweighed the ~700 good points and pulled the first solve away (in 11 of 275 frames until it
    # ran out of evaluations); dropped before it, they have no say: the fit is the good points' fit
    rng = np.random.default_rng(8)
    ang = rng.uniform(-0.12, 0.12, 700)
    good = np.stack([0.04 * np.cos(ang), 0.04 * np.sin(ang), rng.uniform(0.04, 0.06, 700)], 1)
    good += rng.normal(0, 1e-4, good.shape)
    stray = good[:3] + np.array([[0.03, 0.0, 0.0], [0.035, 0.0, 0.0], [0.04, 0.0, 0.0]])
    prior = _pose([0.02, -0.02, 0.03], [0.001, -0.0015, 0.001])
    fitter = ProximityPoseEstimator(CYL)
    alone = fitter.fit(good, prior)
    fit = fitter.fit(np.concatenate([stray, good]), prior)
    assert fit.success and fit.n_outliers == alone.n_outliers + 3 and fit.iterations == alone.iterations
    assert position_error(fit.pose, alone.pose) < 1e-9 and orientation_error(fit.pose, alone.pose) < 1e-12


def test_a_start_several_mm_off_keeps_the_whole_patch():
    # the pre-cut is relative to the median point's distance at the start: a prior 5.7 mm off (e.g. a
    # real fixture placed off its nominal pose) puts good points 1-5.5 mm from the surface there, and
    # none of them may be dropped as stray (an absolute 5 mm cut dropped 125 of 800)
    rng = np.random.default_rng(9)
    ang = rng.uniform(-0.5, 0.5, 800)
    good = np.stack([0.04 * np.cos(ang), 0.04 * np.sin(ang), rng.uniform(0.04, 0.06, 800)], 1)
    good += rng.normal(0, 1e-4, good.shape)
    prior = _pose([0.0, 0.0, 0.0], [0.004, 0.004, 0.0])
    start = np.abs(point_residuals(prior.theta(), good, CYL, with_jacobian=False)[0])
    assert start.max() > 5e-3 and np.median(start) > 3e-3
    fit = ProximityPoseEstimator(CYL).fit(good, prior)
    assert fit.success and fit.n_outliers < 10


@pytest.mark.parametrize("bad", [{"center": [float("nan"), 0.0, 0.05]}, {"axis": [float("inf"), 0.0, 0.0]},
                                 {"axis": [1e-320, 0.0, 0.0]}, {"radius": float("inf")}])
def test_a_cylinder_with_a_non_finite_or_directionless_value_is_refused(bad):
    """Was: json reads NaN and Infinity; such a primitive passed, and the first fit raised scipy's
    ValueError ("Residuals are not finite"), a traceback of `bubble pose`."""
    with pytest.raises(InputError, match="bad cylinder primitive"):
        shape_from_object({"type": "cylinder", "radius": 0.041, "height": 0.095, **bad})


def test_a_mesh_in_other_units_than_metres_is_refused():
    """Was: a mesh in mm asked numpy for a 2.56 PiB grid (MemoryError, exit 1)."""
    mesh = trimesh.creation.box(extents=[70.0, 50.0, 40.0])  # millimetres
    with pytest.raises(InputError, match="object mesh is 70 m across; expected metres"):
        shape_from_object({"type": "mesh"}, mesh.vertices, mesh.faces)


def test_grid_sdf_gradient_matches_finite_differences_off_the_grid_too():
    """Was: off the grid the gradient was the clamping direction alone, the interpolation's slope
    along the axes not clamped dropped (analytic [-1, 0, 0] where finite differences give
    [-1, 0.21, 0]): a wrong Jacobian for points beyond the grid."""
    mesh = trimesh.creation.box(extents=[0.07, 0.05, 0.04])
    mesh.apply_translation([0, 0, 0.02])
    grid = shape_from_object({"type": "mesh"}, mesh.vertices, mesh.faces)
    rng = np.random.default_rng(3)
    points = rng.uniform(-0.15, 0.15, (400, 3)) + [0, 0, 0.02]
    lo, hi = grid.origin, grid.origin + grid.spacing * (np.asarray(grid.values.shape) - 1)
    h = 1e-7
    points = points[~np.all((points > lo - 2 * h) & (points < hi + 2 * h), axis=1)]  # off the grid
    # away from cell faces: the trilinear field's kinks would spoil central differences
    clamped = (points < lo) | (points > hi)
    cell = (np.clip(points, lo, hi) - lo) / grid.spacing
    points = points[np.all(clamped | (np.abs(cell - np.round(cell)) > 1e-3), axis=1)]
    assert len(points) > 50
    _, grad = grid.signed_distance(points)
    numeric = np.stack([(grid.signed_distance(points + h * e)[0] - grid.signed_distance(points - h * e)[0]) / (2 * h)
                        for e in np.eye(3)], axis=1)
    np.testing.assert_allclose(grad, numeric, atol=1e-4)


def test_a_cylinder_in_other_units_than_metres_is_refused():
    """Was: a radius of 1e200 m taken as is (the fits ran, 42 mm off the true pose); a mug in mm failed
    every fit, saying nothing of units."""
    for radius, height, across in ((1e200, 0.095, r"2e\+200"), (41.0, 95.0, "95")):
        with pytest.raises(InputError, match=rf"cylinder primitive is {across} m across; expected metres \(at most 0.5 m\)"):
            shape_from_object({"type": "cylinder", "radius": radius, "height": height})
    assert shape_from_object({"type": "cylinder", "radius": 0.041, "height": 0.095}).radius == 0.041


def test_points_whose_costs_overflow_give_a_failed_fit_without_warnings():
    """Contact points 1e300 m away (a session's absurd intrinsics): was a success with an infinite RMS,
    and scipy's overflow RuntimeWarnings on stderr."""
    import warnings

    points = np.random.default_rng(0).normal(size=(200, 3)) * 1e300
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        fit = ProximityPoseEstimator(CYL).fit(points, Pose(np.array([0.0, 0.0, 0.1]), np.array([1.0, 0.0, 0.0, 0.0])))
    assert not fit.success
