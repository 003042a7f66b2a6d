"""Supervised loss of the paper: L1 between predicted and measured depth over valid pixels only,
optionally weighted per pixel (``contact_weights``: the contact patches count more)."""

from __future__ import annotations

import torch


def masked_l1(pred: torch.Tensor, target: torch.Tensor, valid: torch.Tensor, inverse: bool = False,
              weight: torch.Tensor | None = None) -> torch.Tensor:
    """Mean ``|pred - target|`` over pixels where ``valid`` is true (weighted mean with ``weight``).

    ``pred``, ``target``: ``(N,1,H,W) float32 m``; ``valid``: ``(N,1,H,W) bool`` (ToF zeros and
    padding are false); ``weight``: ``(N,1,H,W) float32`` >= 0 or None (all 1). ``inverse``
    compares inverse depth (1/m) instead. A batch without any valid pixel gives a zero loss that
    still depends on ``pred`` (so backward works).
    """
    if inverse:
        pred = 1.0 / pred
        target = 1.0 / target.clamp(min=1e-6)
    mask = valid.to(pred.dtype)
    if weight is not None:
        mask = mask * weight
    count = mask.sum()
    total = (torch.abs(pred - target) * mask).sum()
    return total / count.clamp(min=1.0)


def contact_weights(contact: torch.Tensor, contact_weight: float) -> torch.Tensor:
    """Per-pixel loss weights ``(N,1,H,W) float32``: ``1 + contact_weight`` on the contact patches
    (``contact (N,1,H,W) bool``), 1 elsewhere. A few-mm dent covers ~5 % of the image; unweighted,
    the network can ignore it and still fit the rest of the membrane to ~0.2 mm."""
    return 1.0 + contact_weight * contact.to(torch.float32)
