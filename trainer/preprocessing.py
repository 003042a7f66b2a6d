"""The mapping between sensor frames and network tensors: IR normalization and input geometry.

* ``IRNormalization``: ``x = (ln(1 + ir) - mean) / std`` on the raw uint16 amplitude. The log
  makes a sensor's emitter power a plain offset, which the per-sensor ``mean`` absorbs.
* ``InputGeometry``: a native ``(H,W)`` frame is scaled by ``scale`` (1.0 when it already fits:
  the default 224 x 172 sensor frame goes into a 224 x 224 input with no resampling) and
  centred with zero padding in the ``(input_height, input_width)`` network input; the network's
  output is cropped (and scaled back) to the native frame. Pixels stay where the intrinsics
  say they are, up to the scale and the offset.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import cv2
import numpy as np

from collect.errors import InputError

#: Default network input (height, width), as in the paper.
DEFAULT_INPUT_SIZE = (224, 224)
#: Largest IR amplitude: the sensor's uint16 range is [0, MAX_IR].
MAX_IR = 65535
#: ln(1 + MAX_IR): ln(1 + ir) of a uint16 amplitude, hence an ``IRNormalization`` mean, lies in
#: [0, this], and its std is at most this (ln-amplitude units).
MAX_LOG_IR = math.log1p(MAX_IR)
#: Smallest ``IRNormalization`` std (ln-amplitude units): ``fit`` clamps to it, so that frames
#: of one flat level do not divide by ~0.
MIN_IR_STD = 1e-3


@dataclass(frozen=True)
class IRNormalization:
    """``x = (ln(1 + ir) - mean) / std``; ``mean`` and ``std`` are in ln-amplitude units."""

    #: Its name in a model's metadata (``to_dict``'s ``kind``).
    KIND = "log1p-standardize"

    mean: float
    std: float

    @classmethod
    def fit(cls, ir: np.ndarray, max_samples: int = 2_000_000) -> "IRNormalization":
        """Statistics of ``ir`` ``(N,H,W) uint16``: of every pixel, or of ``max_samples`` drawn at random
        (seeded) where there are more. Was every k-th pixel: where k shared a factor with the frame's
        width, those lay in a few columns (at 11650 frames of 224 px width, all in column 0, the
        housing's edge: mean 6.85 / std 0.99 instead of 8.70 / 1.51)."""
        flat = np.asarray(ir).reshape(-1)
        if flat.size > max_samples:
            flat = flat[np.random.default_rng(0).integers(0, flat.size, max_samples)]
        logs = np.log1p(flat.astype(np.float64))
        return cls(mean=float(logs.mean()), std=float(max(logs.std(), MIN_IR_STD)))

    def apply(self, ir: np.ndarray) -> np.ndarray:
        """``ir`` ``(...,H,W) uint16`` -> ``(...,H,W) float32`` normalized."""
        return ((np.log1p(np.asarray(ir, dtype=np.float32)) - self.mean) / self.std).astype(np.float32)

    def to_dict(self) -> dict:
        return {"kind": self.KIND, **asdict(self)}

    @classmethod
    def from_dict(cls, data: dict) -> "IRNormalization":
        """From ``to_dict``'s output, as checked by ``trainer.model_dir.check_metadata``."""
        return cls(mean=float(data["mean"]), std=float(data["std"]))


@dataclass(frozen=True)
class InputGeometry:
    """Native sensor frame ``(native_height, native_width)`` <-> network input ``(input_height, input_width)``."""

    native_height: int
    native_width: int
    input_height: int
    input_width: int

    @property
    def scale(self) -> float:
        """Resampling factor native -> input (1.0: none)."""
        return min(1.0, self.input_height / self.native_height, self.input_width / self.native_width)

    @property
    def content_size(self) -> tuple[int, int]:
        """(height, width) of the native frame inside the input, after scaling."""
        s = self.scale
        return int(round(self.native_height * s)), int(round(self.native_width * s))

    @property
    def offset(self) -> tuple[int, int]:
        """(top, left) padding of the frame inside the input."""
        h, w = self.content_size
        return (self.input_height - h) // 2, (self.input_width - w) // 2

    def to_input(self, frames: np.ndarray, nearest: bool = False, fill: float = 0.0) -> np.ndarray:
        """``(N,H,W)`` native frames -> ``(N,input_height,input_width)`` same dtype, padded with ``fill``.

        ``nearest`` resamples (when ``scale < 1``) without mixing values: for depth and masks.
        """
        frames = np.asarray(frames)
        if frames.shape[-2:] != (self.native_height, self.native_width):
            raise InputError(
                f"frame size {frames.shape[-1]}x{frames.shape[-2]} does not match the model's sensor "
                f"size {self.native_width}x{self.native_height}"
            )
        h, w = self.content_size
        top, left = self.offset
        out = np.full(frames.shape[:-2] + (self.input_height, self.input_width), fill, dtype=frames.dtype)
        interp = cv2.INTER_NEAREST if nearest else cv2.INTER_AREA
        for idx in np.ndindex(frames.shape[:-2]):
            img = frames[idx]
            if (h, w) != img.shape:
                img = cv2.resize(img, (w, h), interpolation=interp)
            out[idx][top : top + h, left : left + w] = img
        return out

    def to_native(self, maps: np.ndarray) -> np.ndarray:
        """``(N,input_height,input_width)`` network outputs -> ``(N,H,W)`` native frames (crop, rescale)."""
        h, w = self.content_size
        top, left = self.offset
        crop = maps[..., top : top + h, left : left + w]
        if (h, w) == (self.native_height, self.native_width):
            return np.ascontiguousarray(crop)
        out = np.empty(maps.shape[:-2] + (self.native_height, self.native_width), dtype=maps.dtype)
        for idx in np.ndindex(maps.shape[:-2]):
            out[idx] = cv2.resize(crop[idx], (self.native_width, self.native_height), interpolation=cv2.INTER_LINEAR)
        return out

    def to_dict(self) -> dict:
        return {
            **asdict(self),
            "scale": self.scale,
            "offset_top_left": list(self.offset),
            "method": "scale to fit (area), centre, zero-pad" if self.scale < 1.0 else "centre, zero-pad",
        }

    @classmethod
    def from_dict(cls, data: dict) -> "InputGeometry":
        """From ``to_dict``'s output, as checked by ``trainer.model_dir.check_metadata``."""
        return cls(
            native_height=int(data["native_height"]),
            native_width=int(data["native_width"]),
            input_height=int(data["input_height"]),
            input_width=int(data["input_width"]),
        )
