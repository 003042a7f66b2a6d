"""ToF depth image with the artifacts of a real sensor.

From the true z-depth and the noise-free amplitude: noise growing as 1/amplitude
(``depth_noise_m`` at ``emitter_amplitude``), a systematic bias (offset + radial term),
dropouts (0) where the amplitude saturates (close range) or is too weak, at grazing incidence,
outside the valid field of view and on the housing; flying pixels (mixtures of foreground and
background depth) where the depth gets steeper than at rest, i.e. at contact edges; stuck dead pixels.
Output in ``collect.session_format.DEPTH_UNIT_M``, 0 = invalid.
"""

from __future__ import annotations

import cv2
import numpy as np

from collect.session_format import DEPTH_UNIT_M
from hw_mocks.sensor_spec import SensorSpec

#: Fraction of flying pixels the camera's own filter rejects (reported as 0).
FLYING_PIXEL_DROP = 0.3
_KERNEL = np.ones((3, 3), np.uint8)


class TofRenderer:
    """Depth rendering for one sensor on the full image grid (``rays (H,W,3)``, z = 1)."""

    def __init__(
        self, spec: SensorSpec, rays: np.ndarray, membrane_mask: np.ndarray, housing_depth: np.ndarray, rest_depth: np.ndarray
    ):
        self.spec = spec
        self.membrane_mask = membrane_mask
        self.housing_depth = housing_depth.astype(np.float32)
        rest = np.where(membrane_mask, rest_depth, self.housing_depth).astype(np.float32)
        #: 3x3 depth spread of the rest membrane (m): the smooth dome's own slope.
        self.rest_spread = cv2.dilate(rest, _KERNEL) - cv2.erode(rest, _KERNEL)
        r2 = rays[..., 0] ** 2 + rays[..., 1] ** 2
        field_angle = np.arctan(np.sqrt(r2))
        #: pixels that can hold a valid depth at all: membrane inside the valid field of view.
        self.valid_fov = membrane_mask & (field_angle <= spec.valid_fov_rad)
        self.bias = (spec.depth_bias_m + spec.depth_bias_radial_m * r2).astype(np.float32)
        dead = np.asarray(spec.dead_pixels, dtype=np.int64).reshape(-1, 2)
        self.dead = (dead[:, 0], dead[:, 1])

    def render(self, depth: np.ndarray, amplitude: np.ndarray, incidence: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """``depth (H,W) float32 m`` true, ``amplitude`` noise-free, ``incidence`` cosines ->
        measured depth ``(H,W) uint16`` in ``DEPTH_UNIT_M``, 0 = invalid."""
        spec = self.spec
        valid = (
            self.valid_fov
            & (amplitude < spec.saturation_amplitude)
            & (amplitude > spec.min_amplitude)
            & (incidence > spec.min_incidence_cos)
        )
        sigma = spec.depth_noise_m * spec.emitter_amplitude / np.maximum(amplitude, spec.min_amplitude)
        measured = depth + self.bias + sigma * rng.standard_normal(depth.shape, dtype=np.float32)

        # Flying pixels: where the depth spread of the 3x3 neighbourhood exceeds its spread at rest
        # (steep dent walls and creases at contact edges), the pixel mixes near and far depths.
        filled = np.where(self.membrane_mask, depth, self.housing_depth).astype(np.float32)
        hi_all, lo_all = cv2.dilate(filled, _KERNEL), cv2.erode(filled, _KERNEL)
        flying = self.valid_fov & (hi_all - lo_all - self.rest_spread > spec.flying_pixel_jump_m)
        if flying.any():
            n = int(flying.sum())
            hi, lo = hi_all[flying], lo_all[flying]
            measured[flying] = lo + rng.uniform(0.0, 1.0, n).astype(np.float32) * (hi - lo)
            dropped = np.zeros(depth.shape, dtype=bool)
            dropped[flying] = rng.uniform(0.0, 1.0, n) < FLYING_PIXEL_DROP
            valid &= ~dropped

        out = np.where(valid, np.clip(np.rint(measured / DEPTH_UNIT_M), 1, 65535), 0).astype(np.uint16)
        out[self.dead] = int(round(spec.dead_pixel_depth_m / DEPTH_UNIT_M))
        return out
