"""IR amplitude image of the ToF camera looking at the membrane.

The only light source is the camera's own emitter, so a Lambertian membrane point returns
``emitter_amplitude * albedo * cos(incidence) * (0.093 m / range)^2 * vignetting`` with
vignetting ``cos(field angle)^vignetting_exponent``. Shot noise (variance ``shot_noise_gain *
amplitude``) plus read noise, 16-bit clipping, and stuck values at dead pixels.
"""

from __future__ import annotations

import cv2
import numpy as np

from hw_mocks.sensor_spec import SensorSpec

#: Range (m) at which ``spec.emitter_amplitude`` is defined.
REFERENCE_RANGE_M = 0.093
#: Albedo of the dark housing seen beyond the rim.
HOUSING_ALBEDO = 0.04
FULL_SCALE = 65535


def surface_incidence(depth: np.ndarray, rays: np.ndarray, fx: float, fy: float) -> np.ndarray:
    """``cos`` of the angle between each pixel's viewing ray and the surface normal of the depth
    map ``depth (H,W) float32 m`` (central differences), ``(H,W) float32`` in [0, 1].

    With ``P = d * r``, ``r = ((u-cx)/fx, (v-cy)/fy, 1)``: ``n ~ (-A, -B, A r_x + B r_y + C)``,
    ``A = d_u/fy``, ``B = d_v/fx``, ``C = d/(fx fy)``, and ``n . r = C``.
    """
    a = cv2.Sobel(depth, cv2.CV_32F, 1, 0, ksize=1) * np.float32(0.5 / fy)
    b = cv2.Sobel(depth, cv2.CV_32F, 0, 1, ksize=1) * np.float32(0.5 / fx)
    c = depth * np.float32(1.0 / (fx * fy))
    nz = a * rays[..., 0] + b * rays[..., 1] + c
    norm = np.sqrt((a * a + b * b + nz * nz) * (rays[..., 0] ** 2 + rays[..., 1] ** 2 + 1.0))
    return np.abs(c) / np.maximum(norm, np.float32(1e-30))


class IrRenderer:
    """Amplitude rendering for one sensor on the full image grid (``rays (H,W,3)``, z = 1)."""

    def __init__(self, spec: SensorSpec, rays: np.ndarray, housing_depth: np.ndarray):
        self.spec = spec
        ray_len = np.linalg.norm(rays, axis=-1)
        self.ray_len = ray_len.astype(np.float32)
        #: emitter amplitude times vignetting per pixel (before albedo, incidence and range).
        self.gain = (spec.emitter_amplitude * ray_len ** (-spec.vignetting_exponent)).astype(np.float32)
        housing_range = np.maximum(housing_depth * ray_len, 1e-3)
        self.housing = (self.gain * HOUSING_ALBEDO * (REFERENCE_RANGE_M / housing_range) ** 2).astype(np.float32)
        dead = np.asarray(spec.dead_pixels, dtype=np.int64).reshape(-1, 2)
        self.dead = (dead[:, 0], dead[:, 1])

    def clean(self, depth: np.ndarray, albedo: np.ndarray, incidence: np.ndarray, mask: np.ndarray) -> np.ndarray:
        """Noise-free amplitude ``(H,W) float32``: membrane where ``mask``, housing elsewhere."""
        rng_m = np.maximum(depth * self.ray_len, 1e-3)
        amp = self.gain * albedo * incidence * (REFERENCE_RANGE_M / rng_m) ** 2
        return np.where(mask, amp, self.housing).astype(np.float32)

    def noisy(self, amplitude: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """16-bit amplitude image with shot + read noise and dead pixels, ``(H,W) uint16``."""
        sigma = np.sqrt(self.spec.shot_noise_gain * amplitude + self.spec.read_noise**2)
        noisy = amplitude + sigma * rng.standard_normal(amplitude.shape, dtype=np.float32)
        out = np.clip(np.rint(noisy), 0, FULL_SCALE).astype(np.uint16)
        out[self.dead] = self.spec.dead_pixel_ir
        return out
