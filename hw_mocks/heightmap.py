"""Top-down height field of a mesh: the upper envelope the bubble can press on from above.

``Heightmap.from_mesh(vertices, faces)`` rasterizes the upward-facing triangles onto a regular
x/y grid (vectorized z-buffer, max over triangles). Cells with no surface hold ``floor``
(``FLOOR_DEPTH`` below the mesh's lowest point, so below the fixture plate it rests on), so bilinear
look-ups at silhouettes give steep walls, not holes.
Look-ups take object-frame x/y in metres and return z in metres.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import cv2
import numpy as np

#: How far below the mesh's lowest point (m) the cells with no surface above them lie: well below
#: the fixture plate (was: at z = -0.05 m of the object frame, above the plate under a part whose
#: origin is at its centre).
FLOOR_DEPTH = 0.05


@dataclass(frozen=True)
class Heightmap:
    """``heights (Ny,Nx) float32 m`` over cell centres ``x0 + i*res, y0 + j*res`` (object frame);
    ``floor`` (m): the height of the cells with no surface."""

    heights: np.ndarray
    x0: float
    y0: float
    res: float
    floor: float

    @classmethod
    def from_mesh(cls, vertices: np.ndarray, faces: np.ndarray, res: float = 5e-4) -> "Heightmap":
        """Rasterize the upper envelope of a triangle mesh ``vertices (V,3) m``, ``faces (F,3)``."""
        tri = np.asarray(vertices, dtype=np.float64)[np.asarray(faces)]  # (F,3,3)
        lo = tri[:, :, :2].reshape(-1, 2).min(axis=0) - 3 * res
        hi = tri[:, :, :2].reshape(-1, 2).max(axis=0) + 3 * res
        nx, ny = (np.ceil((hi - lo) / res).astype(int) + 1).tolist()
        floor = float(tri[:, :, 2].min()) - FLOOR_DEPTH
        heights = np.full(ny * nx, floor, dtype=np.float64)

        e1 = tri[:, 1, :2] - tri[:, 0, :2]
        e2 = tri[:, 2, :2] - tri[:, 0, :2]
        det = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
        keep = np.abs(det) > 1e-14  # skip triangles seen edge-on from above (vertical walls)
        tri, e1, e2, det = tri[keep], e1[keep], e2[keep], det[keep]
        # Cell index bounding box of every triangle.
        i_lo = np.ceil((tri[:, :, 0].min(axis=1) - lo[0]) / res).astype(np.int64)
        i_hi = np.floor((tri[:, :, 0].max(axis=1) - lo[0]) / res).astype(np.int64)
        j_lo = np.ceil((tri[:, :, 1].min(axis=1) - lo[1]) / res).astype(np.int64)
        j_hi = np.floor((tri[:, :, 1].max(axis=1) - lo[1]) / res).astype(np.int64)
        ni = np.maximum(i_hi - i_lo + 1, 0)
        nj = np.maximum(j_hi - j_lo + 1, 0)
        counts = ni * nj
        # Process in chunks to bound memory; one candidate cell per (triangle, cell) pair.
        order = np.arange(len(tri))
        chunk_starts = np.searchsorted(np.cumsum(counts), np.arange(0, counts.sum(), 2_000_000))
        bounds = list(chunk_starts) + [len(tri)]
        for a, b in zip(bounds[:-1], bounds[1:]):
            idx = order[a:b]
            if len(idx) == 0 or counts[idx].sum() == 0:
                continue
            owner = np.repeat(idx, counts[idx])
            start = np.repeat(np.cumsum(counts[idx]) - counts[idx], counts[idx])
            local = np.arange(len(owner)) - start
            ci = i_lo[owner] + local % ni[owner]
            cj = j_lo[owner] + local // ni[owner]
            px = lo[0] + ci * res - tri[owner, 0, 0]
            py = lo[1] + cj * res - tri[owner, 0, 1]
            u = (px * e2[owner, 1] - py * e2[owner, 0]) / det[owner]
            v = (e1[owner, 0] * py - e1[owner, 1] * px) / det[owner]
            inside = (u >= -1e-9) & (v >= -1e-9) & (u + v <= 1 + 1e-9)
            o = owner[inside]
            z = tri[o, 0, 2] + u[inside] * (tri[o, 1, 2] - tri[o, 0, 2]) + v[inside] * (tri[o, 2, 2] - tri[o, 0, 2])
            np.maximum.at(heights, cj[inside] * nx + ci[inside], z)
        return cls(heights.reshape(ny, nx).astype(np.float32), float(lo[0]), float(lo[1]), float(res), floor)

    @functools.cached_property
    def top(self) -> float:
        """Highest point (m)."""
        return float(self.heights.max())

    @functools.cached_property
    def covered_bounds(self) -> tuple[float, float, float, float]:
        """``(x_min, x_max, y_min, y_max)`` m of the cells with surface."""
        rows, cols = np.nonzero(self.covered)
        return (
            self.x0 + (cols.min() - 1) * self.res,
            self.x0 + (cols.max() + 1) * self.res,
            self.y0 + (rows.min() - 1) * self.res,
            self.y0 + (rows.max() + 1) * self.res,
        )

    @property
    def covered(self) -> np.ndarray:
        """``(Ny,Nx) bool``: cells with surface above them."""
        return self.heights > self.floor + 1e-6

    def sample(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Bilinear height (m) at object-frame ``x, y`` (same shape, float32);
        ``floor`` off the grid."""
        mx = ((np.asarray(x, dtype=np.float32) - self.x0) / self.res).astype(np.float32, copy=False)
        my = ((np.asarray(y, dtype=np.float32) - self.y0) / self.res).astype(np.float32, copy=False)
        shape, n = mx.shape, mx.size
        if n <= 32767 and mx.ndim != 2:
            mx, my = mx.reshape(1, n), my.reshape(1, n)
        elif mx.ndim != 2 or mx.shape[1] > 32767:  # cv2.remap maps must be 2-D and < 32768 wide
            rows = -(-n // 1024)
            mx = np.pad(mx.ravel(), (0, rows * 1024 - n)).reshape(rows, 1024)
            my = np.pad(my.ravel(), (0, rows * 1024 - n)).reshape(rows, 1024)
        out = cv2.remap(self.heights, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=self.floor)
        return out.ravel()[:n].reshape(shape)

    def normals(self) -> np.ndarray:
        """``(Ny,Nx,3) float32`` unit upward surface normals (object frame) from the height gradient."""
        gy, gx = np.gradient(self.heights.astype(np.float64), self.res)
        n = np.stack([-gx, -gy, np.ones_like(gx)], axis=-1)
        return (n / np.linalg.norm(n, axis=-1, keepdims=True)).astype(np.float32)

    def cell_centres(self) -> tuple[np.ndarray, np.ndarray]:
        """``(xs (Nx,), ys (Ny,))`` cell-centre coordinates in metres."""
        ny, nx = self.heights.shape
        return self.x0 + np.arange(nx) * self.res, self.y0 + np.arange(ny) * self.res
