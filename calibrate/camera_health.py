"""Camera health from a burst of no-contact frames: defective pixels, depth coverage, dot pattern.

Input: ``ir (N,H,W) uint16`` amplitude and ``depth (N,H,W) uint16`` ToF depth (0 = invalid) of
the free, untouched bubble, ``N >= 4`` frames.

* dead pixels: read (near) zero in every frame although their neighbourhood is lit;
* stuck pixels: read the same non-zero value in every frame (healthy lit pixels always carry
  shot and read noise); only pixels whose neighbourhood is lit are judged (not the housing);
* valid-depth coverage: mean fraction of the image with valid depth;
* dot pattern: the printed dots darken the membrane locally. The time-mean IR image is divided
  by its local background (a high percentile over a window larger than a dot); pixels darker
  than ``DOT_RATIO`` of the background, away from the edge of the lit region, are dot pixels.
  ``dot_count`` is the number of dot blobs of a plausible size, ``dot_contrast`` the median over
  those dots of ``1 - ratio`` at their darkest pixel (0 without dots).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy import ndimage

from collect.errors import InputError

#: A pixel is lit when its local background IR is above this fraction of the image's 99th percentile.
LIT_FRACTION = 0.05
#: Dead: temporal max below this fraction of the local background.
DEAD_FRACTION = 0.02
#: Dot pixels: IR below this fraction of the local background.
DOT_RATIO = 0.75
#: Window of the local background, px (larger than a dot).
BACKGROUND_WINDOW = 15
#: Dot blobs (8-connected, px) smaller than the first are specks (dust, a hot-pixel's neighbour),
#: larger than the second are not dots; a printed dot covers 4-40 px on the default camera.
DOT_MIN_AREA, DOT_MAX_AREA = 3, 400


@dataclass
class CameraHealth:
    """Results and the per-pixel maps the report shows (all ``(H,W)``)."""

    dead_pixels: int
    stuck_pixels: int
    valid_depth_coverage: float  # 0..1
    dot_contrast: float  # 0..1
    dot_count: int
    dead_mask: np.ndarray  # bool
    stuck_mask: np.ndarray  # bool
    valid_count: np.ndarray  # int32 frames with valid depth per pixel
    ir_mean: np.ndarray  # float32 time-mean amplitude
    dot_mask: np.ndarray  # bool
    n_frames: int

    def summary(self) -> str:
        return (
            f"{self.dead_pixels} dead, {self.stuck_pixels} stuck px, depth coverage {self.valid_depth_coverage:.0%}, "
            f"{self.dot_count} dots (contrast {self.dot_contrast:.2f})"
        )

    def to_json(self) -> dict:
        return {
            "dead_pixels": self.dead_pixels,
            "stuck_pixels": self.stuck_pixels,
            "valid_depth_coverage": self.valid_depth_coverage,
            "dot_contrast": self.dot_contrast,
            "dot_count": self.dot_count,
            "n_frames": self.n_frames,
        }

    def maps(self) -> dict[str, np.ndarray]:
        """The per-pixel maps, each ``(H,W)``, for ``np.savez``."""
        return {
            "dead_mask": self.dead_mask,
            "stuck_mask": self.stuck_mask,
            "valid_count": self.valid_count,
            "ir_mean": self.ir_mean,
            "dot_mask": self.dot_mask,
        }


def local_background(image: np.ndarray, window: int = BACKGROUND_WINDOW) -> np.ndarray:
    """``(H,W) float32``: the 80th percentile of ``image`` over a ``window`` x ``window`` neighbourhood."""
    return ndimage.percentile_filter(image.astype(np.float32), 80, size=window, mode="nearest")


def assess_camera(ir: np.ndarray, depth: np.ndarray) -> CameraHealth:
    """Camera health of ``N >= 4`` no-contact frames: ``ir (N,H,W) uint16`` amplitude and ``depth
    (N,H,W) uint16`` ToF depth (0 = invalid); see the module docstring."""
    ir = np.asarray(ir)
    depth = np.asarray(depth)
    if ir.ndim != 3 or ir.shape != depth.shape:
        raise InputError(f"camera health: need (N,H,W) IR and depth of one shape, got {ir.shape} and {depth.shape}")
    if ir.shape[0] < 4:
        raise InputError(f"camera health: need at least 4 no-contact frames, got {ir.shape[0]}")
    n = ir.shape[0]
    irf = ir.astype(np.float32)
    ir_max = irf.max(axis=0)
    ir_min = irf.min(axis=0)
    ir_mean = irf.mean(axis=0)

    # Neighbourhood level without the pixel's own defects pulling it down: the percentile filter
    # ignores isolated dark pixels and small clusters.
    background = local_background(ir_mean)
    lit = background > LIT_FRACTION * max(float(np.percentile(ir_mean, 99)), 1.0)

    dead = lit & (ir_max <= DEAD_FRACTION * background)
    stuck = lit & (ir_max == ir_min) & ~dead

    valid = depth > 0
    valid_count = valid.sum(axis=0).astype(np.int32)
    coverage = float(valid.mean())

    # Dots are judged away from the edge of the lit region, where the background estimate
    # runs off the membrane (the housing would look like a dark blob), and on the membrane: the
    # region of valid depth in most frames, the holes its dots make in it filled (was: the housing
    # at the image's top and bottom edges passed as 1-3 dots of full contrast on a sensor with none).
    membrane = ndimage.binary_fill_holes(valid_count > n // 2)
    core = ndimage.binary_erosion(lit, iterations=BACKGROUND_WINDOW // 2) & membrane & ~dead & ~stuck
    ratio = np.where(core, ir_mean / np.maximum(background, 1.0), 1.0)
    _, labels, stats, _ = cv2.connectedComponentsWithStats((core & (ratio < DOT_RATIO)).astype(np.uint8), connectivity=8)
    areas = stats[1:, cv2.CC_STAT_AREA]
    dots = np.flatnonzero((areas >= DOT_MIN_AREA) & (areas <= DOT_MAX_AREA)) + 1
    dot_mask = np.isin(labels, dots)
    dot_count = int(dots.size)
    # darkest pixel of each dot (its centre), median over the dots
    contrast = float(1.0 - np.median(ndimage.minimum(ratio, labels, dots))) if dot_count else 0.0
    return CameraHealth(
        dead_pixels=int(dead.sum()),
        stuck_pixels=int(stuck.sum()),
        valid_depth_coverage=coverage,
        dot_contrast=contrast,
        dot_count=dot_count,
        dead_mask=dead,
        stuck_mask=stuck,
        valid_count=valid_count,
        ir_mean=ir_mean,
        dot_mask=dot_mask,
        n_frames=n,
    )
