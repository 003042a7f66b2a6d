"""Contact against a sensor's no-contact reference: the reference depth map and the contact mask.

Shared by the trainer (contact-weighted loss) and the pose check (``calibrate.contact_patch``).
Depth maps are ``(H,W) float32 m`` camera z-depth, 0 (or non-finite) = invalid.
"""

from __future__ import annotations

import warnings

import numpy as np
from scipy import ndimage

from collect.errors import InputError

#: Depth decrease from the reference (m) that marks a pixel as in contact (the pose check's patch).
CONTACT_THRESHOLD_M = 1.5e-3


def _valid(depth: np.ndarray) -> np.ndarray:
    return np.isfinite(depth) & (depth > 0.0)


def reference_depth(frames: np.ndarray) -> np.ndarray:
    """No-contact reference: per-pixel median of the valid depths of ``frames (K,H,W) m``.

    Returns ``(H,W) float32 m``, 0 where no frame was valid.
    """
    frames = np.asarray(frames, dtype=np.float32)
    if frames.ndim != 3 or len(frames) == 0:
        raise InputError(f"no-contact reference needs (K,H,W) depth frames, got shape {frames.shape}")
    masked = np.where(_valid(frames), frames, np.nan)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN pixels (never valid) -> NaN
        ref = np.nanmedian(masked, axis=0)
    ref = np.nan_to_num(ref, nan=0.0)
    return ref.astype(np.float32)


def drop_specks(mask: np.ndarray, min_pixels: int) -> np.ndarray:
    """``mask (H,W) or (N,H,W) bool`` without its 8-connected parts of fewer than ``min_pixels``
    pixels in each image (single pixels where depth noise crossed the threshold)."""
    mask = np.asarray(mask, dtype=bool)
    neighbours = np.ones((3, 3), dtype=bool)
    if mask.ndim == 3:  # connected within each image only
        neighbours = np.stack([np.zeros_like(neighbours), neighbours, np.zeros_like(neighbours)])
    labels, _ = ndimage.label(mask, structure=neighbours)
    keep = np.bincount(labels.ravel(), minlength=1) >= min_pixels
    keep[0] = False  # the background
    return keep[labels]


def contact_mask(depth: np.ndarray, reference: np.ndarray,
                 threshold_m: float = CONTACT_THRESHOLD_M) -> np.ndarray:
    """``(H,W) bool`` (or ``(N,H,W)`` for ``(N,H,W)`` depth maps against one ``(H,W)``
    reference): valid in both and closer to the camera than the reference by > threshold."""
    depth = np.asarray(depth, dtype=np.float32)
    reference = np.asarray(reference, dtype=np.float32)
    if depth.shape[-2:] != reference.shape:
        raise InputError(f"depth {depth.shape} and reference {reference.shape} differ in shape")
    with np.errstate(invalid="ignore"):
        return _valid(depth) & _valid(reference) & (reference - depth > threshold_m)
