"""Contact patch from tactile depth: where the membrane is pushed in, lifted to a point cloud.

The first stage of the paper's pose pipeline (Sec. V): compare a depth map with the
no-contact reference of the same sensor, keep the pixels pushed toward the camera by more than
a threshold (the contact patch, ``trainer.contact``), lift them to 3-D with the pinhole intrinsics
and downsample the cloud to a fixed number of points (1500 in the paper), deterministically.

Depth maps are ``(H,W) float32 m`` camera z-depth, 0 (or non-finite) = invalid.
"""

from __future__ import annotations

import numpy as np

from trainer.contact import CONTACT_THRESHOLD_M, contact_mask

#: Points kept per cloud (the paper's 1500).
N_POINTS = 1500


def lift(depth: np.ndarray, mask: np.ndarray, intrinsics: dict) -> np.ndarray:
    """Pixels of ``mask`` lifted to camera-frame points ``(N,3) float64 m``, in raster order.

    ``intrinsics``: ``fx, fy, cx, cy`` (pixels); ``x = (u - cx) z / fx``, ``y = (v - cy) z / fy``.
    """
    rows, cols = np.nonzero(mask)
    z = depth[rows, cols].astype(np.float64)
    x = (cols - float(intrinsics["cx"])) * z / float(intrinsics["fx"])
    y = (rows - float(intrinsics["cy"])) * z / float(intrinsics["fy"])
    return np.stack([x, y, z], axis=1)


def downsample(points: np.ndarray, n_points: int = N_POINTS) -> np.ndarray:
    """At most ``n_points`` of ``points (N,3)``, evenly strided over their order (deterministic)."""
    if len(points) <= n_points:
        return points
    idx = np.round(np.linspace(0, len(points) - 1, n_points)).astype(np.int64)
    return points[idx]


def contact_points(depth: np.ndarray, reference: np.ndarray, intrinsics: dict,
                   threshold_m: float = CONTACT_THRESHOLD_M,
                   n_points: int = N_POINTS) -> np.ndarray:
    """Contact patch of ``depth (H,W) m`` against ``reference (H,W) m`` as ``(<=n_points,3) m``."""
    mask = contact_mask(depth, reference, threshold_m)
    return downsample(lift(depth, mask, intrinsics), n_points)
