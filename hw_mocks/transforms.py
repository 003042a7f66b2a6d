"""Rigid transforms between UR-style poses and 4x4 matrices.

A pose is ``(6,) [x, y, z, rx, ry, rz]``: metres + rotation vector (rad), the parent frame's
coordinates of the child frame's origin and orientation. A matrix ``T_parent_child (4,4)`` maps
child coordinates to parent coordinates.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation


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
