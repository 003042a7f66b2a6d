"""Bounded inverse-depth output head shared by every network.

A network ends in one logit channel ``x``; the head maps it to metric depth through a sigmoid
over inverse depth, clamped to the range:

``depth = clamp(1 / (1/max_depth + (1/min_depth - 1/max_depth) * sigmoid(x)), min_depth, max_depth)``.

Any output lies in the closed range ``[min_depth, max_depth]`` as float32 holds its bounds
(0.04 m is 0.0399999991, 0.12 m is 0.1199999973), and reaches a bound where the sigmoid saturates
(|x| above about 17). Without the clamp, float32 rounding put such outputs one unit in the last
place outside (0.12000000476 for 0.12).
"""

from __future__ import annotations

import math

import torch
from torch import nn


class BoundedInverseDepth(nn.Module):
    """Logits ``(N,1,H,W)`` -> depth ``(N,1,H,W) float32 m`` in ``[min_depth, max_depth]`` (float32 bounds)."""

    def __init__(self, min_depth: float, max_depth: float):
        super().__init__()
        if not 0.0 < min_depth < max_depth:
            raise ValueError(f"bad depth range ({min_depth}, {max_depth})")
        self.min_depth = float(min_depth)
        self.max_depth = float(max_depth)

    def logit(self, depth: float) -> float:
        """The logit whose output is ``depth`` (m); e.g. to initialize the last layer's bias."""
        inv_min, inv_max = 1.0 / self.min_depth, 1.0 / self.max_depth
        p = (1.0 / depth - inv_max) / (inv_min - inv_max)
        return math.log(p / (1.0 - p))

    def init_bias(self, conv: nn.Conv2d, depth: float | None = None) -> None:
        """Make ``conv`` (the logit layer) start at ``depth`` (m; default the middle of the range)."""
        depth = 0.5 * (self.min_depth + self.max_depth) if depth is None else depth
        depth = min(max(depth, 1.01 * self.min_depth), 0.99 * self.max_depth)
        nn.init.constant_(conv.bias, self.logit(depth))

    def forward(self, logits: torch.Tensor) -> torch.Tensor:
        inv_min, inv_max = 1.0 / self.min_depth, 1.0 / self.max_depth
        return (1.0 / (inv_max + (inv_min - inv_max) * torch.sigmoid(logits))).clamp(self.min_depth, self.max_depth)
