"""Building blocks shared by the depth networks (plain torch)."""

from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional as F


def scaled(channels: int, width: float, minimum: int = 4) -> int:
    """``channels`` scaled by the width multiplier, rounded to a multiple of 4 (at least ``minimum``)."""
    return max(minimum, int(round(channels * width / 4.0)) * 4)


class ConvELU(nn.Module):
    """3x3 convolution (reflection padded) + ELU, the monodepth2 decoder unit: ``(N,Cin,H,W) -> (N,Cout,H,W)``."""

    def __init__(self, in_channels: int, out_channels: int):
        super().__init__()
        self.conv = nn.Conv2d(in_channels, out_channels, 3, padding=1, padding_mode="reflect")
        self.act = nn.ELU(inplace=True)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.act(self.conv(x))


class BasicBlock(nn.Module):
    """ResNet basic block: two 3x3 conv + BN with an identity (or 1x1 projection) shortcut;
    ``(N,Cin,H,W) -> (N,Cout,H/stride,W/stride)``."""

    def __init__(self, in_channels: int, out_channels: int, stride: int = 1):
        super().__init__()
        self.conv1 = nn.Conv2d(in_channels, out_channels, 3, stride, 1, bias=False)
        self.bn1 = nn.BatchNorm2d(out_channels)
        self.conv2 = nn.Conv2d(out_channels, out_channels, 3, 1, 1, bias=False)
        self.bn2 = nn.BatchNorm2d(out_channels)
        self.shortcut: nn.Module = nn.Identity()
        if stride != 1 or in_channels != out_channels:
            self.shortcut = nn.Sequential(
                nn.Conv2d(in_channels, out_channels, 1, stride, bias=False), nn.BatchNorm2d(out_channels)
            )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        out = F.relu(self.bn1(self.conv1(x)), inplace=True)
        out = self.bn2(self.conv2(out))
        return F.relu(out + self.shortcut(x), inplace=True)


class ResNetEncoder(nn.Module):
    """ResNet-18-style encoder for 1-channel input.

    ``(N,1,H,W)`` -> list of 5 feature maps at strides 2, 4, 8, 16, 32 with
    ``self.channels`` channels (64, 64, 128, 256, 512 times ``width``). H and W must be
    multiples of 32.
    """

    def __init__(self, width: float = 1.0, in_channels: int = 1):
        super().__init__()
        c = [scaled(n, width) for n in (64, 64, 128, 256, 512)]
        self.channels = c
        self.stem = nn.Sequential(
            nn.Conv2d(in_channels, c[0], 7, 2, 3, bias=False), nn.BatchNorm2d(c[0]), nn.ReLU(inplace=True)
        )
        self.pool = nn.MaxPool2d(3, 2, 1)
        self.layer1 = nn.Sequential(BasicBlock(c[0], c[1]), BasicBlock(c[1], c[1]))
        self.layer2 = nn.Sequential(BasicBlock(c[1], c[2], 2), BasicBlock(c[2], c[2]))
        self.layer3 = nn.Sequential(BasicBlock(c[2], c[3], 2), BasicBlock(c[3], c[3]))
        self.layer4 = nn.Sequential(BasicBlock(c[3], c[4], 2), BasicBlock(c[4], c[4]))

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        f0 = self.stem(x)
        f1 = self.layer1(self.pool(f0))
        f2 = self.layer2(f1)
        f3 = self.layer3(f2)
        f4 = self.layer4(f3)
        return [f0, f1, f2, f3, f4]


def upsample2(x: torch.Tensor) -> torch.Tensor:
    """Nearest-neighbour 2x upsampling ``(N,C,H,W) -> (N,C,2H,2W)``."""
    return F.interpolate(x, scale_factor=2.0, mode="nearest")
