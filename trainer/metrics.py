"""The paper's depth metrics (as in the BTS / packnet-sfm evaluation code).

Over valid ground-truth pixels (``min_depth < gt < max_depth``), the prediction clamped to
``[min_depth, max_depth]``, each metric is computed per image and then averaged over images:

* ``abs_rel = mean(|gt - pred| / gt)``, ``sq_rel = mean((gt - pred)^2 / gt)`` (m)
* ``rmse = sqrt(mean((gt - pred)^2))`` (m), ``rmse_log = sqrt(mean((ln gt - ln pred)^2))``
* ``silog = 100 * sqrt(mean(d^2) - mean(d)^2)``, ``d = ln pred - ln gt`` (population variance,
  clamped at 0)
* ``a1, a2, a3 = mean(max(gt/pred, pred/gt) < 1.05 ** k)`` for k = 1, 2, 3 (the paper's tight
  thresholds).

Images without any valid ground-truth pixel are left out of the average (``n_images`` counts
the images that took part, ``n_pixels`` their valid pixels). An image whose prediction is NaN or
inf on a valid pixel (a diverged network) has every metric NaN, so the averages are NaN too: a
check of any one key sees it (``trainer.training`` refuses a model whose ``abs_rel`` is not finite).
"""

from __future__ import annotations

import numpy as np

from collect.errors import InputError

#: The metric keys, in the order of the paper's tables plus the remaining ones.
METRIC_KEYS = ("abs_rel", "sq_rel", "rmse", "rmse_log", "silog", "a1", "a2", "a3")

#: Base of the accuracy thresholds ``delta < THRESHOLD_BASE ** k``.
THRESHOLD_BASE = 1.05


def image_metrics(pred: np.ndarray, gt: np.ndarray) -> dict[str, float]:
    """Metrics of one image over already-selected pixels.

    ``pred`` and ``gt`` are ``(P,) float64 m``, both strictly positive, ``P >= 1``.
    """
    ratio = np.maximum(gt / pred, pred / gt)
    diff = gt - pred
    d = np.log(pred) - np.log(gt)
    silog_var = max(float(np.mean(d**2) - np.mean(d) ** 2), 0.0)
    return {
        "abs_rel": float(np.mean(np.abs(diff) / gt)),
        "sq_rel": float(np.mean(diff**2 / gt)),
        "rmse": float(np.sqrt(np.mean(diff**2))),
        "rmse_log": float(np.sqrt(np.mean(d**2))),
        "silog": float(100.0 * np.sqrt(silog_var)),
        "a1": float(np.mean(ratio < THRESHOLD_BASE)),
        "a2": float(np.mean(ratio < THRESHOLD_BASE**2)),
        "a3": float(np.mean(ratio < THRESHOLD_BASE**3)),
    }


def in_depth_range(depth, min_depth: float, max_depth: float):
    """Where ``depth`` (any shape, m; a numpy array or a torch tensor) lies strictly inside
    ``(min_depth, max_depth)``: the pixels that train a model and that its metrics count (0, an
    invalid ToF pixel, lies outside). A bool array or tensor of ``depth``'s shape."""
    return (depth > min_depth) & (depth < max_depth)


def no_depth_in_range(frames: str, min_depth: float, max_depth: float, purpose: str) -> InputError:
    """The one-line error for ``frames`` (e.g. ``no training frame``) without a ToF pixel in
    ``(min_depth, max_depth)`` m, which leaves nothing to ``purpose`` (e.g. ``train on``)."""
    return InputError(f"{frames} has ToF depth within the model's range {min_depth:g}-{max_depth:g} m: nothing to "
                      f"{purpose} (check the camera's depth stream: bubble info)")


def depth_metrics(
    pred: np.ndarray,
    gt: np.ndarray,
    min_depth: float = 0.04,
    max_depth: float = 0.12,
    mask: np.ndarray | None = None,
) -> dict[str, float | int]:
    """The paper's metrics of predicted against ground-truth depth.

    ``pred``, ``gt``: ``(H,W)`` or ``(N,H,W)`` depth in m (same shape); ``gt`` pixels outside
    ``(min_depth, max_depth)`` (0 = invalid ToF) are ignored. ``mask`` (same shape, bool)
    further restricts the pixels taken into account. Returns the keys of ``METRIC_KEYS``
    (averaged over images) plus ``n_images`` and ``n_pixels``; the metric values (all of them) are
    NaN when no image has a valid pixel, or when a prediction on a valid pixel is NaN or inf.
    """
    pred = np.asarray(pred, dtype=np.float64)
    gt = np.asarray(gt, dtype=np.float64)
    if pred.shape != gt.shape:
        raise InputError(f"prediction shape {pred.shape} differs from ground truth shape {gt.shape}")
    if pred.ndim == 2:
        pred, gt = pred[None], gt[None]
        mask = None if mask is None else np.asarray(mask)[None]
    if pred.ndim != 3:
        raise InputError(f"depth maps must be (H,W) or (N,H,W), got shape {pred.shape}")
    if not 0.0 < min_depth < max_depth:
        raise InputError(f"bad depth range: min_depth={min_depth}, max_depth={max_depth}")
    if mask is not None and np.shape(mask) != gt.shape:
        raise InputError(f"mask shape {np.shape(mask)} differs from depth shape {gt.shape}")

    per_image = []
    n_pixels = 0
    for i in range(gt.shape[0]):
        valid = in_depth_range(gt[i], min_depth, max_depth)
        if mask is not None:
            valid &= np.asarray(mask[i], dtype=bool)
        if not valid.any():
            continue
        p = pred[i][valid]
        finite = np.isfinite(p).all()  # was: inf clipped to a bound, NaN counted as a miss in a1-a3 only
        per_image.append(image_metrics(np.clip(p, min_depth, max_depth), gt[i][valid]) if finite
                         else dict.fromkeys(METRIC_KEYS, float("nan")))
        n_pixels += int(valid.sum())
    out: dict[str, float | int] = {}
    for key in METRIC_KEYS:
        out[key] = float(np.mean([m[key] for m in per_image])) if per_image else float("nan")
    out["n_images"] = len(per_image)
    out["n_pixels"] = n_pixels
    return out
