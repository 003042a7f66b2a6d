"""UR-style poses: rigid transforms to and from 4x4 matrices, the path length of a linear move, and
poses interpolated between samples.

A pose is ``(6,) [x, y, z, rx, ry, rz]``: metres + rotation vector (rad), the parent frame's
coordinates of the child frame's origin and orientation. A matrix ``T_parent_child (4,4)`` maps
child coordinates to parent coordinates.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

#: Path length (m) that one radian of pure tool reorientation counts as in a linear move (the UR
#: controller scales rotation into the tool speed; the planner's time estimate and the arm's twin
#: both use it).
ROTATION_M_PER_RAD = 0.1


def pose_to_matrix(pose) -> np.ndarray:
    """``(6,) [m, rotvec]`` -> ``(4,4) float64`` homogeneous transform."""
    p = np.asarray(pose, dtype=np.float64).reshape(6)
    out = np.eye(4)
    out[:3, :3] = Rotation.from_rotvec(p[3:6]).as_matrix()
    out[:3, 3] = p[:3]
    return out


def matrix_to_pose(matrix) -> np.ndarray:
    """``(4,4)`` homogeneous transform -> ``(6,) [m, rotvec]``."""
    m = np.asarray(matrix, dtype=np.float64)
    return np.concatenate([m[:3, 3], Rotation.from_matrix(m[:3, :3]).as_rotvec()])


def invert(matrix) -> np.ndarray:
    """Inverse of a rigid ``(4,4)`` transform."""
    m = np.asarray(matrix, dtype=np.float64)
    out = np.eye(4)
    out[:3, :3] = m[:3, :3].T
    out[:3, 3] = -m[:3, :3].T @ m[:3, 3]
    return out


def rotation_between_rad(a, b) -> float:
    """Angle (rad) of the rotation from the orientation of pose ``a`` (6,) to that of ``b`` (6,)."""
    ra = Rotation.from_rotvec(np.asarray(a, dtype=np.float64)[3:6])
    rb = Rotation.from_rotvec(np.asarray(b, dtype=np.float64)[3:6])
    return float((ra.inv() * rb).magnitude())


def linear_path_m(a, b) -> float:
    """Path length (m) of a linear move from pose ``a`` (6,) to ``b`` (6,): the translation, or the
    reorientation at ``ROTATION_M_PER_RAD`` where that is longer."""
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    return max(float(np.linalg.norm(b[:3] - a[:3])), rotation_between_rad(a, b) * ROTATION_M_PER_RAD)


def interpolate_poses(t, sample_t, poses) -> np.ndarray:
    """Poses ``(n,6) [m, rotvec]`` at times ``t (n,)`` s from ``poses (M,6)`` sampled at non-decreasing
    ``sample_t (M,)`` s: positions linearly, orientations along the shortest turn between samples
    (spherical), held at the first and last sample outside them. Was: each rotation-vector component
    interpolated alone, and with the tool pointing down, a half turn where a UR reports the vector
    with either sign, two samples 0.2 deg apart gave no turn at all halfway between them."""
    sample_t = np.asarray(sample_t, dtype=np.float64)
    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 6)
    t = np.clip(np.atleast_1d(np.asarray(t, dtype=np.float64)), sample_t[0], sample_t[-1])
    first = np.r_[True, np.diff(sample_t) > 0]  # a repeated time keeps its first sample (Slerp's times increase)
    sample_t, poses = sample_t[first], poses[first]
    out = np.empty((len(t), 6))
    for k in range(3):
        out[:, k] = np.interp(t, sample_t, poses[:, k])
    turns = Rotation.from_rotvec(poses[:, 3:])
    out[:, 3:] = turns[0].as_rotvec() if len(sample_t) == 1 else Slerp(sample_t, turns)(t).as_rotvec()
    return out
