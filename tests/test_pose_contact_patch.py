"""Contact patch: mask against the no-contact reference, lifting with intrinsics, downsampling."""

import numpy as np
import pytest

from calibrate.contact_patch import contact_points, downsample, lift
from trainer.contact import contact_mask, reference_depth
from collect.errors import InputError

INTR = {"fx": 120.0, "fy": 118.0, "cx": 111.5, "cy": 85.5, "width": 224, "height": 172}
H, W = 172, 224


def _dented(depth_ref: np.ndarray, center=(86, 112), radius_px=25, depth_mm=5.0) -> np.ndarray:
    rows, cols = np.mgrid[:H, :W]
    r2 = ((rows - center[0]) ** 2 + (cols - center[1]) ** 2) / radius_px**2
    dent = np.clip(1.0 - r2, 0.0, None) * depth_mm * 1e-3
    return (depth_ref - dent).astype(np.float32)


def test_reference_depth_is_median_of_valid_pixels():
    rng = np.random.default_rng(0)
    frames = np.full((5, H, W), 0.09, np.float32) + rng.normal(0, 1e-5, (5, H, W)).astype(np.float32)
    frames[0, 10, 10] = 0.0  # dropout
    frames[1, 10, 10] = np.nan
    frames[2, 10, 10] = 0.5  # outlier: the median ignores it
    frames[:, 0, 0] = 0.0  # never valid
    ref = reference_depth(frames)
    assert ref.dtype == np.float32 and ref.shape == (H, W)
    assert ref[0, 0] == 0.0
    assert abs(ref[10, 10] - 0.09) < 1e-4
    with pytest.raises(InputError):
        reference_depth(np.zeros((H, W)))


def test_contact_mask_selects_dent_beyond_threshold_and_ignores_invalid():
    ref = np.full((H, W), 0.09, np.float32)
    ref[:5] = 0.0  # housing, invalid in the reference
    depth = _dented(ref + 0.0)
    depth[86, 112] = 0.0  # dropout at the centre
    depth[90, 112] = np.nan
    mask = contact_mask(depth, ref, threshold_m=1.5e-3)
    rows, cols = np.mgrid[:H, :W]
    expected = ((rows - 86) ** 2 + (cols - 112) ** 2) / 25**2 < 1.0 - 1.5 / 5.0
    expected[86, 112] = expected[90, 112] = False
    # equality up to pixels on the threshold's rim
    assert np.sum(mask != expected) <= 8
    assert not mask[86, 112] and not mask[90, 112]
    with pytest.raises(InputError):
        contact_mask(depth[:10], ref)


def test_lift_inverts_the_pinhole_projection():
    rng = np.random.default_rng(1)
    depth = rng.uniform(0.06, 0.1, (H, W)).astype(np.float32)
    mask = rng.random((H, W)) < 0.05
    pts = lift(depth, mask, INTR)
    rows, cols = np.nonzero(mask)
    u = INTR["fx"] * pts[:, 0] / pts[:, 2] + INTR["cx"]
    v = INTR["fy"] * pts[:, 1] / pts[:, 2] + INTR["cy"]
    np.testing.assert_allclose(u, cols, atol=1e-6)
    np.testing.assert_allclose(v, rows, atol=1e-6)
    np.testing.assert_allclose(pts[:, 2], depth[mask], rtol=1e-6)


def test_downsample_is_deterministic_and_spreads_over_the_patch():
    pts = np.arange(9000 * 3, dtype=float).reshape(9000, 3)
    a = downsample(pts, 1500)
    b = downsample(pts, 1500)
    assert a.shape == (1500, 3)
    np.testing.assert_array_equal(a, b)
    assert a[0, 0] == pts[0, 0] and a[-1, 0] == pts[-1, 0]  # first and last both kept
    assert len(np.unique(a[:, 0])) == 1500
    few = pts[:100]
    np.testing.assert_array_equal(downsample(few, 1500), few)


def test_contact_points_of_a_dent_lie_in_it():
    ref = np.full((H, W), 0.09, np.float32)
    depth = _dented(ref, radius_px=40, depth_mm=6.0)
    pts = contact_points(depth, ref, INTR, threshold_m=1e-3, n_points=1500)
    assert pts.shape == (1500, 3)
    assert np.all(pts[:, 2] < 0.09 - 1e-3)
    assert abs(np.mean(pts[:, 0])) < 2e-3  # centred on the optical axis (dent at the image centre)
    none = contact_points(ref, ref, INTR)
    assert none.shape == (0, 3)
