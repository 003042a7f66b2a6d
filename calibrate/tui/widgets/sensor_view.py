"""Live sensor view: IR amplitude and ToF depth previews drawn with half-block characters."""

from __future__ import annotations

import numpy as np
from rich.segment import Segment
from textual.containers import Horizontal, Vertical
from textual.geometry import Size
from textual.strip import Strip
from textual.widget import Widget
from textual.widgets import Static

from calibrate.tui.halfblock import DEPTH, GREY, Colormap, Scaled, fit_cells, halfblock_rows, scale_image


class HalfBlockImage(Widget):
    """One image scaled to fit the widget (square pixels, centred), redrawn when it changes."""

    DEFAULT_CSS = """
    HalfBlockImage { width: 1fr; height: 1fr; }
    """

    def __init__(self, colormap: Colormap, **kwargs) -> None:
        super().__init__(**kwargs)
        self.colormap = colormap
        self.scaled: Scaled | None = None
        self._strips: list[Strip] = []
        self._strips_for: tuple[int, int] | None = None
        self._blank = Strip.blank(0)

    def set_image(self, scaled: Scaled | None) -> None:
        """Show an image mapped to colour indices (see ``halfblock.scale_image``)."""
        self.scaled = scaled
        self._strips_for = None
        self.refresh()

    def _build(self, size: Size) -> None:
        """Cache one strip per line for ``size`` (cells)."""
        style = self.rich_style
        self._strips = []
        self._blank = Strip.blank(size.width, style)
        self._strips_for = (size.width, size.height)
        if self.scaled is None:
            return
        cols, rows = fit_cells(self.scaled.index.shape, size.width, size.height)
        pad = (size.width - cols) // 2
        left = [Segment(" " * pad, style)] if pad else []
        for segments in halfblock_rows(self.scaled.index, cols, rows, self.colormap):
            self._strips.append(Strip(left + segments, pad + cols).extend_cell_length(size.width, style))

    def render_line(self, y: int) -> Strip:
        size = self.size
        if self._strips_for != (size.width, size.height):
            self._build(size)
        return self._strips[y] if y < len(self._strips) else self._blank


class SensorView(Vertical):
    """IR and depth with their scales, fed with the latest snapshot's images: side by side, or
    stacked when ``compact`` (the always-visible preview under the bench panel)."""

    def __init__(self, compact: bool = False, **kwargs) -> None:
        super().__init__(**kwargs)
        self.border_title = "Live sensor" if compact else "Sensor"
        self.set_class(compact, "-compact")
        self.ir_caption = Static("IR amplitude: no frame yet", classes="caption")
        self.ir_image = HalfBlockImage(GREY)
        self.depth_caption = Static("ToF depth: no frame yet", classes="caption")
        self.depth_image = HalfBlockImage(DEPTH)
        self.legend = Static(self._legend_text(), classes="sensor-legend")

    def compose(self):
        with Horizontal(classes="sensor-images"):
            with Vertical(classes="sensor-pane"):
                yield self.ir_caption
                yield self.ir_image
            with Vertical(classes="sensor-pane"):
                yield self.depth_caption
                yield self.depth_image
        yield self.legend

    @staticmethod
    def _legend_text(no_data: str = "") -> str:
        return f"[#db3907]near[/] → [#3e7df5]far[/]  [on #460046]  [/] no data{no_data}"

    def show(self, ir: np.ndarray | None, depth_m: np.ndarray | None) -> None:
        """Draw new images: ``ir`` (H,W) uint16 amplitude, ``depth_m`` (H,W) float32 m, 0 = invalid."""
        if ir is not None:
            scaled = scale_image(np.asarray(ir, dtype=np.float32))
            self.ir_image.set_image(scaled)
            self.ir_caption.update(f"IR {scaled.lo:.0f}-{scaled.hi:.0f}", layout=False)
        if depth_m is not None:
            depth = np.asarray(depth_m, dtype=np.float32)
            scaled = scale_image(depth, valid=depth > 0)
            self.depth_image.set_image(scaled)
            self.depth_caption.update(f"depth {scaled.lo * 1e3:.1f}-{scaled.hi * 1e3:.1f} mm", layout=False)
            self.legend.update(self._legend_text(f" {scaled.invalid_fraction * 100:.0f} %"), layout=False)
