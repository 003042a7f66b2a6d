"""Supervised loss of the paper: L1 between predicted and measured depth over valid pixels only."""

from __future__ import annotations

import torch


def masked_l1(pred: torch.Tensor, target: torch.Tensor, valid: torch.Tensor, inverse: bool = False) -> torch.Tensor:
    """Mean ``|pred - target|`` over pixels where ``valid`` is true.

    ``pred``, ``target``: ``(N,1,H,W) float32 m``; ``valid``: ``(N,1,H,W) bool`` (ToF zeros and
    padding are false). ``inverse`` compares inverse depth (1/m) instead. A batch without any
    valid pixel gives a zero loss that still depends on ``pred`` (so backward works).
    """
    if inverse:
        pred = 1.0 / pred
        target = 1.0 / target.clamp(min=1e-6)
    mask = valid.to(pred.dtype)
    count = mask.sum()
    total = (torch.abs(pred - target) * mask).sum()
    return total / count.clamp(min=1.0)
