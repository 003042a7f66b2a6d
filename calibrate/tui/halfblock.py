"""Images rendered in a terminal with the upper half-block character "▀".

Each terminal cell shows two image pixels stacked vertically: the foreground colour paints the
upper one, the background colour the lower one, so pixels come out roughly square. Images are
resampled by nearest neighbour (honest for depth: no blending across invalid pixels) and coloured
through a 256-entry lookup table; invalid pixels get their own colour.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from rich.color import Color
from rich.segment import Segment
from rich.style import Style

UPPER_HALF = "\u2580"

#: Anchor colours of the depth colour map (near = warm, far = cool), RGB 0-255, evenly spaced.
_DEPTH_ANCHORS = np.array(
    [
        (122, 4, 3),
        (219, 57, 7),
        (254, 155, 45),
        (210, 233, 53),
        (100, 253, 106),
        (27, 207, 212),
        (62, 125, 245),
        (48, 18, 59),
    ],
    dtype=np.float64,
)


def _interpolated_lut(anchors: np.ndarray) -> np.ndarray:
    """(256,3) uint8 lookup table interpolating the anchor colours linearly."""
    x = np.linspace(0.0, 1.0, len(anchors))
    t = np.linspace(0.0, 1.0, 256)
    return np.stack([np.interp(t, x, anchors[:, c]) for c in range(3)], axis=1).round().astype(np.uint8)


INVALID_RGB = (70, 0, 70)  # dark magenta: no data (ToF dropout, housing)
#: Light grey: no depth in the depth map, unlike any of its colours (its far end, (48, 18, 59), was 31
#: RGB units from the dark magenta: the farthest membrane read as a dropout).
DEPTH_INVALID_RGB = (160, 160, 160)


class Colormap:
    """A 256-entry colour table plus the colour of invalid pixels, with rich styles cached per
    (upper, lower) cell colour pair (index 256 = invalid), and the segments of runs of equal cells."""

    #: Cached runs at most; the cache starts again when full (a 39x27-cell image uses ~800).
    MAX_CACHED_RUNS = 50_000

    def __init__(self, lut: np.ndarray, invalid_rgb: tuple[int, int, int] = INVALID_RGB):
        self.lut = lut  # (256,3) uint8 RGB
        self._colors = [Color.from_rgb(*map(int, rgb)) for rgb in lut] + [Color.from_rgb(*invalid_rgb)]
        self._styles: dict[tuple[int, int], Style] = {}
        self._runs: dict[tuple[int, int, int], Segment] = {}

    def run(self, upper: int, lower: int, cells: int) -> Segment:
        """The segment of ``cells`` equal half-block cells (upper, lower pixel colour indices)."""
        key = (upper, lower, cells)
        segment = self._runs.get(key)
        if segment is None:
            if len(self._runs) >= self.MAX_CACHED_RUNS:
                self._runs.clear()
            segment = self._runs[key] = Segment(UPPER_HALF * cells, self.style(upper, lower))
        return segment

    def style(self, upper: int, lower: int) -> Style:
        """Style of a half-block cell: foreground = upper pixel, background = lower pixel."""
        key = (upper, lower)
        style = self._styles.get(key)
        if style is None:
            style = Style(color=self._colors[upper], bgcolor=self._colors[lower])
            self._styles[key] = style
        return style


GREY = Colormap(_interpolated_lut(np.array([(0, 0, 0), (255, 255, 255)], dtype=np.float64)))
DEPTH = Colormap(_interpolated_lut(_DEPTH_ANCHORS), DEPTH_INVALID_RGB)


@dataclass
class Scaled:
    """An image mapped to lookup-table indices, ready to draw.

    ``index``: (H,W) int16, 0..255 into the colour table, -1 where the pixel is invalid;
    ``lo``/``hi``: the values mapped to index 0 and 255 (the image's unit).
    """

    index: np.ndarray
    lo: float
    hi: float
    invalid_fraction: float


def scale_image(values: np.ndarray, valid: np.ndarray | None = None, percentiles=(1.0, 99.0)) -> Scaled:
    """Auto-contrast ``values`` (H,W) to table indices over the given percentiles of valid pixels."""
    values = np.asarray(values, dtype=np.float32)
    if valid is None:
        valid = np.isfinite(values)
    else:
        valid = valid & np.isfinite(values)
    index = np.full(values.shape, -1, dtype=np.int16)
    if not valid.any():
        return Scaled(index, 0.0, 0.0, 1.0)
    lo, hi = np.percentile(values[valid], percentiles)
    span = float(hi - lo) if hi > lo else 1.0
    scaled = np.clip((values - lo) / span, 0.0, 1.0) * 255.0
    index[valid] = scaled[valid].round().astype(np.int16)
    return Scaled(index, float(lo), float(hi), float(1.0 - valid.mean()))


def fit_cells(image_hw: tuple[int, int], box_cols: int, box_rows: int) -> tuple[int, int]:
    """Largest (cols, rows) of cells showing an (H,W) image with square pixels inside a box."""
    h, w = image_hw
    if box_cols <= 0 or box_rows <= 0 or h <= 0 or w <= 0:
        return 0, 0
    scale = min(box_cols / w, 2 * box_rows / h)
    cols = max(1, int(w * scale))
    rows = max(1, int(h * scale) // 2)
    return min(cols, box_cols), min(rows, box_rows)


def halfblock_rows(index: np.ndarray, cols: int, rows: int, colormap: Colormap) -> list[list[Segment]]:
    """Segments for ``rows`` terminal lines of ``cols`` cells showing ``index`` (H,W) int16.

    ``index`` holds colour-table indices 0..255, or -1 for invalid pixels. Runs of equal cells
    are merged into one segment. Colours are quantized to 64 levels (plenty for a terminal; keeps
    at most 65^2 cached styles per colour map).
    """
    if cols <= 0 or rows <= 0:
        return []
    h, w = index.shape
    ys = np.minimum(((np.arange(2 * rows) + 0.5) * h / (2 * rows)).astype(np.int64), h - 1)
    xs = np.minimum(((np.arange(cols) + 0.5) * w / cols).astype(np.int64), w - 1)
    sampled = index[np.ix_(ys, xs)].astype(np.int64) & ~3  # 64 levels: bounds the style cache
    sampled[sampled < 0] = 256  # the invalid colour sits after the table
    run = colormap.run
    lines: list[list[Segment]] = []
    for r in range(rows):
        upper, lower = sampled[2 * r].tolist(), sampled[2 * r + 1].tolist()
        segments: list[Segment] = []
        run_start = 0
        for c in range(1, cols + 1):
            if c == cols or upper[c] != upper[run_start] or lower[c] != lower[run_start]:
                segments.append(run(upper[run_start], lower[run_start], c - run_start))
                run_start = c
        lines.append(segments)
    return lines
