"""Where the camera rays meet an object: the obstacle of the membrane problem.

Each object is represented by its top-down height field (``hw_mocks.heightmap``). A ray is
marched through a depth window around the rest membrane depth (the only depths the membrane can
reach), the first sample below the height field brackets the hit, bisection and a secant step
refine it. All look-ups are vectorized ``cv2.remap`` calls.
"""

from __future__ import annotations

import numpy as np

from hw_mocks.heightmap import Heightmap

#: The membrane can be pushed at most this far towards the camera (m) ...
REACH_IN_M = 0.035
#: ... and bulges out at most this far (m): beyond it an object cannot touch the membrane.
REACH_OUT_M = 0.004
MARCH_SAMPLES = 9
BISECTIONS = 3


def object_depth(
    heightmap: Heightmap, obj_from_cam: np.ndarray, rays: np.ndarray, rest_depth: np.ndarray
) -> np.ndarray:
    """Z-depth (m) at which each camera ray first enters the object, ``inf`` where it does not
    within ``[rest_depth - REACH_IN_M, rest_depth + REACH_OUT_M]``.

    ``obj_from_cam (4,4)``: camera frame -> object frame. ``rays (rows,cols,3)`` camera frame with
    z = 1; ``rest_depth (rows,cols)`` m. Returns ``(rows,cols) float64``; rays hitting the object
    before the window get the window start.
    """
    shape = rest_depth.shape
    r = obj_from_cam[:3, :3]
    o = obj_from_cam[:3, 3]
    v = (rays.reshape(-1, 3) @ r.T).astype(np.float32)
    t_lo = (rest_depth.ravel() - REACH_IN_M).astype(np.float32)
    t_hi = (rest_depth.ravel() + REACH_OUT_M).astype(np.float32)
    out = np.full(t_lo.shape, np.inf)

    # Candidates: rays whose window segment reaches below the object's top and whose x/y span
    # overlaps the object's footprint.
    z_far = o[2] + t_hi * v[:, 2]
    z_near = o[2] + t_lo * v[:, 2]
    x_min, x_max, y_min, y_max = heightmap.covered_bounds
    x_a, x_b = o[0] + t_lo * v[:, 0], o[0] + t_hi * v[:, 0]
    y_a, y_b = o[1] + t_lo * v[:, 1], o[1] + t_hi * v[:, 1]
    near = (
        (np.minimum(z_far, z_near) <= heightmap.top)
        & (np.maximum(x_a, x_b) >= x_min)
        & (np.minimum(x_a, x_b) <= x_max)
        & (np.maximum(y_a, y_b) >= y_min)
        & (np.minimum(y_a, y_b) <= y_max)
    )
    candidates = np.nonzero(near)[0]
    if len(candidates) == 0:
        return out.reshape(shape)
    v = np.ascontiguousarray(v[candidates].T)  # (3, n)
    t_lo, t_hi = t_lo[candidates], t_hi[candidates]
    ox, oy, oz = (np.float32(c) for c in o)

    def above(t: np.ndarray, vv: np.ndarray) -> np.ndarray:
        """Height of the ray points ``o + t*vv`` above the surface (m): > 0 outside the object."""
        return oz + t * vv[2] - heightmap.sample(ox + t * vv[0], oy + t * vv[1])

    steps = np.linspace(0.0, 1.0, MARCH_SAMPLES, dtype=np.float32)
    f_prev = above(t_lo, v)
    inside_at_start = f_prev <= 0
    hit_lo = np.where(inside_at_start, t_lo, np.nan).astype(np.float32)
    hit_hi = hit_lo.copy()
    f_lo = np.zeros_like(t_lo)
    f_hi = np.zeros_like(t_lo)
    open_ = ~inside_at_start
    t_prev = t_lo.copy()
    for s in steps[1:]:
        if not open_.any():
            break
        sel = np.nonzero(open_)[0]
        t = t_lo[sel] + s * (t_hi[sel] - t_lo[sel])
        f = above(t, v[:, sel])
        crossed = f <= 0
        c = sel[crossed]
        hit_lo[c], hit_hi[c] = t_prev[sel][crossed], t[crossed]
        f_lo[c], f_hi[c] = f_prev[sel][crossed], f[crossed]
        open_[c] = False
        t_prev[sel] = t
        f_prev[sel] = f

    brackets = np.nonzero(~inside_at_start & ~np.isnan(hit_lo))[0]
    if len(brackets):
        a, b = hit_lo[brackets], hit_hi[brackets]
        fa, fb = f_lo[brackets], f_hi[brackets]
        vv = v[:, brackets]
        for _ in range(BISECTIONS):
            mid = 0.5 * (a + b)
            fm = above(mid, vv)
            below = fm <= 0
            b = np.where(below, mid, b)
            fb = np.where(below, fm, fb)
            a = np.where(below, a, mid)
            fa = np.where(below, fa, fm)
        denom = np.where(fa - fb > 1e-9, fa - fb, 1.0)
        t_hit = np.where(fa - fb > 1e-9, a + (b - a) * fa / denom, b)
        hit_lo[brackets] = t_hit
    found = ~np.isnan(hit_lo)
    out[candidates[found]] = hit_lo[found]
    return out.reshape(shape)
