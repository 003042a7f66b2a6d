"""Depth networks, one per module, built by architecture name.

Every network maps normalized IR ``(N,1,H,W) float32`` (H, W multiples of 32) to metric depth
``(N,1,H,W) float32 m`` in ``[min_depth, max_depth]`` (the bounds as float32 holds them: 0.04 m is
0.0399999991), and ends in a logit layer ``to_logits`` followed by the ``head``
(``BoundedInverseDepth``).
"""

from __future__ import annotations

import math

from torch import nn

from collect.errors import InputError
from trainer.networks.bts import BTSDepth
from trainer.networks.packnet import PackNetDepth
from trainer.networks.resnet import ResNetDepth

#: Architecture name -> network class ``cls(width, min_depth, max_depth)``.
ARCHITECTURES: dict[str, type[nn.Module]] = {
    "resnet": ResNetDepth,
    "packnet": PackNetDepth,
    "bts": BTSDepth,
}

#: Input height and width must be multiples of this (the encoders downsample 5 times).
INPUT_MULTIPLE = 32


#: Widest channel width multiplier accepted (the defaults are 0.25-0.375; 4 is ~100x their weights).
MAX_WIDTH = 4.0


def check_width(width: float) -> None:
    """Raise ``InputError`` unless ``width`` is a channel width multiplier in (0, ``MAX_WIDTH``]."""
    if not (math.isfinite(width) and 0 < width <= MAX_WIDTH):
        raise InputError(f"network width must be a number in (0, {MAX_WIDTH:g}], got {width}")


def build_network(arch: str, width: float, min_depth: float, max_depth: float) -> nn.Module:
    """A freshly initialized network of architecture ``arch`` (one of ``ARCHITECTURES``)."""
    if arch not in ARCHITECTURES:
        raise InputError(f"unknown architecture {arch!r}; choose one of {', '.join(ARCHITECTURES)}")
    check_width(width)
    return ARCHITECTURES[arch](width, min_depth, max_depth)


def set_initial_depth(network: nn.Module, depth: float) -> None:
    """Make a fresh ``network`` start by predicting ``depth`` (m) everywhere (bias of its logit layer)."""
    network.head.init_bias(network.to_logits, depth)
