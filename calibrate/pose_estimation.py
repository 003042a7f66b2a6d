"""Proximity pose estimation (the paper's Sec. V): fit a known shape to a tactile point cloud.

The pose ``X`` of the object (geometry ``G``) in the camera frame maps object coordinates to
camera coordinates, ``p_cam = R(q) p_obj + t``. It is parametrized by
``theta = [t (3) m, q (4)]`` with ``q = [w, x, y, z]`` a quaternion, and estimated by nonlinear
least squares (``scipy.optimize.least_squares``, analytic Jacobian) on

    r_i = phi(R(q/|q|)^T (p_i - t))            one residual per contact point p_i (m)
    r_n = w_n (|q|^2 - 1)                      unit-norm residual (fixes the quaternion's scale)
    r_t = w_p (t - t_prior)                    prior on the position (3, m)
    r_q = w_p L (q - q_prior)                  prior on the orientation (4, m)

where ``phi`` is the shape's proximity field (signed distance, negative inside, m). The cost is
the sum of squared signed distances of the points to the surface. The quaternion is normalized
inside the residual and the unit-norm residual removes the remaining scale freedom.

The prior weighs as much as one contact point per coordinate (``w_p = 1``), the orientation
scaled by ``L`` = 0.1 m per unit of quaternion (about 5 cm per radian: the displacement a turn
causes half a mug away from the object's origin). Against 1500 points it moves the pose by
micrometres in the directions the patch constrains well; it holds the directions the patch
barely constrains (a cylinder's position across its axis and the axis direction, seen through
a shallow, 1 cm wide patch) near the prior instead of letting them wander by millimetres with
the depth noise, and it decides the directions the patch leaves free (a cylinder's spin about its
axis and shift along it). See ``docs/pose.md``.

Shapes: ``Cylinder`` (capped, analytic) and ``GridSDF`` (any triangle mesh, a signed-distance
field precomputed on a grid and trilinearly interpolated). ``shape_from_object`` builds one from
the object's description in a session file.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import Protocol

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from collect.errors import InputError

#: Fewest contact points a fit accepts (the pose has 6 degrees of freedom; a handful of points
#: gives a meaningless fit).
MIN_POINTS = 30
#: Largest object a mesh or a cylinder primitive may describe (m, across): the bench's objects
#: (``hw_mocks.objects``, 5 mm to 0.5 m). Beyond, it is in other units, and a mesh's signed-distance
#: grid would not fit in memory.
MAX_MESH_SIZE_M = 0.5
#: Relative tolerances (``xtol``, ``ftol``) of the Levenberg-Marquardt fit. Tighter ones (1e-10)
#: made a quarter to half of the fits of a held-out mug pose run out of evaluations while creeping
#: along the cylinder's symmetric directions (held there only by the then weak prior), skipping those
#: frames; 1e-8 ends them all, still stopping only when a step moves the pose by ~1e-8 (10 nm).
FIT_TOLERANCE = 1e-8
#: Points farther than this (m) beyond the median point's distance from the surface at the fit's
#: starting pose are dropped before the first solve (relative to the median, so that a start several
#: mm off, e.g. a real fixture's placement error, keeps the whole patch). A ToF contact patch holds
#: ~10 stray single pixels away from the contact (depth noise where the IR amplitude is low reaches
#: past the contact threshold); the 2-7 of them 30-40 mm from the object otherwise dominate the
#: least-squares cost, and the solve wandered off and ran out of evaluations on 11 of 275 hold frames
#: of session 22's bench_pose (`runs/bp22`), all on the ToF depth.
GROSS_OUTLIER_M = 5e-3
#: Weight of the prior residual (1: the position error in m weighs like one contact point's signed distance).
#: With the earlier 1e-2 the fit of a held-out mug pose wandered across the cylinder's axis by
#: 1-30 mm from frame to frame of one static hold, on ToF depth as on predicted depth.
PRIOR_WEIGHT = 1.0
#: Metres per unit of quaternion in the orientation prior (about 0.05 m per radian).
PRIOR_ROTATION_SCALE_M = 0.1


class Shape(Protocol):
    """A shape with a proximity field in its own (object) frame.

    ``center`` ``(3,)`` m, object frame: the point whose position ``e_x`` compares (the shape's own
    reference point, not the object's origin on the fixture, which may lie a lever arm away).
    """

    center: tuple[float, float, float]

    def signed_distance(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``points (N,3) m`` in the object frame -> ``(phi (N,) m, grad (N,3))``, negative inside."""


@dataclass(frozen=True)
class Cylinder:
    """Solid capped cylinder: ``radius``, ``height`` m, centred on ``center`` (object frame, m),
    its axis along the unit vector ``axis`` (object frame)."""

    radius: float
    height: float
    center: tuple[float, float, float] = (0.0, 0.0, 0.0)
    axis: tuple[float, float, float] = (0.0, 0.0, 1.0)

    @cached_property
    def basis(self) -> np.ndarray:
        """``(3,3)`` orthonormal columns ``[e1, e2, axis]``: cylinder frame -> object frame."""
        a = np.asarray(self.axis, dtype=np.float64)
        a = a / np.linalg.norm(a)
        helper = np.array([1.0, 0.0, 0.0]) if abs(a[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        e1 = np.cross(helper, a)
        e1 /= np.linalg.norm(e1)
        return np.stack([e1, np.cross(a, e1), a], axis=1)

    def signed_distance(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Exact field of the capped cylinder: ``points (N,3) m`` (object frame) -> ``(phi (N,) m,
        grad (N,3) unit)``, negative inside (``Shape.signed_distance``)."""
        basis = self.basis
        p = (np.asarray(points, dtype=np.float64) - np.asarray(self.center)) @ basis
        r = np.hypot(p[:, 0], p[:, 1])
        d_r = r - self.radius  # distance to the side wall (signed)
        d_z = np.abs(p[:, 2]) - 0.5 * self.height  # distance to the nearer cap plane (signed)
        # Most points of a patch lie beside the side wall, between the cap planes, where the wall
        # is the nearest surface: phi = d_r, gradient radial. The others take the general case.
        beside_wall = (d_z <= np.minimum(d_r, 0.0)) & (r > 1e-12)
        phi = d_r
        grad = p / np.where(beside_wall, r, 1.0)[:, None]
        grad[:, 2] = 0.0
        if not beside_wall.all():
            rest = ~beside_wall
            phi[rest], grad[rest] = self._near_caps(p[rest], r[rest], d_r[rest], d_z[rest])
        return phi, grad @ basis.T

    @staticmethod
    def _near_caps(p: np.ndarray, r: np.ndarray, d_r: np.ndarray, d_z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(phi (M,) m, grad (M,3))`` in the cylinder frame of any points ``p (M,3)`` (radius
        ``r``, side-wall and cap-plane distances ``d_r``, ``d_z``, all ``(M,)`` m): outside
        the rims, beyond the caps, or inside nearer a cap than the wall."""
        safe_r = np.where(r > 1e-12, r, 1.0)
        radial = np.stack([p[:, 0] / safe_r, p[:, 1] / safe_r, np.zeros_like(r)], axis=1)
        radial[r <= 1e-12] = (1.0, 0.0, 0.0)
        sign_z = np.where(p[:, 2] >= 0.0, 1.0, -1.0)
        a = np.maximum(d_r, 0.0)
        b = np.maximum(d_z, 0.0)
        outside_d = np.hypot(a, b)
        outside = outside_d > 0.0
        inside_side = d_r >= d_z  # inside: the nearer surface is the side wall

        phi = np.where(outside, outside_d, np.maximum(d_r, d_z))
        safe_d = np.where(outside, outside_d, 1.0)
        w_r = np.where(outside, a / safe_d, inside_side.astype(np.float64))
        w_z = np.where(outside, b / safe_d, (~inside_side).astype(np.float64))
        grad = radial * w_r[:, None]
        grad[:, 2] += w_z * sign_z
        return phi, grad


@dataclass(frozen=True)
class GridSDF:
    """Signed-distance field of any closed mesh, sampled on a regular grid (object frame).

    ``values (X,Y,Z) float64 m`` at points ``origin + spacing * (i, j, k)``; trilinear
    interpolation inside the grid, points outside are clamped to the grid box and the distance
    to it is added (the field stays continuous and points toward the object).
    """

    values: np.ndarray
    origin: np.ndarray  # (3,) m, the grid's first sample
    spacing: float  # m
    center: tuple[float, float, float]  # m, the centre of the mesh's bounding box

    @classmethod
    def from_mesh(cls, vertices: np.ndarray, faces: np.ndarray, spacing: float = 1.5e-3,
                  margin: float = 0.015, band: float = 6e-3) -> "GridSDF":
        """Precompute from a closed, outward-oriented triangle mesh ``vertices (V,3) m``, ``faces (F,3)``.

        Within ``band`` (m) of the surface: distance to the nearest of dense surface samples,
        signed by the side of that sample's face normal. Farther out: ``band`` plus the grid
        distance to the band, negative in the regions the band encloses.
        """
        import trimesh
        from scipy import ndimage
        from scipy.spatial import cKDTree

        mesh = trimesh.Trimesh(np.asarray(vertices, np.float64), np.asarray(faces, np.int64),
                               process=False)
        if len(mesh.faces) == 0:
            raise InputError("object mesh has no faces; cannot build its signed-distance field")
        size = float(np.max(mesh.extents)) if np.all(np.isfinite(mesh.vertices)) else float("nan")
        if not size <= MAX_MESH_SIZE_M:  # the grid grows as its cube (a mesh in mm asked for 2.56 PiB)
            raise InputError(f"object mesh is {size:.3g} m across; expected metres (at most {MAX_MESH_SIZE_M:g} m)")
        n_samples = int(np.clip(mesh.area / (0.5 * spacing) ** 2, 20_000, 300_000))
        samples, face_idx = trimesh.sample.sample_surface(mesh, n_samples, seed=0)
        normals = mesh.face_normals[face_idx]
        lo = mesh.bounds[0] - margin
        shape = tuple(np.ceil((mesh.bounds[1] + margin - lo) / spacing).astype(int) + 1)
        axes = [lo[k] + spacing * np.arange(shape[k]) for k in range(3)]
        grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
        dist, nearest = cKDTree(samples).query(grid, distance_upper_bound=band, workers=1)
        in_band = np.isfinite(dist)
        values = np.empty(len(grid))
        near = nearest[in_band]
        side = np.einsum("ij,ij->i", grid[in_band] - samples[near], normals[near])
        values[in_band] = np.where(side < 0.0, -dist[in_band], dist[in_band])
        far = (~in_band).reshape(shape)
        labels, _ = ndimage.label(far)
        faces_of_box = [labels[0], labels[-1], labels[:, 0], labels[:, -1], labels[:, :, 0], labels[:, :, -1]]
        outside_labels = np.unique(np.concatenate([f.ravel() for f in faces_of_box]))
        far_dist = band + ndimage.distance_transform_edt(far) * spacing
        far_sign = np.where(np.isin(labels, outside_labels[outside_labels > 0]), 1.0, -1.0)
        values[~in_band] = (far_sign * far_dist)[far]
        return cls(values=values.reshape(shape), origin=lo, spacing=float(spacing),
                   center=tuple(float(c) for c in mesh.bounds.mean(axis=0)))

    def signed_distance(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Trilinear interpolation of the grid: ``points (N,3) m`` (object frame) -> ``(phi (N,) m,
        grad (N,3))``, negative inside (``Shape.signed_distance``); a point off the grid takes the
        value at the nearest grid point plus its distance to the grid box."""
        p = np.asarray(points, dtype=np.float64)
        hi_idx = np.asarray(self.values.shape) - 1
        g = (p - self.origin) / self.spacing
        g_in = np.clip(g, 0.0, hi_idx)
        i0 = np.minimum(np.floor(g_in).astype(np.int64), hi_idx - 1)
        f = g_in - i0
        v = self.values
        corner = {}
        for dx in (0, 1):
            for dy in (0, 1):
                for dz in (0, 1):
                    corner[dx, dy, dz] = v[i0[:, 0] + dx, i0[:, 1] + dy, i0[:, 2] + dz]
        fx, fy, fz = f[:, 0], f[:, 1], f[:, 2]
        c00 = corner[0, 0, 0] * (1 - fx) + corner[1, 0, 0] * fx
        c01 = corner[0, 0, 1] * (1 - fx) + corner[1, 0, 1] * fx
        c10 = corner[0, 1, 0] * (1 - fx) + corner[1, 1, 0] * fx
        c11 = corner[0, 1, 1] * (1 - fx) + corner[1, 1, 1] * fx
        c0 = c00 * (1 - fy) + c10 * fy
        c1 = c01 * (1 - fy) + c11 * fy
        phi = c0 * (1 - fz) + c1 * fz
        d_x = ((corner[1, 0, 0] - corner[0, 0, 0]) * (1 - fy) * (1 - fz)
               + (corner[1, 1, 0] - corner[0, 1, 0]) * fy * (1 - fz)
               + (corner[1, 0, 1] - corner[0, 0, 1]) * (1 - fy) * fz
               + (corner[1, 1, 1] - corner[0, 1, 1]) * fy * fz)
        d_y = (c10 - c00) * (1 - fz) + (c11 - c01) * fz
        d_z = c1 - c0
        grad = np.stack([d_x, d_y, d_z], axis=1) / self.spacing
        # Outside the grid box: add the distance to the box, along the clamping direction; the
        # gradient keeps the interpolation's along the axes not clamped (was: dropped there)
        out = (g - g_in) * self.spacing
        out_norm = np.linalg.norm(out, axis=1)
        outside = out_norm > 0.0
        if np.any(outside):
            phi = phi + out_norm
            grad[outside] = grad[outside] * (out[outside] == 0.0) + out[outside] / out_norm[outside, None]
        return phi, grad


def shape_from_object(primitive: dict | None, vertices: np.ndarray | None = None,
                      faces: np.ndarray | None = None) -> Shape:
    """The shape to fit for an object described in a session file.

    ``primitive`` ``{"type": "cylinder", "radius": m, "height": m, "center": [x,y,z] m,
    "axis": [ax,ay,az]}`` (``center`` defaults to ``[0, 0, height/2]``, ``axis`` to ``[0, 0, 1]``:
    upright, base at the origin) gives a ``Cylinder``; any other type with a mesh (``vertices (V,3)
    float m`` and ``faces (F,3) int``, object frame) gives a ``GridSDF`` of the mesh.
    """
    kind = (primitive or {}).get("type")
    if kind == "cylinder":
        try:
            radius = float(primitive["radius"])
            height = float(primitive["height"])
            center = tuple(float(c) for c in primitive.get("center", (0.0, 0.0, 0.5 * height)))
            axis = tuple(float(c) for c in primitive.get("axis", (0.0, 0.0, 1.0)))
        except (KeyError, TypeError, ValueError) as err:
            raise InputError(f"cylinder primitive needs numeric radius, height, center, axis: {primitive}") from err
        numbers = np.array([radius, height, *center, *axis]) if len(center) == len(axis) == 3 else None
        if (numbers is None or not np.all(np.isfinite(numbers)) or not (radius > 0.0 and height > 0.0)
                or np.linalg.norm(axis) < 1e-9):  # json reads NaN and Infinity; an axis of 1e-320 has no direction
            raise InputError(f"bad cylinder primitive: {primitive}")
        size = max(2.0 * radius, height)
        if size > MAX_MESH_SIZE_M:  # was: taken as is, and a radius of 1e200 m "fitted" 42 mm off the true pose
            raise InputError(f"cylinder primitive is {size:.3g} m across; expected metres (at most {MAX_MESH_SIZE_M:g} m)")
        return Cylinder(radius=radius, height=height, center=center, axis=axis)
    if vertices is not None and faces is not None and len(faces):
        return GridSDF.from_mesh(vertices, faces)
    raise InputError(f"object shape {kind!r} has no signed-distance model and no mesh")


# ----------------------------------------------------------------------------------------------
# Quaternion algebra, q = [w, x, y, z].


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """Unit quaternion ``(4,) [w,x,y,z]`` -> rotation matrix ``(3,3)``."""
    w, x, y, z = q
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def matrix_to_quat(rot: np.ndarray) -> np.ndarray:
    """Rotation matrix ``(3,3)`` -> unit quaternion ``(4,) [w,x,y,z]`` with ``w >= 0``."""
    x, y, z, w = Rotation.from_matrix(rot).as_quat()
    q = np.array([w, x, y, z])
    return q if w >= 0 else -q


@dataclass(frozen=True)
class Pose:
    """Object pose in the camera frame: ``p_cam = R(quaternion) p_obj + position``."""

    position: np.ndarray  # (3,) m
    quaternion: np.ndarray  # (4,) [w,x,y,z], unit norm

    @classmethod
    def from_matrix(cls, transform: np.ndarray) -> "Pose":
        """From a homogeneous transform ``(4,4)`` (object -> camera, m)."""
        return cls(np.asarray(transform[:3, 3], np.float64).copy(), matrix_to_quat(transform[:3, :3]))

    def matrix(self) -> np.ndarray:
        """Homogeneous transform ``(4,4)``, object -> camera."""
        out = np.eye(4)
        out[:3, :3] = quat_to_matrix(self.quaternion)
        out[:3, 3] = self.position
        return out

    def theta(self) -> np.ndarray:
        """Parameter vector ``(7,) [t (m), q]``."""
        return np.concatenate([self.position, self.quaternion])


def position_error(a: Pose, b: Pose, point=(0.0, 0.0, 0.0)) -> float:
    """``e_x = ||p1 - p2||`` (m): the distance between where the two poses put ``point`` ``(3,)``
    (object frame, m; the object's origin by default, a shape's ``center`` in the pose check)."""
    point = np.asarray(point, dtype=np.float64)
    p1 = quat_to_matrix(a.quaternion) @ point + a.position
    p2 = quat_to_matrix(b.quaternion) @ point + b.position
    return float(np.linalg.norm(p1 - p2))


def orientation_error(a: Pose, b: Pose) -> float:
    """``e_theta = 1 - |q1 . q2|`` (Huynh 2009, metric 3; 0 = same orientation, at most 1)."""
    return float(1.0 - min(1.0, abs(float(np.dot(a.quaternion, b.quaternion)))))


def align_symmetry(shape: Shape, pose: Pose, reference: Pose) -> Pose:
    """The pose equivalent to ``pose`` under the shape's symmetry that is closest to ``reference``.

    A cylinder looks the same after a spin about its axis and a shift along it, so no point cloud
    can tell those apart; comparing with a true pose is only meaningful modulo them. For a
    ``Cylinder`` this returns ``pose`` spun about and slid along its axis to best match
    ``reference``; other shapes are returned unchanged.
    """
    if not isinstance(shape, Cylinder):
        return pose
    basis = shape.basis
    axis = basis[:, 2]
    center = np.asarray(shape.center, dtype=np.float64)
    rot = quat_to_matrix(pose.quaternion)
    # spin: twist of the relative rotation about the axis (swing-twist decomposition)
    q_rel = matrix_to_quat(rot.T @ quat_to_matrix(reference.quaternion))
    spin = 2.0 * np.arctan2(q_rel[1:] @ axis, q_rel[0])
    spin_rot = Rotation.from_rotvec(spin * axis).as_matrix()
    sym = np.eye(4)  # spin about the axis through the centre, in the object frame
    sym[:3, :3] = spin_rot
    sym[:3, 3] = center - spin_rot @ center
    moved = pose.matrix() @ sym
    # slide: move the centre along the (camera-frame) axis toward the reference's centre
    axis_cam = moved[:3, :3] @ axis
    center_ref = quat_to_matrix(reference.quaternion) @ center + reference.position
    center_cam = moved[:3, :3] @ center + moved[:3, 3]
    moved[:3, 3] += axis_cam * (axis_cam @ (center_ref - center_cam))
    return Pose.from_matrix(moved)


# ----------------------------------------------------------------------------------------------
# Residuals and their analytic Jacobian.


#: Column indices that lay out the outer products ``v_i g_j`` of two ``(N,3)`` arrays as ``(N,9)``.
_OUTER_I = np.repeat(np.arange(3), 3)
_OUTER_J = np.tile(np.arange(3), 3)


def _rotation_derivatives(u: np.ndarray) -> np.ndarray:
    """``(4,3,3)`` derivatives of the rotation matrix ``R(q)`` (homogeneous quadratic form, equal to
    ``quat_to_matrix`` on unit quaternions) with respect to ``w, x, y, z``, at ``u`` ``(4,)``."""
    w, x, y, z = u
    return 2.0 * np.array([
        [[w, -z, y], [z, w, -x], [-y, x, w]],
        [[x, y, z], [y, -x, -w], [z, w, -x]],
        [[-y, x, w], [x, y, z], [-w, z, -y]],
        [[-z, -w, x], [w, -z, y], [x, y, z]],
    ])


def point_residuals(theta: np.ndarray, points: np.ndarray, shape: Shape,
                    with_jacobian: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
    """Signed distances of the camera-frame ``points (N,3) m`` to the shape posed by ``theta (7,)``.

    Returns ``r (N,) m`` and, if asked, ``J (N,7) = dr/dtheta`` (analytic, through the
    normalization of the quaternion).
    """
    t = theta[:3]
    q = theta[3:]
    q_norm = float(np.linalg.norm(q))
    u = q / q_norm
    rot = quat_to_matrix(u)
    v = points - t
    p_obj = v @ rot  # rows R^T v: camera -> object frame
    phi, g = shape.signed_distance(p_obj)
    if not with_jacobian:
        return phi, None

    jac = np.empty((len(points), 7))
    jac[:, :3] = -(g @ rot.T)  # dr/dt = -(R g)^T
    # dr/du_k = g . (dR_k^T v) = sum_ij v_i (dR_k)_ij g_j; then u = q/|q|: du/dq = (I - u u^T)/|q|
    to_q = _rotation_derivatives(u).reshape(4, 9).T @ (np.eye(4) - np.outer(u, u)) / q_norm
    jac[:, 3:] = (v[:, _OUTER_I] * g[:, _OUTER_J]) @ to_q
    return phi, jac


@dataclass(frozen=True)
class FitResult:
    """One pose fit: the pose found and how well the contact points sit on the surface there."""

    pose: Pose
    rms_m: float  # root mean square signed distance of the points kept, at the solution
    n_points: int  # points kept
    n_outliers: int  # points dropped as outliers
    iterations: int  # Jacobian evaluations
    success: bool


class ProximityPoseEstimator:
    """Fits a shape's pose to contact points; one instance per shape, reused across frames.

    Before the first fit, points farther from the surface at the starting pose than the median
    point plus ``GROSS_OUTLIER_M`` are dropped (stray ToF pixels away from the contact). After it,
    points farther from the surface than ``outlier_k`` robust standard deviations of the residuals
    (and than ``outlier_floor_m``) are dropped - ToF flying pixels, membrane that bends in near the
    object without touching it - and the fit is refined from there (``outlier_k = 0`` turns both
    off).
    """

    def __init__(self, shape: Shape, prior_weight: float = PRIOR_WEIGHT,
                 prior_rotation_scale_m: float = PRIOR_ROTATION_SCALE_M, norm_weight: float = 1.0,
                 max_evaluations: int = 100, outlier_k: float = 3.0, outlier_floor_m: float = 3e-4):
        self.shape = shape
        self.outlier_k = float(outlier_k)
        self.outlier_floor_m = float(outlier_floor_m)
        self.prior_weight = float(prior_weight)
        self.prior_rotation_scale_m = float(prior_rotation_scale_m)
        #: ``(7,)`` weights of the prior residual: ``w_p`` on the position, ``w_p L`` on the quaternion.
        self._prior_weights = self.prior_weight * np.array([1.0] * 3 + [self.prior_rotation_scale_m] * 4)
        self.norm_weight = float(norm_weight)
        self.max_evaluations = int(max_evaluations)
        self._cache: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None

    def _evaluate(self, theta, points, theta_prior):
        """Residuals ``(N+8,)`` and Jacobian ``(N+8,7)`` at ``theta``; the last pair is cached
        (the solver asks for the Jacobian at the point it just evaluated)."""
        if self._cache is not None and np.array_equal(self._cache[0], theta):
            return self._cache[1], self._cache[2]
        n = len(points)
        phi, jac_points = point_residuals(theta, points, self.shape, with_jacobian=True)
        q = theta[3:]
        res = np.empty(n + 8)
        res[:n] = phi
        res[n] = self.norm_weight * (q @ q - 1.0)
        res[n + 1:] = self._prior_weights * (theta - theta_prior)
        jac = np.zeros((n + 8, 7))
        jac[:n] = jac_points
        jac[n, 3:] = 2.0 * self.norm_weight * q
        jac[n + 1:, :] = np.diag(self._prior_weights)
        self._cache = (theta.copy(), res, jac)
        return res, jac

    def _residuals(self, theta, points, theta_prior):
        return self._evaluate(theta, points, theta_prior)[0]

    def _jacobian(self, theta, points, theta_prior):
        return self._evaluate(theta, points, theta_prior)[1]

    def fit(self, points: np.ndarray, prior: Pose, start: Pose | None = None) -> FitResult:
        """Pose of the shape best explaining ``points (N,3) m`` (camera frame).

        ``prior``: pose near the true one (the prior term pulls toward it);
        ``start``: initial guess (default the prior; pass the previous frame's result to warm start).
        Raises ``InputError`` for too few or non-finite points.
        """
        points = np.ascontiguousarray(points, dtype=np.float64)
        if points.ndim != 2 or points.shape[1] != 3:
            raise InputError(f"contact points must be (N,3), got {points.shape}")
        if len(points) < MIN_POINTS:
            raise InputError(f"too few contact points for a pose fit: {len(points)} < {MIN_POINTS}")
        if not np.all(np.isfinite(points)):
            raise InputError("contact points contain NaN or infinite values")
        theta_prior = prior.theta()
        x0 = (start or prior).theta()
        if x0[3:] @ theta_prior[3:] < 0:  # same hemisphere as the prior
            x0 = np.concatenate([x0[:3], -x0[3:]])
        n_outliers = 0
        if self.outlier_k > 0:
            distance = np.abs(point_residuals(x0, points, self.shape, with_jacobian=False)[0])
            near = distance <= float(np.median(distance)) + GROSS_OUTLIER_M  # a start off by more widens it
            n_near = int(near.sum())
            if MIN_POINTS <= n_near < len(points):
                n_outliers = len(points) - n_near
                points = points[near]
        sol = self._solve(x0, points, theta_prior)
        evaluations = int(sol.njev or sol.nfev)
        if self.outlier_k > 0 and sol.status > 0:
            r = sol.fun[: len(points)]
            spread = 1.4826 * float(np.median(np.abs(r - np.median(r))))
            keep = np.abs(r) <= max(self.outlier_k * spread, self.outlier_floor_m)
            if not keep.all() and keep.sum() >= MIN_POINTS:
                n_outliers += int(len(points) - keep.sum())
                points = points[keep]
                sol = self._solve(sol.x, points, theta_prior)
                evaluations += int(sol.njev or sol.nfev)
        q = sol.x[3:] / np.linalg.norm(sol.x[3:])
        if q[0] < 0:
            q = -q
        with np.errstate(over="ignore", invalid="ignore"):
            rms = float(np.sqrt(np.mean(sol.fun[: len(points)] ** 2)))
        # converged to numbers that overflow (points from absurd intrinsics) is no fit (was: success, inf errors)
        success = sol.status > 0 and bool(np.all(np.isfinite(sol.x))) and np.isfinite(rms)
        return FitResult(pose=Pose(sol.x[:3].copy(), q), rms_m=rms, n_points=len(points),
                         n_outliers=n_outliers, iterations=evaluations, success=bool(success))

    def _solve(self, x0: np.ndarray, points: np.ndarray, theta_prior: np.ndarray):
        self._cache = None
        try:  # points so far off that the costs overflow end as a failed fit (``fit``), not as warnings on stderr
            with np.errstate(over="ignore", invalid="ignore"):
                return least_squares(self._residuals, x0, jac=self._jacobian, method="lm",
                                     args=(points, theta_prior), xtol=FIT_TOLERANCE, ftol=FIT_TOLERANCE,
                                     max_nfev=self.max_evaluations)
        finally:
            self._cache = None
