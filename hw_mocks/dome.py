"""Rest geometry of the bubble seen by its camera: pixel rays, the inflated dome, the rim.

The rest membrane is the elliptic paraboloid of ``hw_mocks.sensor_spec`` in the TCP frame
(apex at the origin, rim at ``z = -dome_height_m``); the camera sits at ``spec.camera_in_tcp``.
A ``RayGrid`` is a regular grid of pixel centres (full image, or a coarser physics grid that
covers the whole rim) with its camera-frame rays ``(x/z, y/z, 1)``, so ``depth * ray`` is the
3-D point of a pixel at z-depth ``depth``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hw_mocks.sensor_spec import SensorSpec
from collect.transforms import invert, pose_to_matrix


@dataclass(frozen=True)
class RayGrid:
    """Pixel centres ``u = u0 + step*j``, ``v = v0 + step*i`` (full-image pixel units) of a
    ``shape = (rows, cols)`` grid, and their rays ``(rows, cols, 3) float64`` (camera frame, z = 1)."""

    u0: float
    v0: float
    step: int
    shape: tuple[int, int]
    rays: np.ndarray

    @classmethod
    def build(cls, spec: SensorSpec, u0: float, v0: float, step: int, shape: tuple[int, int]) -> "RayGrid":
        """The grid of ``shape = (rows, cols)`` pixels starting at pixel ``(u0, v0)`` (px) every ``step`` px,
        with its rays through ``spec``'s pinhole intrinsics."""
        rows, cols = shape
        u = u0 + step * np.arange(cols, dtype=np.float64)
        v = v0 + step * np.arange(rows, dtype=np.float64)
        uu, vv = np.meshgrid(u, v)
        rays = np.stack([(uu - spec.cx) / spec.fx, (vv - spec.cy) / spec.fy, np.ones_like(uu)], axis=-1)
        return cls(float(u0), float(v0), int(step), (int(rows), int(cols)), rays)

    def coords_of(self, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Grid coordinates (float32, for ``cv2.remap``) of full-image pixel coordinates ``u, v`` (any
        shape; the results have it too)."""
        return ((u - self.u0) / self.step).astype(np.float32), ((v - self.v0) / self.step).astype(np.float32)


class Dome:
    """The inflated membrane at rest, for one sensor spec."""

    def __init__(self, spec: SensorSpec):
        self.spec = spec
        self.a = spec.dome_semi_x_m
        self.b = spec.dome_semi_y_m
        self.h = spec.dome_height_m
        #: ``(4,4)`` camera frame -> TCP frame.
        self.tcp_from_cam = pose_to_matrix(spec.camera_in_tcp)
        self.cam_from_tcp = invert(self.tcp_from_cam)

    def rest_depth(self, grid: RayGrid) -> tuple[np.ndarray, np.ndarray]:
        """Z-depth of the rest membrane along each ray: ``(depth (rows,cols) float64 m, mask bool)``;
        depth is 0 where the ray misses the membrane (it sees the housing beyond the rim)."""
        r = self.tcp_from_cam[:3, :3]
        c = self.tcp_from_cam[:3, 3]
        v = grid.rays @ r.T  # ray directions in the TCP frame, per unit z-depth
        ia, ib = 1.0 / self.a**2, 1.0 / self.b**2
        # z + h*(x^2/a^2 + y^2/b^2) = 0 along c + t*v.
        qa = self.h * (v[..., 0] ** 2 * ia + v[..., 1] ** 2 * ib)
        qb = 2 * self.h * (c[0] * v[..., 0] * ia + c[1] * v[..., 1] * ib) + v[..., 2]
        qc = self.h * (c[0] ** 2 * ia + c[1] ** 2 * ib) + c[2]
        disc = qb**2 - 4 * qa * qc
        ok = disc >= 0
        sq = np.sqrt(np.where(ok, disc, 0.0))
        # The camera is inside the dome (qc < 0): exactly one positive root.
        with np.errstate(divide="ignore", invalid="ignore"):
            t = np.where(qa > 1e-12, (-qb + sq) / (2 * qa), -qc / qb)
        z_hit = c[2] + t * v[..., 2]
        mask = ok & (t > 0) & (z_hit >= -self.h)
        return np.where(mask, t, 0.0), mask

    def rim_plane_depth(self, grid: RayGrid) -> np.ndarray:
        """Z-depth (m) at which each ray crosses the rim plane (where it sees the housing)."""
        r = self.tcp_from_cam[:3, :3]
        c = self.tcp_from_cam[:3, 3]
        vz = (grid.rays @ r.T)[..., 2]
        return np.where(vz > 1e-6, (-self.h - c[2]) / np.maximum(vz, 1e-6), 0.0)

    def rest_normals(self, grid: RayGrid, depth: np.ndarray) -> np.ndarray:
        """Outward unit normals of the rest dome at the rest points, camera frame ``(rows,cols,3)``."""
        p_cam = grid.rays * depth[..., None]
        p = p_cam @ self.tcp_from_cam[:3, :3].T + self.tcp_from_cam[:3, 3]
        n = np.stack([2 * self.h * p[..., 0] / self.a**2, 2 * self.h * p[..., 1] / self.b**2, np.ones(depth.shape)], axis=-1)
        n /= np.linalg.norm(n, axis=-1, keepdims=True)
        return n @ self.tcp_from_cam[:3, :3]  # rotate TCP -> camera (R^T n, as row vectors)

    def to_tcp(self, points_cam: np.ndarray) -> np.ndarray:
        """Camera-frame points ``(...,3)`` -> TCP frame."""
        return points_cam @ self.tcp_from_cam[:3, :3].T + self.tcp_from_cam[:3, 3]

    def rim_pixel_bounds(self, n: int = 720) -> tuple[float, float, float, float]:
        """``(u_min, u_max, v_min, v_max)`` of the rim ellipse projected into the image (pixels)."""
        th = np.linspace(0, 2 * np.pi, n, endpoint=False)
        rim = np.stack([self.a * np.cos(th), self.b * np.sin(th), np.full_like(th, -self.h)], axis=1)
        pc = rim @ self.cam_from_tcp[:3, :3].T + self.cam_from_tcp[:3, 3]
        u = self.spec.fx * pc[:, 0] / pc[:, 2] + self.spec.cx
        v = self.spec.fy * pc[:, 1] / pc[:, 2] + self.spec.cy
        return float(u.min()), float(u.max()), float(v.min()), float(v.max())
