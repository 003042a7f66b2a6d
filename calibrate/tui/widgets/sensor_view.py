"""Live sensor view: IR amplitude and ToF depth previews drawn with half-block characters."""

from __future__ import annotations

import numpy as np
from rich.segment import Segment
from textual.containers import Horizontal, Vertical
from textual.geometry import Region, Size
from textual.strip import Strip
from textual.widget import Widget
from textual.widgets import Static

from calibrate.tui.halfblock import DEPTH, GREY, Colormap, Scaled, fit_cells, halfblock_rows, scale_image


class HalfBlockImage(Widget):
    """One image scaled to fit the widget (square pixels, centred), redrawn when it changes.

    It hands the compositor its cached lines as they are (``render_lines``), its segments passed
    through the app's line filters once each instead of through textual's per-line styling on every
    frame: the widget has no border, padding or text to style, and that pass over its ~30 segments
    per line was most of the cost of a preview update, which a key press arriving with it had to
    wait for (docs/tui.md "Responsiveness").
    """

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
        self._filter_key: tuple | None = None  # (app line filters, background) of ``_filtered``
        self._filtered: dict[Segment, list[Segment]] = {}  # segment -> it through those filters

    def set_image(self, scaled: Scaled | None) -> None:
        """Show an image mapped to colour indices (see ``halfblock.scale_image``)."""
        self.scaled = scaled
        self._strips_for = None
        self.refresh()

    def _build(self, size: Size) -> None:
        """Cache one strip per line for ``size`` (cells), through the app's line filters."""
        style = self.rich_style
        filter_key = (tuple(self.get_line_filters()), self.background_colors[1])
        if filter_key != self._filter_key:
            self._filter_key, self._filtered = filter_key, {}
        self._strips = []
        self._blank = self._filtered_strip([Segment(" " * size.width, style)], size.width)
        self._strips_for = (size.width, size.height)
        if self.scaled is None:
            return
        cols, rows = fit_cells(self.scaled.index.shape, size.width, size.height)
        pad_left = (size.width - cols) // 2
        pad_right = size.width - cols - pad_left
        left = [Segment(" " * pad_left, style)] if pad_left else []
        right = [Segment(" " * pad_right, style)] if pad_right else []
        for segments in halfblock_rows(self.scaled.index, cols, rows, self.colormap):
            self._strips.append(self._filtered_strip(left + segments + right, size.width))

    def _filtered_strip(self, segments: list[Segment], width: int) -> Strip:
        """A strip of ``segments`` through the app's line filters. Each filter maps every segment on its
        own (textual's all do), so each distinct segment (a run of equal cells) is filtered once."""
        filters, background = self._filter_key
        cache = self._filtered
        out: list[Segment] = []
        for segment in segments:
            done = cache.get(segment)
            if done is None:
                done = [segment]
                for line_filter in filters:
                    done = line_filter.apply(done, background)
                if len(cache) >= Colormap.MAX_CACHED_RUNS:
                    cache.clear()
                cache[segment] = done
            out.extend(done)
        return Strip(out, width)

    def render_lines(self, crop: Region) -> list[Strip]:
        """The cached lines in ``crop`` (widget coordinates)."""
        size = self.size
        if self._strips_for != (size.width, size.height):
            self._build(size)
        lines = [self._strips[y] if y < len(self._strips) else self._blank for y in crop.line_range]
        x1, x2 = crop.column_span
        if (x1, x2) != (0, size.width):
            lines = [line.crop(x1, x2) for line in lines]
        return lines


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
        self._shown_ir: np.ndarray | None = None  # the arrays drawn last, as passed to ``show``
        self._shown_depth: np.ndarray | None = None

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
        """Draw new images: ``ir`` (H,W) uint16 amplitude (counts), ``depth_m`` (H,W) float32 m, 0 = invalid.

        None, or the very array drawn last (showing the sensor tab again with no new snapshot), leaves
        that image as it is.
        """
        if ir is not None and ir is not self._shown_ir:
            self._shown_ir = ir
            scaled = scale_image(np.asarray(ir, dtype=np.float32))
            self.ir_image.set_image(scaled)
            self.ir_caption.update(f"IR {scaled.lo:.0f}-{scaled.hi:.0f} counts", layout=False)
        if depth_m is not None and depth_m is not self._shown_depth:
            self._shown_depth = depth_m
            depth = np.asarray(depth_m, dtype=np.float32)
            scaled = scale_image(depth, valid=depth > 0)
            self.depth_image.set_image(scaled)
            # was: "depth 0.0-0.0 mm" for a frame with no valid pixel
            self.depth_caption.update("depth: no valid pixels" if scaled.invalid_fraction == 1.0 else
                                      f"depth {scaled.lo * 1e3:.1f}-{scaled.hi * 1e3:.1f} mm", layout=False)
            self.legend.update(self._legend_text(f" {scaled.invalid_fraction * 100:.0f} %"), layout=False)
