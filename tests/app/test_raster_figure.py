"""The survey preview drawn with Pillow (`_app/raster_figure.py`): its ticks, its panels' placement and colours,
and a preview of a survey whose heights are known."""

import io
import math
import subprocess
import sys

import numpy as np
from PIL import Image

from jaxstereo._app.raster_figure import RasterFigure, colour_mapped, nice_ticks, tick_labels, viridis
from jaxstereo._stereo.survey import PREVIEW_PANELS, PREVIEW_SIZE_PX, SUBMERGED_COLOUR, Survey, survey_preview_png


def _brute_force_ticks(lo, hi, most=7):
    """Every step 1, 2, 2.5, 5 x 10^k tried from the smallest: the first with at most `most` multiples in range."""
    for k in range(-9, 10):
        for factor in (1, 2, 2.5, 5):
            step = factor * 10.0**k
            first, last = math.ceil(lo / step - 1e-9), math.floor(hi / step + 1e-9)
            if last - first + 1 <= most:
                return np.arange(first, last + 1) * step
    raise AssertionError


def test_ticks_are_the_round_values_of_the_smallest_step_that_fits():
    for lo, hi in ((-0.5, 1727.5), (-0.372, 0.431), (0.0, 0.375), (0.0013, 0.0017), (-5, 5), (100.2, 101.9),
                   (0.00123, 0.37), (-1e4, 3e5)):
        ticks = nice_ticks(lo, hi)
        np.testing.assert_allclose(ticks, _brute_force_ticks(lo, hi), rtol=0, atol=1e-12 * max(abs(lo), abs(hi)))
        assert 2 <= ticks.size <= 7 and ticks[0] >= lo - 1e-12 and ticks[-1] <= hi + 1e-12
    assert nice_ticks(0.2, 0.2).tolist() == [0.2] and nice_ticks(np.nan, 1.0).size == 0


def test_tick_labels_carry_the_decimals_their_step_needs():
    assert tick_labels(np.array([0.0, 250.0, 500.0])) == ["0", "250", "500"]
    assert tick_labels(np.array([-0.2, 0.0, 0.2])) == ["\u22120.2", "0.0", "0.2"]
    assert tick_labels(np.array([0.0, 0.25, 0.5])) == ["0.00", "0.25", "0.50"]
    assert tick_labels(np.array([-2.5, 0.0, 2.5])) == ["\u22122.5", "0.0", "2.5"]
    assert tick_labels(np.array([0.0012, 0.0014])) == ["0.0012", "0.0014"]


def test_colours_follow_viridis_and_empty_cells_stay_white():
    import matplotlib

    reference = np.rint(matplotlib.colormaps["viridis"](np.arange(256))[:, :3] * 255).astype(np.uint8)
    np.testing.assert_array_equal(viridis(), reference)  # OpenCV's copy of matplotlib's map
    values = np.array([[0.0, 0.5, 1.0], [np.nan, -3.0, 7.0]])
    rgb = colour_mapped(values, 0.0, 1.0)
    np.testing.assert_array_equal(rgb[0], reference[[0, 128, 255]])
    np.testing.assert_array_equal(rgb[1], [[255, 255, 255], reference[0], reference[255]])


def _decoded(png: bytes) -> np.ndarray:
    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB"))


def test_a_panel_shows_each_image_pixel_over_its_data_extent_with_ticks_at_their_values():
    fig = RasterFigure(800, 500)
    rgb = np.array([[[255, 0, 0], [0, 255, 0], [0, 0, 255], [255, 255, 0]],
                    [[0, 255, 255], [255, 0, 255], [90, 90, 90], [200, 120, 40]]], np.uint8)
    extent = (10.0, 30.0, 5.0, 0.0)  # x 10-30 left to right, y 0 at the top to 5 at the bottom: 5 units a pixel
    panel = fig.image_panel((100, 60, 600, 360), rgb, extent, "title", "x", "y")
    assert (panel.width, panel.height) == (600, 150)  # equal scale: 20 x 5 data units into 600 x 360 pixels
    assert (panel.left, panel.top) == (100, 60 + (360 - 150) // 2)  # centred
    out = _decoded(fig.png())
    for row in range(2):
        for column in range(4):
            x = panel.left + int((column + 0.5) * panel.width / 4)
            y = panel.top + int((row + 0.5) * panel.height / 2)
            np.testing.assert_array_equal(out[y, x], rgb[row, column])
    below = out[panel.top + panel.height + 2]  # a row through the x ticks' marks, under the frame
    for value in nice_ticks(10.0, 30.0):
        x = round(panel.left + (value - 10.0) / 20.0 * (panel.width - 1))
        assert below[x].max() < 100, value  # a dark tick mark at the value's column
    assert below[panel.left + panel.width // 2 + 3:panel.left + panel.width // 2 + 20].min() > 200  # none between


def _ramp_survey(n_u=300, n_v=200, water_level=0.1):
    """Points at pixels u 50..349, v 40..239 of a 400 x 300 image, their height rising with u from 0 to 0.299 m;
    those below `water_level` submerged."""
    u, v = np.meshgrid(np.arange(50, 50 + n_u), np.arange(40, 40 + n_v))
    z = 0.001 * (u - 50).ravel()
    points = np.stack([0.001 * u.ravel(), -0.001 * v.ravel(), z], axis=1)
    pixels = np.stack([u.ravel(), v.ravel()], axis=1).astype(np.float32)
    return Survey(points, np.zeros((z.size, 3), np.uint8), pixels, z < water_level, "{}", "exact", water_level)


def _lut_index(colours: np.ndarray) -> np.ndarray:
    """The viridis entry nearest each colour (k, 3)."""
    d = np.abs(colours[:, None, :].astype(int) - viridis()[None].astype(int)).sum(axis=2)
    return d.argmin(axis=1)


def test_the_preview_colours_each_pixel_by_its_height_and_leaves_the_rest_white():
    survey = _ramp_survey()
    out = _decoded(survey_preview_png(survey, (400, 300), "ramp"))
    assert out.shape == (PREVIEW_SIZE_PX[1], PREVIEW_SIZE_PX[0], 3)
    fig = RasterFigure(*PREVIEW_SIZE_PX)
    left, top, width, height = fig.box(PREVIEW_PANELS[0])
    scale = min(width / 400, height / 300)  # the image panel: 400 x 300 pixels at equal scale, centred
    pw, ph = round(400 * scale), round(300 * scale)
    x0, y0 = left + (width - pw) // 2, top + (height - ph) // 2
    row = y0 + int(140 * scale)  # image row 140, among the points
    columns = x0 + ((np.arange(60, 340, 10) + 0.5) * scale).astype(int)
    index = _lut_index(out[row, columns])
    # colour limits: the heights' 1st and 99th percentiles (0.003, 0.296 m); each column's height mapped between
    heights = 0.001 * (np.arange(60, 340, 10) - 50)
    expected = np.clip(np.rint((heights - 0.00299) / (0.29601 - 0.00299) * 255), 0, 255)
    assert np.abs(index - expected).max() <= 3 and np.all(np.diff(index) > 0)
    assert (out[row, x0 + int(20 * scale)] == 255).all() and (out[y0 + int(280 * scale), columns[5]] == 255).all()
    bar_left, bar_top, bar_width, bar_height = fig.box(PREVIEW_PANELS[2])
    middle = bar_left + bar_width // 2
    np.testing.assert_array_equal(out[bar_top, middle], viridis()[255])
    np.testing.assert_array_equal(out[bar_top + bar_height - 1, middle], viridis()[0])
    legend = out[:, fig.box(PREVIEW_PANELS[1])[0]:]  # the top view's side: its legend's square
    assert (legend == SUBMERGED_COLOUR).all(axis=2).sum() > 50
    title = out[:40]
    assert (title < 100).all(axis=2).sum() > 100  # the title's text


def test_an_empty_survey_and_a_flat_one_still_give_a_preview():
    empty = _ramp_survey(0, 0)
    flat = Survey(np.array([[0.0, 0.0, 0.1], [0.01, 0.0, 0.1]]), np.zeros((2, 3), np.uint8),
                  np.array([[5.0, 5.0], [6.0, 5.0]], np.float32), np.zeros(2, bool), "{}", "none", float("nan"))
    for survey in (empty, flat):
        out = _decoded(survey_preview_png(survey, (400, 300)))
        assert out.shape == (PREVIEW_SIZE_PX[1], PREVIEW_SIZE_PX[0], 3) and (out < 100).all(axis=2).any()


def test_the_preview_does_not_import_matplotlib():
    """A fresh `reconstruct` draws its preview without matplotlib (its import and axes took a sixth of the
    command's CPU time): drawing one imports none of it."""
    script = ("import sys, numpy as np; from jaxstereo._stereo.survey import Survey, survey_preview_png;"
              "p = np.random.default_rng(0).uniform(0, 0.3, (1000, 3));"
              "s = Survey(p, np.zeros((1000, 3), np.uint8), (p[:, :2] * 1000).astype(np.float32), p[:, 2] < 0.1,"
              " '{}', 'exact', 0.1);"
              "png = survey_preview_png(s, (400, 300));"
              "print(png[:4] == b'\\x89PNG', any(m.startswith('matplotlib') for m in sys.modules))")
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True)
    assert done.stdout.split() == ["True", "False"], done.stderr[-2000:]


def test_without_freetype_the_preview_is_drawn_in_pillows_bitmap_font(monkeypatch):
    """A Pillow built without FreeType has only its bitmap font: the text is placed from its box instead."""
    from PIL import ImageFont

    from jaxstereo._app import raster_figure

    class NoFreeType:  # what Pillow holds for its FreeType module when it was built without one
        def __getattr__(self, name):
            raise ImportError("The _imagingft C module is not installed")

    monkeypatch.setattr(ImageFont, "core", NoFreeType())
    raster_figure.font.cache_clear()
    try:
        assert not isinstance(raster_figure.font(16), ImageFont.FreeTypeFont)
        out = _decoded(survey_preview_png(_ramp_survey(), (400, 300), "ramp"))
    finally:
        raster_figure.font.cache_clear()
    assert out.shape == (PREVIEW_SIZE_PX[1], PREVIEW_SIZE_PX[0], 3)
    ink = (out < 100).all(axis=2)
    assert ink[:40].sum() > 20  # the title, near the top
    fig = RasterFigure(*PREVIEW_SIZE_PX)
    left, top, width, height = fig.box(PREVIEW_PANELS[0])
    assert ink[top + height + 6:top + height + 30, left:left + width].sum() > 50  # the x tick labels under the panel
