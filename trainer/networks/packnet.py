"""``packnet``: encoder-decoder with packing / unpacking blocks, after PackNet-01.

Packing folds space into channels without losing detail (space-to-depth), mixes the folded
channels with a 3D convolution and compresses them with a 2D convolution; unpacking expands
channels with a 2D and a 3D convolution and unfolds them back into space (depth-to-space).
Sized for a CPU: ``width`` scales every channel count (1.0 = PackNet-01's 64..512 ladder).
Input ``(N,1,H,W)`` normalized IR (H, W multiples of 32), output ``(N,1,H,W) float32 m``.
"""

from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional as F

from trainer.networks.blocks import scaled
from trainer.networks.depth_head import BoundedInverseDepth

#: Number of feature "slices" the 3D convolutions of the packing blocks produce.
PACKING_DEPTH = 4


def group_norm(channels: int) -> nn.GroupNorm:
    """GroupNorm over ``channels`` in up to 16 groups of at least 4 channels: the largest number of
    groups within that which divides ``channels`` (a width such as 0.3 gives 76 channels: 4 groups
    of 19, where 16 would not divide them)."""
    groups = max(g for g in range(1, max(min(16, channels // 4), 1) + 1) if channels % g == 0)
    return nn.GroupNorm(groups, channels)


class Conv2D(nn.Module):
    """Conv + GroupNorm + ELU (PackNet's Conv2D unit): ``(N,Cin,H,W) -> (N,Cout,H/stride,W/stride)``."""

    def __init__(self, in_channels: int, out_channels: int, kernel: int = 3, stride: int = 1):
        super().__init__()
        self.conv = nn.Conv2d(in_channels, out_channels, kernel, stride, kernel // 2)
        self.norm = group_norm(out_channels)
        self.act = nn.ELU(inplace=True)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.act(self.norm(self.conv(x)))


class ResidualBlock(nn.Module):
    """Two Conv2D units with a projected shortcut: ``(N,Cin,H,W) -> (N,Cout,H/stride,W/stride)``."""

    def __init__(self, in_channels: int, out_channels: int, stride: int):
        super().__init__()
        self.conv1 = Conv2D(in_channels, out_channels, 3, stride)
        self.conv2 = nn.Conv2d(out_channels, out_channels, 3, 1, 1)
        self.norm = group_norm(out_channels)
        self.shortcut = nn.Conv2d(in_channels, out_channels, 1, stride)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.elu(self.norm(self.conv2(self.conv1(x)) + self.shortcut(x)))


class Packing(nn.Module):
    """``(N,C,H,W) -> (N,C,H/2,W/2)``: space-to-depth, 3D conv over the folded channels, 2D conv."""

    def __init__(self, channels: int):
        super().__init__()
        self.conv3d = nn.Conv3d(1, PACKING_DEPTH, 3, padding=1)
        self.conv = Conv2D(channels * 4 * PACKING_DEPTH, channels, 3)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = F.pixel_unshuffle(x, 2)
        n, c, h, w = x.shape
        x = self.conv3d(x.unsqueeze(1)).reshape(n, c * PACKING_DEPTH, h, w)
        return self.conv(x)


class Unpacking(nn.Module):
    """``(N,Cin,H,W) -> (N,Cout,2H,2W)``: 2D conv, 3D conv over the channels, depth-to-space."""

    def __init__(self, in_channels: int, out_channels: int):
        super().__init__()
        self.conv = Conv2D(in_channels, out_channels * 4 // PACKING_DEPTH, 3)
        self.conv3d = nn.Conv3d(1, PACKING_DEPTH, 3, padding=1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = self.conv(x)
        n, c, h, w = x.shape
        x = self.conv3d(x.unsqueeze(1)).reshape(n, c * PACKING_DEPTH, h, w)
        return F.pixel_shuffle(x, 2)


class PackNetDepth(nn.Module):
    """The module's network: IR ``(N,1,H,W)`` -> depth ``(N,1,H,W) float32 m`` in ``[min_depth, max_depth]``."""

    def __init__(self, width: float, min_depth: float, max_depth: float):
        super().__init__()
        c = [scaled(n, width, minimum=8) for n in (32, 64, 64, 128, 256, 512)]
        self.pre = Conv2D(1, c[0], 5)
        self.pack = nn.ModuleList()
        self.enc = nn.ModuleList()
        for i in range(5):
            self.pack.append(Packing(c[i]))
            self.enc.append(ResidualBlock(c[i], c[i + 1], 1))
        self.unpack = nn.ModuleList()
        self.dec = nn.ModuleList()
        for i in range(5, 0, -1):
            self.unpack.append(Unpacking(c[i], c[i - 1]))
            self.dec.append(Conv2D(c[i - 1] * 2, c[i - 1], 3))
        self.to_logits = nn.Conv2d(c[0], 1, 3, padding=1)
        self.head = BoundedInverseDepth(min_depth, max_depth)
        self.head.init_bias(self.to_logits)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """``x (N,1,H,W) float32`` normalized IR (H, W multiples of 32) -> depth ``(N,1,H,W) float32 m``."""
        y = self.pre(x)
        skips = [y]
        for pack, enc in zip(self.pack, self.enc):
            y = enc(pack(y))
            skips.append(y)
        for step, (unpack, dec) in enumerate(zip(self.unpack, self.dec)):
            y = unpack(y)
            y = dec(torch.cat([y, skips[4 - step]], dim=1))
        return self.head(self.to_logits(y))
