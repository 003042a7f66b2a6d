"""The pseudo-random black dot pattern printed on the inside of the membrane.

Dots are placed on a jittered hexagonal lattice in the TCP-frame x/y coordinates of the dome
(seeded by ``spec.dot_seed``; spacing from ``spec.dot_coverage`` and ``spec.dot_radius_m``).
``albedo_texture`` paints them into an image indexed by the *rest* pixel of each membrane
material point; the renderer warps that texture by the material motion, so the dots move with
the membrane.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from hw_mocks.dome import Dome, RayGrid
from hw_mocks.sensor_spec import SensorSpec


def dot_centres(spec: SensorSpec) -> np.ndarray:
    """``(N,2) float64 m``: dot centres (TCP-frame x, y; on the dome surface) inside the rim;
    empty without dots. Spacing is set in x/y, so dots thin out slightly on the steep flanks."""
    if not spec.dots:
        return np.zeros((0, 2))
    rng = np.random.default_rng(spec.dot_seed)
    r = spec.dot_radius_m
    spacing = np.sqrt(2 * np.pi * r * r / (np.sqrt(3) * spec.dot_coverage))
    a, b = spec.dome_semi_x_m, spec.dome_semi_y_m
    rows = np.arange(-b, b + spacing, spacing * np.sqrt(3) / 2)
    pts = []
    for k, y in enumerate(rows):
        xs = np.arange(-a, a + spacing, spacing) + (spacing / 2 if k % 2 else 0.0)
        pts.append(np.stack([xs, np.full_like(xs, y)], axis=1))
    pts = np.concatenate(pts)
    pts += rng.uniform(-0.3, 0.3, size=pts.shape) * max(spacing - 2 * r, 0.0)
    inside = (pts[:, 0] / a) ** 2 + (pts[:, 1] / b) ** 2 <= 1.0
    return pts[inside]


def albedo_texture(spec: SensorSpec, dome: Dome, grid: RayGrid, rest_depth: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """``(rows,cols) float32`` albedo of the membrane material seen at rest by each pixel of
    ``grid`` (membrane albedo, dots darker, edges anti-aliased over one pixel footprint)."""
    texture = np.full(grid.shape, spec.membrane_albedo, dtype=np.float32)
    centres = dot_centres(spec)
    if len(centres) == 0:
        return texture
    # Distances on the dome surface (3-D), so printed dots are round on the membrane.
    h, a, b = spec.dome_height_m, spec.dome_semi_x_m, spec.dome_semi_y_m
    z = -h * ((centres[:, 0] / a) ** 2 + (centres[:, 1] / b) ** 2)
    p = dome.to_tcp(grid.rays * rest_depth[..., None])
    dist, _ = cKDTree(np.column_stack([centres, z])).query(p[mask])
    footprint = rest_depth[mask] * grid.step / spec.fx  # m per pixel on the membrane
    ink = np.clip(0.5 - (dist - spec.dot_radius_m) / footprint, 0.0, 1.0)
    texture[mask] = spec.membrane_albedo + (spec.dot_albedo - spec.membrane_albedo) * ink
    return texture
