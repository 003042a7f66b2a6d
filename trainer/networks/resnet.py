"""``resnet``: ResNet-18-style encoder + monodepth2-style decoder with skip connections.

The paper's fastest network. ``width`` scales every channel count (1.0 = ResNet-18).
Input ``(N,1,H,W)`` normalized IR (H, W multiples of 32), output ``(N,1,H,W) float32 m``.
"""

from __future__ import annotations

import torch
from torch import nn

from trainer.networks.blocks import ConvELU, ResNetEncoder, scaled, upsample2
from trainer.networks.depth_head import BoundedInverseDepth


class ResNetDepth(nn.Module):
    """The module's network: IR ``(N,1,H,W)`` -> depth ``(N,1,H,W) float32 m`` in ``[min_depth, max_depth]``."""

    def __init__(self, width: float, min_depth: float, max_depth: float):
        super().__init__()
        self.encoder = ResNetEncoder(width)
        enc = self.encoder.channels
        dec = [scaled(n, width) for n in (16, 32, 64, 128, 256)]
        self.upconv_a = nn.ModuleList()
        self.upconv_b = nn.ModuleList()
        for i in range(4, -1, -1):
            in_a = enc[4] if i == 4 else dec[i + 1]
            self.upconv_a.append(ConvELU(in_a, dec[i]))
            in_b = dec[i] + (enc[i - 1] if i > 0 else 0)
            self.upconv_b.append(ConvELU(in_b, dec[i]))
        self.to_logits = nn.Conv2d(dec[0], 1, 3, padding=1, padding_mode="reflect")
        self.head = BoundedInverseDepth(min_depth, max_depth)
        self.head.init_bias(self.to_logits)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """``x (N,1,H,W) float32`` normalized IR (H, W multiples of 32) -> depth ``(N,1,H,W) float32 m``."""
        feats = self.encoder(x)
        y = feats[4]
        for step, i in enumerate(range(4, -1, -1)):
            y = upsample2(self.upconv_a[step](y))
            if i > 0:
                y = torch.cat([y, feats[i - 1]], dim=1)
            y = self.upconv_b[step](y)
        return self.head(self.to_logits(y))
