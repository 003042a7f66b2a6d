"""UR-style poses: rigid transforms to and from 4x4 matrices, and the path length of a linear move.

A pose is ``(6,) [x, y, z, rx, ry, rz]``: metres + rotation vector (rad), the parent frame's
coordinates of the child frame's origin and orientation. A matrix ``T_parent_child (4,4)`` maps
child coordinates to parent coordinates.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

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
