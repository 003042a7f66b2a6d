"""Geometry-respecting augmentation of normalized IR batches (training only).

Only the IR intensities change: a random emitter gain (an offset in log amplitude), a small
contrast change and, optionally, pixel noise. Pixels never move, so depth and validity stay as
measured (no flips: the principal point is off centre, so a flipped image would not match its depth).

Pixel noise is for pretraining across many sensors only; a fine-tune on one sensor does better
without it (docs/trainer.md, "Augmentation").
"""

from __future__ import annotations

import torch

#: Largest |ln gain| of the emitter-power change.
MAX_LOG_GAIN = 0.25
#: Largest relative contrast change.
MAX_CONTRAST = 0.1
#: Standard deviation of the pixel noise the base model is pretrained with, in normalized units
#: (``trainer.pretrain``; fine-tunes add none).
PRETRAIN_NOISE_STD = 0.03


def augment_ir(x: torch.Tensor, content: torch.Tensor, ir_std: float, generator: torch.Generator,
               noise_std: float = 0.0) -> torch.Tensor:
    """``x`` ``(B,1,h,w)`` normalized IR -> augmented copy; the padding (``~content`` ``(1,1,h,w)``) stays 0.

    ``ir_std`` is the normalization's std (ln-amplitude units), to turn a gain into an offset;
    ``noise_std`` the standard deviation of added Gaussian pixel noise (normalized units, 0 = none).
    """
    b = x.shape[0]
    log_gain = (torch.rand(b, 1, 1, 1, generator=generator) * 2 - 1) * MAX_LOG_GAIN
    contrast = 1.0 + (torch.rand(b, 1, 1, 1, generator=generator) * 2 - 1) * MAX_CONTRAST
    out = x * contrast + log_gain / ir_std
    if noise_std > 0:
        out = out + torch.randn(x.shape, generator=generator) * noise_std
    return out * content.to(x.dtype)
