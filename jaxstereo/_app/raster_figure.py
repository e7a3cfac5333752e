"""A figure drawn straight onto a raster with Pillow: the survey preview every `reconstruct` writes.

A fresh `jaxstereo reconstruct` draws one figure, its survey's preview. Drawn by matplotlib, importing it (0.35
CPU-s in a process that has numpy) and laying out and drawing its axes (0.26-0.38 CPU-s) were a sixth of the
command's CPU time, on a 2-core machine that the command keeps busy. Drawn here, a preview of the POV-Ray flume's
1.2 million points takes 0.11 s (its PNG's encoding a third of that), and the command on that flume's 1728x1152 pair
took a median 1.73 s against 1.97 s with matplotlib's (10 alternated runs each; docs/speed.md, round 70). It has what
the matplotlib figure had: a title, image panels in framed axes with ticks at round values and their labels, axis
labels, a colour bar and a legend, in DejaVu Sans (the font file matplotlib ships, found without importing
matplotlib; Pillow's own font where it is missing). Every other figure of the project is matplotlib's.

Pixel coordinates run right and down from the figure's top-left corner. A panel's data `extent` is
`(left, right, bottom, top)` in data units, as matplotlib's `imshow` takes it: an image whose rows run down the
data's y axis (pixel rows, v) has `bottom > top`.
"""

from __future__ import annotations

import functools
import importlib.util
import io
import math
import os
from typing import NamedTuple

import numpy as np
from PIL import Image, ImageDraw, ImageFont

from .plots import PNG_COMPRESSION

INK = (0, 0, 0)
TICK_PX = 5  # tick marks' length, outward


@functools.cache
def viridis() -> np.ndarray:
    """matplotlib's viridis colour map, (256, 3) uint8 RGB (OpenCV's copy of it: the same 256 colours)."""
    import cv2

    return np.ascontiguousarray(cv2.applyColorMap(np.arange(256, dtype=np.uint8)[:, None],
                                                  cv2.COLORMAP_VIRIDIS)[:, 0, ::-1])


def colour_mapped(values: np.ndarray, vmin: float, vmax: float, empty=(255, 255, 255)) -> np.ndarray:
    """`values` (h, w) mapped through viridis from `vmin` to `vmax` (clipped at both ends): (h, w, 3) uint8 RGB,
    `empty` where a value is NaN."""
    span = vmax - vmin if vmax > vmin else 1.0
    with np.errstate(invalid="ignore"):
        index = np.clip(np.rint((values - vmin) * (255.0 / span)), 0, 255)
    known = np.isfinite(values)
    out = viridis()[np.where(known, index, 0).astype(np.intp)]
    out[~known] = empty
    return out


def nice_ticks(lo: float, hi: float, most: int = 7) -> np.ndarray:
    """Round values between `lo` and `hi` (inclusive): multiples of the smallest step of 1, 2, 2.5 or 5 times a
    power of ten that gives at most `most` of them (at least two where the range holds two)."""
    if not (np.isfinite(lo) and np.isfinite(hi)) or hi <= lo:
        return np.array([lo]) if np.isfinite(lo) else np.zeros(0)
    span = hi - lo
    power = 10.0 ** math.floor(math.log10(span / most))
    for factor in (1.0, 2.0, 2.5, 5.0, 10.0, 20.0):
        step = factor * power
        first, last = math.ceil(lo / step - 1e-9), math.floor(hi / step + 1e-9)
        if last - first + 1 <= most:
            return np.arange(first, last + 1) * step
    return np.array([lo, hi])


def tick_labels(ticks: np.ndarray) -> list[str]:
    """The ticks written with as many decimals as their step needs, negative ones with a minus sign (U+2212)."""
    if ticks.size == 0:
        return []
    step = float(np.min(np.diff(ticks))) if ticks.size > 1 else abs(float(ticks[0])) or 1.0
    decimals = max(0, -math.floor(math.log10(step) + 1e-9))
    if abs(round(step * 10**decimals) - step * 10**decimals) > 1e-6:  # a step of 2.5, 0.25: one more decimal
        decimals += 1
    labels = []
    for value in ticks:
        text = f"{abs(value):.{decimals}f}"
        labels.append(("\u2212" + text) if value < 0 and float(text) != 0 else text)
    return labels


@functools.cache
def font(size_px: int) -> ImageFont.FreeTypeFont | ImageFont.ImageFont:
    """DejaVu Sans at `size_px` pixels, from matplotlib's font files (found, not imported); Pillow's own font at that
    size where the file is missing, and its bitmap font (one size) where Pillow was built without FreeType."""
    spec = importlib.util.find_spec("matplotlib")
    folder = spec.submodule_search_locations[0] if spec is not None and spec.submodule_search_locations else None
    try:
        if folder is not None:
            try:
                return ImageFont.truetype(os.path.join(folder, "mpl-data", "fonts", "ttf", "DejaVuSans.ttf"), size_px)
            except OSError:  # the file gone: Pillow's own
                pass
        return ImageFont.load_default(size_px)  # FreeType's, at this size
    except ImportError:  # no FreeType: a size asks for it too
        return ImageFont.load_default()


def _anchored_text(draw: ImageDraw.ImageDraw, xy, text: str, face, anchor: str, fill) -> None:
    """`text` placed at `xy` by its `anchor` (Pillow's two letters: l/m/r across, then a/t/m/b/s/d down). Pillow
    places it with FreeType fonts; a bitmap font (Pillow without FreeType) is placed here from its box, the
    baseline taken as the box's bottom."""
    if isinstance(face, ImageFont.FreeTypeFont):
        draw.text(xy, text, fill=fill, font=face, anchor=anchor)
        return
    left, top, right, bottom = draw.textbbox((0, 0), text, font=face)
    across = {"l": 0.0, "m": 0.5, "r": 1.0}[anchor[0]]
    down = {"a": 0.0, "t": 0.0, "m": 0.5}.get(anchor[1], 1.0)
    draw.text((xy[0] - left - across * (right - left), xy[1] - top - down * (bottom - top)), text, fill=fill,
              font=face)


class Panel(NamedTuple):
    """A panel's axes as placed on the figure: `left`, `top`, `width`, `height` pixels, and its data `extent`
    `(left, right, bottom, top)`."""

    left: int
    top: int
    width: int
    height: int
    extent: tuple[float, float, float, float]


class RasterFigure:
    """A white figure of `width` x `height` pixels to draw panels, a colour bar and text on; `png()` encodes it.
    `text_px` is the labels' font size (the titles' is a fifth larger)."""

    def __init__(self, width: int, height: int, text_px: int = 16):
        self.image = Image.new("RGB", (width, height), (255, 255, 255))
        self.draw = ImageDraw.Draw(self.image)
        self.text_px = text_px

    @property
    def size(self) -> tuple[int, int]:
        return self.image.size

    def box(self, fractions: tuple[float, float, float, float]) -> tuple[int, int, int, int]:
        """`(left, bottom, width, height)` in figure fractions, as matplotlib places axes, in pixels
        `(left, top, width, height)`."""
        w, h = self.size
        left, bottom, width, height = fractions
        return round(left * w), round((1 - bottom - height) * h), round(width * w), round(height * h)

    def _face(self, text: str, size_px: int | None):
        """The font at `size_px` (the labels' size when None), and `text` as it can draw it: a bitmap font (Pillow
        without FreeType) has Latin-1 only, and a hyphen for the minus sign."""
        face = font(size_px or self.text_px)
        return face, text if isinstance(face, ImageFont.FreeTypeFont) else text.replace("\u2212", "-")

    def text(self, xy, text: str, size_px: int | None = None, anchor: str = "la", rotated: bool = False) -> None:
        """`text` at pixel `xy`, placed by Pillow's `anchor` (e.g. "mb": its middle and baseline there); `rotated`
        turns it a quarter anticlockwise (reading upward) about its middle, which is put at `xy`."""
        face, text = self._face(text, size_px)
        if not rotated:
            _anchored_text(self.draw, xy, text, face, anchor, INK)
            return
        left, top, right, bottom = self.draw.textbbox((0, 0), text, font=face)
        mask = Image.new("L", (right - left + 2, bottom - top + 2), 0)
        ImageDraw.Draw(mask).text((1 - left, 1 - top), text, fill=255, font=face)
        mask = mask.rotate(90, expand=True)
        corner = (round(xy[0] - mask.width / 2), round(xy[1] - mask.height / 2))
        self.image.paste(Image.new("RGB", mask.size, INK), corner, mask)

    def text_width(self, text: str, size_px: int | None = None) -> int:
        face, text = self._face(text, size_px)
        left, _, right, _ = self.draw.textbbox((0, 0), text, font=face)
        return right - left

    def image_panel(self, box: tuple[int, int, int, int], rgb: np.ndarray, extent, title: str = "", xlabel: str = "",
                    ylabel: str = "", anchor: str = "C") -> Panel:
        """`rgb` (h, w, 3) uint8, its row 0 at the panel's top, drawn over the data `extent` at equal scale on both
        axes, as large as fits the pixel `box` `(left, top, width, height)` and placed in it by `anchor` ("C": its
        centre, "W": its left side, centred up and down), then framed, ticked, labelled and titled."""
        bl, bt, bw, bh = box
        dx, dy = abs(extent[1] - extent[0]), abs(extent[2] - extent[3])
        scale = min(bw / dx, bh / dy) if dx > 0 and dy > 0 else 1.0
        pw, ph = max(1, round(dx * scale)), max(1, round(dy * scale))
        left = bl + (bw - pw) // 2 if anchor == "C" else bl
        top = bt + (bh - ph) // 2
        panel = Panel(left, top, pw, ph, tuple(float(e) for e in extent))
        picture = Image.fromarray(np.ascontiguousarray(rgb, dtype=np.uint8))
        self.image.paste(picture.resize((pw, ph), Image.Resampling.NEAREST), (left, top))
        self.draw.rectangle((left - 1, top - 1, left + pw, top + ph), outline=INK)
        self._ticks(panel, xlabel, ylabel)
        if title:
            self.text((left + pw / 2, top - 8), title, round(1.15 * self.text_px), "mb")
        return panel

    def _ticks(self, panel: Panel, xlabel: str, ylabel: str) -> None:
        """Ticks at round values under and left of `panel`, their labels, and the axis labels."""
        left, top, width, height = panel[:4]
        x0, x1, y0, y1 = panel.extent  # (left, right, bottom, top)
        gap = 3
        ticks = nice_ticks(min(x0, x1), max(x0, x1))
        for value, label in zip(ticks, tick_labels(ticks)):
            x = round(left + (value - x0) / (x1 - x0) * (width - 1))  # whole pixels: crisp marks
            self.draw.line((x, top + height, x, top + height + TICK_PX), fill=INK)
            self.text((x, top + height + TICK_PX + gap), label, anchor="mt")
        if xlabel:
            self.text((left + width / 2, top + height + TICK_PX + 2 * gap + 1.3 * self.text_px), xlabel, anchor="mt")
        ticks = nice_ticks(min(y0, y1), max(y0, y1))
        labels = tick_labels(ticks)
        for value, label in zip(ticks, labels):
            y = round(top + (value - y1) / (y0 - y1) * (height - 1))
            self.draw.line((left - 1 - TICK_PX, y, left - 1, y), fill=INK)
            self.text((left - 1 - TICK_PX - gap, y), label, anchor="rm")
        if ylabel:
            widest = max((self.text_width(label) for label in labels), default=0)
            self.text((left - TICK_PX - 2 * gap - widest - 0.7 * self.text_px, top + height / 2), ylabel, rotated=True)

    def colour_bar(self, box: tuple[int, int, int, int], vmin: float, vmax: float, label: str = "") -> None:
        """viridis from `vmin` (bottom) to `vmax` (top) in the pixel `box` `(left, top, width, height)`, framed, with
        ticks and their labels on its right and the `label` beyond them."""
        left, top, width, height = box
        rows = viridis()[np.rint(np.linspace(255, 0, height)).astype(np.intp)]
        self.image.paste(Image.fromarray(np.repeat(rows[:, None], width, axis=1)), (left, top))
        self.draw.rectangle((left - 1, top - 1, left + width, top + height), outline=INK)
        span = vmax - vmin if vmax > vmin else 1.0
        ticks = nice_ticks(vmin, vmax)
        labels = tick_labels(ticks)
        for value, text in zip(ticks, labels):
            y = round(top + (vmax - value) / span * (height - 1))
            self.draw.line((left + width, y, left + width + TICK_PX, y), fill=INK)
            self.text((left + width + TICK_PX + 3, y), text, anchor="lm")
        if label:
            widest = max((self.text_width(text) for text in labels), default=0)
            self.text((left + width + TICK_PX + 6 + widest + 0.7 * self.text_px, top + height / 2), label, rotated=True)

    def legend(self, panel: Panel, colour: tuple[int, int, int], text: str) -> None:
        """One entry, a square of `colour` and its `text`, in a framed box in `panel`'s top-right corner."""
        size = round(0.8 * self.text_px)
        pad = 5
        width = size + pad + self.text_width(text, size) + 3 * pad
        right, top = panel.left + panel.width - pad, panel.top + pad
        self.draw.rectangle((right - width, top, right, top + size + 2 * pad + 2), fill=(255, 255, 255),
                            outline=(204, 204, 204))
        square = (right - width + pad, top + pad + 1, right - width + pad + size, top + pad + 1 + size)
        self.draw.rectangle(square, fill=colour)
        self.text((square[2] + pad, top + pad + 1 + size / 2), text, size, "lm")

    def png(self) -> bytes:
        """The figure as PNG bytes."""
        buffer = io.BytesIO()
        self.image.save(buffer, format="PNG", compress_level=PNG_COMPRESSION)
        return buffer.getvalue()
