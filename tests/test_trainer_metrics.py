"""trainer.metrics against hand-computed values (the definitions in its docstring)."""

import math

import numpy as np
import pytest

from collect.errors import InputError
from trainer.metrics import METRIC_KEYS, depth_metrics


def test_single_image_matches_hand_computation():
    gt = np.array([[0.10, 0.08], [0.05, 0.0]])  # last pixel invalid (ToF dropout)
    pred = np.array([[0.11, 0.08], [0.02, 0.09]])  # 0.02 gets clamped to min_depth 0.04
    m = depth_metrics(pred, gt, min_depth=0.04, max_depth=0.12)
    p = np.array([0.11, 0.08, 0.04])
    g = np.array([0.10, 0.08, 0.05])
    d = np.log(p) - np.log(g)
    assert m["abs_rel"] == pytest.approx((0.01 / 0.10 + 0 + 0.01 / 0.05) / 3)
    assert m["sq_rel"] == pytest.approx((0.01**2 / 0.10 + 0 + 0.01**2 / 0.05) / 3)
    assert m["rmse"] == pytest.approx(math.sqrt((0.01**2 + 0 + 0.01**2) / 3))
    assert m["rmse_log"] == pytest.approx(math.sqrt(np.mean(d**2)))
    assert m["silog"] == pytest.approx(100 * math.sqrt(np.mean(d**2) - np.mean(d) ** 2))
    # ratios 1.1, 1.0, 1.25 against thresholds 1.05, 1.1025, 1.157625
    assert m["a1"] == pytest.approx(1 / 3)
    assert m["a2"] == pytest.approx(2 / 3)
    assert m["a3"] == pytest.approx(2 / 3)
    assert m["n_images"] == 1 and m["n_pixels"] == 3
    assert set(METRIC_KEYS) <= set(m)


def test_per_image_then_mean_over_images():
    gt = np.full((2, 1, 2), 0.1)
    gt[1, 0, 1] = 0.0  # image 1 has one valid pixel
    pred = np.array([[[0.1, 0.1]], [[0.12, 0.1]]])
    m = depth_metrics(pred, gt, min_depth=0.04, max_depth=0.2)
    # image 0: abs_rel 0; image 1: abs_rel 0.2 -> mean 0.1 (a pixel mean would give 0.2/3)
    assert m["abs_rel"] == pytest.approx(0.1)
    assert m["a1"] == pytest.approx(0.5)
    assert m["n_images"] == 2 and m["n_pixels"] == 3


def test_constant_log_offset_has_zero_silog_and_out_of_range_gt_ignored():
    gt = np.array([[0.05, 0.10, 0.5]])  # 0.5 m is beyond max_depth: ignored
    m = depth_metrics(gt * 1.02, gt, min_depth=0.04, max_depth=0.12)
    assert m["silog"] == pytest.approx(0.0, abs=1e-6)
    assert m["rmse_log"] == pytest.approx(math.log(1.02))
    assert m["a1"] == 1.0 and m["n_pixels"] == 2


def test_no_valid_pixel_gives_nan_and_zero_counts():
    m = depth_metrics(np.ones((3, 3)) * 0.1, np.zeros((3, 3)))
    assert math.isnan(m["abs_rel"]) and m["n_images"] == 0 and m["n_pixels"] == 0


def test_mask_restricts_pixels_and_shape_errors():
    gt = np.array([[0.1, 0.1]])
    pred = np.array([[0.1, 0.2]])
    assert depth_metrics(pred, gt, mask=np.array([[True, False]]))["abs_rel"] == 0.0
    with pytest.raises(InputError):
        depth_metrics(pred, gt[:, :1])
    with pytest.raises(InputError):
        depth_metrics(pred[None, None], gt[None, None])


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_a_non_finite_prediction_makes_every_metric_nan(bad):
    """Was: NaN abs_rel, rmse, silog but finite a1-a3 (the NaN pixel a miss), and inf clipped to a
    bound (all finite), though the docstring said NaN only for no valid pixel."""
    gt = np.full((2, 2, 2), 0.1)
    pred = gt.copy()
    pred[1, 0, 0] = bad
    m = depth_metrics(pred, gt)
    assert all(math.isnan(m[k]) for k in METRIC_KEYS), m
    assert m["n_images"] == 2 and m["n_pixels"] == 8
    gt[1, 0, 0] = 0.0  # the same prediction on an ignored pixel (ToF dropout) counts for nothing
    assert depth_metrics(pred, gt)["a1"] == 1.0
