"""``bts``: encoder + decoder with local planar guidance (LPG) layers, after BTS (Lee et al.).

At strides 8, 4 and 2 the decoder predicts, per cell, a local plane (unit normal from two
angles, and a distance) and expands it to a full-resolution depth estimate with the LPG
equation ``d(u,v) = n4 / (n1 u + n2 v + n3)``; the three estimates guide the final
full-resolution prediction. Encoder: the ResNet-18-style one of ``resnet`` (the paper's BTS used
a DenseNet; a ResNet keeps it CPU-sized). ``width`` scales every channel count.
Input ``(N,1,H,W)`` normalized IR (H, W multiples of 32), output ``(N,1,H,W) float32 m``.
"""

from __future__ import annotations

import math

import torch
from torch import nn
from torch.nn import functional as F

from trainer.networks.blocks import ConvELU, ResNetEncoder, scaled, upsample2
from trainer.networks.depth_head import BoundedInverseDepth

#: Largest tilt of an LPG plane normal from the optical axis; keeps the LPG denominator > 0.2.
MAX_PLANE_TILT = math.pi / 4


class LocalPlanarGuidance(nn.Module):
    """Features ``(N,C,H/k,W/k)`` -> relative depth ``(N,1,H,W)`` from one plane per k x k cell."""

    def __init__(self, in_channels: int, cell: int):
        super().__init__()
        self.cell = cell
        self.to_plane = nn.Conv2d(in_channels, 3, 1)

    def forward(self, feats: torch.Tensor) -> torch.Tensor:
        k = self.cell
        params = torch.sigmoid(self.to_plane(feats))
        theta = params[:, 0:1] * MAX_PLANE_TILT
        phi = params[:, 1:2] * (2.0 * math.pi)
        dist = params[:, 2:3]
        plane = torch.cat(
            [torch.sin(theta) * torch.cos(phi), torch.sin(theta) * torch.sin(phi), torch.cos(theta), dist], dim=1
        )
        plane = F.interpolate(plane, scale_factor=float(k), mode="nearest")
        h, w = plane.shape[-2:]
        offsets = (torch.arange(k, dtype=plane.dtype, device=plane.device) - (k - 1) / 2.0) / k
        u = offsets.repeat(w // k).view(1, 1, 1, w)
        v = offsets.repeat(h // k).view(1, 1, h, 1)
        return plane[:, 3:4] / (plane[:, 0:1] * u + plane[:, 1:2] * v + plane[:, 2:3])


class BTSDepth(nn.Module):
    """The module's network: IR ``(N,1,H,W)`` -> depth ``(N,1,H,W) float32 m`` in ``[min_depth, max_depth]``."""

    def __init__(self, width: float, min_depth: float, max_depth: float):
        super().__init__()
        self.encoder = ResNetEncoder(width)
        enc = self.encoder.channels
        d = [scaled(n, width) for n in (16, 32, 64, 128, 256)]
        self.up16 = ConvELU(enc[4], d[4])
        self.conv16 = ConvELU(d[4] + enc[3], d[4])
        self.context = nn.ModuleList(
            nn.Conv2d(d[4], d[4] // 2, 3, padding=r, dilation=r) for r in (1, 3, 6)
        )
        self.fuse16 = ConvELU(d[4] + 3 * (d[4] // 2), d[3])
        self.up8 = ConvELU(d[3], d[2])
        self.conv8 = ConvELU(d[2] + enc[2], d[2])
        self.lpg8 = LocalPlanarGuidance(d[2], 8)
        self.up4 = ConvELU(d[2], d[1])
        self.conv4 = ConvELU(d[1] + enc[1] + 1, d[1])
        self.lpg4 = LocalPlanarGuidance(d[1], 4)
        self.up2 = ConvELU(d[1], d[0])
        self.conv2 = ConvELU(d[0] + enc[0] + 1, d[0])
        self.lpg2 = LocalPlanarGuidance(d[0], 2)
        self.up1 = ConvELU(d[0], d[0])
        self.conv1 = ConvELU(d[0] + 3, d[0])
        self.to_logits = nn.Conv2d(d[0], 1, 3, padding=1, padding_mode="reflect")
        self.head = BoundedInverseDepth(min_depth, max_depth)
        self.head.init_bias(self.to_logits)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """``x (N,1,H,W) float32`` normalized IR (H, W multiples of 32) -> depth ``(N,1,H,W) float32 m``."""
        f = self.encoder(x)
        y = self.conv16(torch.cat([upsample2(self.up16(f[4])), f[3]], dim=1))
        y = self.fuse16(torch.cat([y] + [F.elu(c(y)) for c in self.context], dim=1))
        y = self.conv8(torch.cat([upsample2(self.up8(y)), f[2]], dim=1))
        lpg8 = self.lpg8(y)
        y = upsample2(self.up4(y))
        y = self.conv4(torch.cat([y, f[1], F.interpolate(lpg8, size=y.shape[-2:], mode="nearest")], dim=1))
        lpg4 = self.lpg4(y)
        y = upsample2(self.up2(y))
        y = self.conv2(torch.cat([y, f[0], F.interpolate(lpg4, size=y.shape[-2:], mode="nearest")], dim=1))
        lpg2 = self.lpg2(y)
        y = upsample2(self.up1(y))
        y = self.conv1(torch.cat([y, lpg8, lpg4, lpg2], dim=1))
        return self.head(self.to_logits(y))
