"""Sub-pixel refinement over two patch sizes, on a pair rendered from an analytic disparity field."""

import cv2
import numpy as np

from jaxstereo._stereo import matching, row_bands
from jaxstereo._stereo.matching import refine_disparity

H, W = 200, 320
CENTRE, WIDTH, HEIGHT = (100, 160), 9.0, 1.2  # a bump of the disparity (a rock): pixels
BASE = 20.0


def _bumped_pair(seed=0):
    """A textured pair whose true disparity (h, w) is a flat BASE plus a Gaussian bump, the right image
    rendered exactly from the left one's texture (x_right = x_left - d), and SGBM-like starting values
    (the truth plus 0.1 px of noise, quantised to 1/16 px)."""
    rng = np.random.default_rng(seed)
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    def disparity(u):
        return BASE + HEIGHT * np.exp(-((u - CENTRE[1]) ** 2 + (v - CENTRE[0]) ** 2) / (2 * WIDTH**2))
    texture = cv2.GaussianBlur(rng.uniform(0, 255, (H, W + 64)).astype(np.float32), (0, 0), 1.2)
    left = texture[:, :W]
    source = u + BASE  # the left column each right pixel sees: u_left - d(u_left) = u_right
    for _ in range(30):
        source = u + disparity(source)
    right = cv2.remap(texture, source.astype(np.float32), v.astype(np.float32), cv2.INTER_CUBIC)
    truth = disparity(u)
    start = np.round((truth + rng.normal(0.0, 0.1, truth.shape)) * 16) / 16
    as_image = [np.clip(im, 0, 255).astype(np.uint8) for im in (left, right)]
    return *as_image, start.astype(np.float32), truth


def _rms(left, right, start, truth, small_window):
    """RMS error (px) of `refine_disparity` on the bump and on the flat part far from it."""
    v, u = np.mgrid[0:H, 0:W]
    r = np.hypot(v - CENTRE[0], u - CENTRE[1])
    bump, flat = r < 1.5 * WIDTH, (r > 5 * WIDTH) & (u > 40) & (u < W - 40) & (v > 20) & (v < H - 20)
    d = refine_disparity(left, right, start, window=31, small_window=small_window, with_sigma=True).disparity
    return [float(np.sqrt(np.mean((d[m] - truth[m]) ** 2))) for m in (bump, flat)]


def test_the_small_patch_follows_a_curved_surface_the_large_one_smooths():
    """Over a bump 9 px wide the 31 px patch averages the relief (0.16 px RMS on it, measured); where the 15 px
    patch disagrees it is taken (0.15 px: it smooths too, less), and the flat part keeps the large patch."""
    left, right, start, truth = _bumped_pair()
    bump_large, flat_large = _rms(left, right, start, truth, None)
    bump_both, flat_both = _rms(left, right, start, truth, 15)
    assert bump_both < 0.97 * bump_large
    assert flat_both <= 1.02 * flat_large
    assert flat_both < 0.05  # the flat part's 0.1 px of start noise gone: 0.002 px measured


def test_sgbm_block_keeps_the_patch_fit_from_leaving_a_correct_match(monkeypatch):
    """Where the 31 px patch straddles the bump it pulls the fit off the (correct) start; SGBM's own 5 x 5 block
    then fits the refined value far worse than its own and the start stands: 0.36 px RMS on the bump without
    the check, 0.16 with it (with the 15 px patch too: 0.18 and 0.15). Measured without the bound on the moves,
    which does part of the same work (see the next test)."""
    left, right, start, truth = _bumped_pair()
    monkeypatch.setattr(matching, "MOVE_SIGMAS", 1e9)
    checked = _rms(left, right, start, truth, None)
    monkeypatch.setattr(matching, "BLOCK_FIT_SIGMAS", 1e9)  # no check
    unchecked = _rms(left, right, start, truth, None)
    assert checked[0] < 0.5 * unchecked[0]
    assert checked[1] <= 1.01 * unchecked[1]  # the flat part's refinement kept


def test_a_fit_moves_no_further_from_sgbm_than_its_bound(monkeypatch):
    """Each refined value lies within 2 of SGBM's own standard deviations (or 0.3 px) of SGBM's value, and a small
    patch's within half a pixel too; the fits pulled off the bump's correct starts are held there (with the check
    against SGBM's block turned off, 0.36 px RMS on the bump unbounded, 0.24 px bounded, measured), while the flat
    part keeps its refinement (0.0025 px RMS left of the start's 0.1 px, 0.0019 px unbounded)."""
    left, right, start, truth = _bumped_pair()
    sgbm_sigma = refine_disparity(left, right, start, subpixel=False).sigma
    large, both = (refine_disparity(left, right, start, window=31, small_window=s).disparity for s in (None, 15))
    for refined in (large, both):
        bound = np.maximum(matching.MOVE_SIGMAS * sgbm_sigma, matching.MIN_MOVE_PX)
        assert np.all(np.abs(refined - start) <= bound + 1e-5)
    far = np.abs(both - start) > matching.MAX_MOVE_PX + 1e-5
    assert np.array_equal(both[far], large[far])  # only the large patch's values move further
    monkeypatch.setattr(matching, "BLOCK_FIT_SIGMAS", 1e9)
    bounded = _rms(left, right, start, truth, None)
    monkeypatch.setattr(matching, "MOVE_SIGMAS", 1e9)
    unbounded = _rms(left, right, start, truth, None)
    assert bounded[0] < 0.8 * unbounded[0]
    assert bounded[1] < 0.01


def test_the_right_cameras_other_levels_are_mapped_onto_the_lefts_before_the_fit():
    """The fit compares grey levels as they are, and two cameras rarely record a scene alike. With the right image
    15 % darker and 12 levels brighter, or under a gamma of 1.3, the refined disparities of the pair's inner part were
    0.069 and 0.086 px RMS off with its levels as they are (0.027 px as rendered, the start 0.10 px, measured); mapped
    onto the left's at the start's matches first (the default), 0.027 px. Where the cameras agree nothing changes."""
    left, right, start, truth = _bumped_pair()
    v, u = np.mgrid[0:H, 0:W]
    inner = (u > 40) & (u < W - 40) & (v > 20) & (v < H - 20)

    def rms(image, **kwargs):
        d = refine_disparity(left, image, start, **kwargs).disparity
        return float(np.sqrt(np.mean((d[inner] - truth[inner]) ** 2)))

    rendered = refine_disparity(left, right, start, match_levels=False).disparity
    assert np.array_equal(refine_disparity(left, right, start).disparity, rendered, equal_nan=True)
    as_rendered = rms(right, match_levels=False)
    assert as_rendered < 0.04
    for other in (np.rint(right * 0.85 + 12), np.rint(255 * (right / 255.0) ** 1.3)):
        other = np.clip(other, 0, 255).astype(np.uint8)
        assert rms(other) < 1.1 * as_rendered
        assert rms(other, match_levels=False) > 2 * as_rendered


RAMP = (0.07, 0.03)  # disparity slopes (px per px along u, v): a surface inclined to the image


def _inclined_pair(seed=0):
    """A pair whose true disparity (h, w) is a plane (BASE + RAMP), textured with a contrast that varies over
    a few pixels (a patch's gradient energy lies off its centre), and SGBM-like starting values (the truth plus
    0.1 px of noise, quantised to 1/16 px)."""
    rng = np.random.default_rng(seed)
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    def disparity(u):
        return BASE + RAMP[0] * (u - W / 2) + RAMP[1] * (v - H / 2)
    fine = cv2.GaussianBlur(rng.uniform(-1, 1, (H, W + 64)).astype(np.float32), (0, 0), 1.2)
    contrast = cv2.GaussianBlur(rng.uniform(0, 1, (H, W + 64)).astype(np.float32), (0, 0), 6.0)
    contrast = (contrast - contrast.min()) / (contrast.max() - contrast.min())
    texture = 128 + 600 * fine * contrast**3
    source = u + BASE
    for _ in range(50):
        source = u + disparity(source)
    right = cv2.remap(texture, source.astype(np.float32), v.astype(np.float32), cv2.INTER_CUBIC)
    truth = disparity(u)
    start = np.round((truth + rng.normal(0.0, 0.1, truth.shape)) * 16) / 16
    as_image = [np.clip(im, 0, 255).astype(np.uint8) for im in (texture[:, :W], right)]
    return *as_image, start.astype(np.float32), truth


def test_an_inclined_surface_is_refined_at_each_patch_centre(monkeypatch):
    """On a plane inclined to the image a 31 px patch's SGBM disparities spread 0.69 px (std) without an edge:
    the patch is judged by their spread about the plane fitted to them, and refined. Its one shift is the
    disparity where its gradient energy lies, moved to its centre along that plane: 0.012 px RMS against the
    truth, measured (0.147 px without the move, worse than the starts' 0.10)."""
    left, right, start, truth = _inclined_pair()
    inner = (slice(30, H - 30), slice(50, W - 50))

    def rms():
        d = refine_disparity(left, right, start, window=31, small_window=15, with_sigma=True).disparity
        return float(np.sqrt(np.mean((d - truth)[inner] ** 2))), float(np.mean((d != start)[inner]))

    start_rms = float(np.sqrt(np.mean((start - truth)[inner] ** 2)))
    moved, refined_share = rms()
    assert refined_share > 0.95  # 0.997 measured: the spread about the plane passes the patches
    assert moved < 0.25 * start_rms
    monkeypatch.setattr(matching, "_energy_centroid",
                        lambda gg, total, box, u, v: (np.zeros_like(gg), np.zeros_like(gg)))
    unmoved, _ = rms()
    assert unmoved > 5 * moved


def test_bands_of_rows_on_threads_give_the_whole_images_values(monkeypatch):
    """`refine_disparity` runs on bands of rows (one per core), each extended by two windows' half-widths: the
    result must be the one the whole image gives, bit for bit, whatever the number of bands; with a halo one
    row short of that it is not (the `_disagreement` window reads rows the band's edge reflected)."""

    left, right, start, _ = _bumped_pair(seed=3)
    start[::7, ::5] = np.nan  # unmatched pixels too
    offset = np.random.default_rng(4).uniform(-1.5, 1.5, start.shape).astype(np.float32)  # rows off the rectified

    def refine():
        return refine_disparity(left, right, start, offset, window=31, small_window=15, with_sigma=True)

    monkeypatch.setattr(row_bands, "available_cores", lambda: 1)
    whole = refine()
    monkeypatch.setattr(row_bands, "available_cores", lambda: 3)
    monkeypatch.setattr(row_bands, "MIN_BAND_HALOS", 1)  # three bands of 67 rows and their halos of 30
    banded = refine()
    for a, b in zip(whole, banded):
        np.testing.assert_array_equal(a, b)
    real_map = row_bands.map_row_bands
    monkeypatch.setattr(matching, "map_row_bands", lambda fn, h, halo, **size: real_map(fn, h, halo - 1, **size))
    short = refine()
    assert not all(np.array_equal(a, b, equal_nan=True) for a, b in zip(whole, short))


def test_the_rectangle_around_the_matches_gives_the_whole_images_values(monkeypatch):
    """Each band is worked on only around its matches (and a halo): the result must be the one the whole band
    gives, bit for bit, with the pixels outside all NaN, on a pair whose matches leave wide margins unmatched on
    every side (as the columns left of SGBM's first disparity are), with rows off the rectified ones."""
    left, right, start, _ = _bumped_pair(seed=5)
    start[:, :70] = np.nan
    start[:, 290:] = np.nan
    start[:40] = np.nan
    start[165:] = np.nan
    start[::9, ::4] = np.nan
    offset = np.random.default_rng(6).uniform(-1.5, 1.5, start.shape).astype(np.float32)
    monkeypatch.setattr(row_bands, "available_cores", lambda: 1)  # one band: the whole image
    shapes = []
    real_rows = matching._refine_rows

    def recorded(L, *args, **kwargs):
        shapes.append(L.shape[:2])
        return real_rows(L, *args, **kwargs)

    monkeypatch.setattr(matching, "_refine_rows", recorded)

    def refine():
        return refine_disparity(left, right, start, offset, window=31, small_window=15, with_sigma=True)

    cropped = refine()
    monkeypatch.setattr(matching, "_match_extent", lambda valid, halo: (0, valid.shape[0], 0, valid.shape[1]))
    whole = refine()
    for a, b in zip(whole, cropped):
        np.testing.assert_array_equal(a, b)
    assert shapes[0] == (165 + 30 - (40 - 30), 290 + 30 - (70 - 30))  # the matches' rectangle and a halo of 30 px
    assert np.isnan(cropped.disparity[~np.isfinite(start)]).all()
    assert np.isfinite(cropped.disparity[np.isfinite(start)]).all()


def test_a_band_without_a_match_gives_nan_and_the_others_their_whole_image_values(monkeypatch):
    """Three bands of rows, the last one (with its halo) without a single match: it comes back all NaN (no
    off-surface flag), and the bands with matches give the values one whole-image band does, bit for bit."""
    left, right, start, _ = _bumped_pair(seed=7)
    start[100:] = np.nan  # the third band, rows 133-199, and its halo from row 103 hold no match
    monkeypatch.setattr(row_bands, "MIN_BAND_HALOS", 1)
    extents = []
    real_extent = matching._match_extent

    def recorded(valid, halo):
        extents.append(real_extent(valid, halo))
        return extents[-1]

    monkeypatch.setattr(matching, "_match_extent", recorded)

    def refine(cores: int):
        monkeypatch.setattr(row_bands, "available_cores", lambda: cores)
        return refine_disparity(left, right, start, window=31, small_window=15, with_sigma=True)

    whole, banded = refine(1), refine(3)
    assert extents.count(None) == 1  # the third band's
    for a, b in zip(whole, banded):
        np.testing.assert_array_equal(a, b)
    assert np.isnan(banded.disparity[100:]).all() and np.isnan(banded.sigma[100:]).all()
    assert not banded.off_surface[100:].any()
    assert np.isfinite(banded.disparity[:100]).all()


def test_a_patch_across_the_waterline_keeps_its_value_and_adds_its_offset_from_the_small_patch():
    """With a waterline through the pair (the matches right of column 160 above the water), the values are the
    ones without it; patches across the line (within 15 px of it, 4 px for a small patch's fit) take their own
    std combined with the mean of the small patch's fit less the large one's over the small patch, less the part of
    it the small fits' own noise explains (a numpy reference from the two patch sizes run alone); away from the
    line the std is unchanged."""
    left, right, start, _ = _inclined_pair(seed=2)
    waterline = np.where(np.arange(W)[None, :] >= 160, start - 1.0, start + 1.0).astype(np.float32)
    plain = refine_disparity(left, right, start, window=31, small_window=9)
    split = refine_disparity(left, right, start, window=31, small_window=9, waterline=waterline)
    large = refine_disparity(left, right, start, window=31, small_window=None)
    small = refine_disparity(left, right, start, window=9, small_window=None)
    np.testing.assert_array_equal(split.disparity, plain.disparity)
    np.testing.assert_array_equal(split.disagreement, plain.disagreement)
    u = np.arange(W)[None, :].repeat(H, axis=0)
    inner = (np.arange(H)[:, None] >= 20) & (np.arange(H)[:, None] < H - 20)
    across, away = inner & (np.abs(u - 159.5) < 15), inner & (np.abs(u - 159.5) > 16) & (u > 40) & (u < W - 40)
    np.testing.assert_array_equal(split.sigma[away], plain.sigma[away])
    both = (large.disparity != start) & (small.disparity != start)  # where each patch size kept its fit
    difference = np.where(both, small.disparity - large.disparity, 0.0)
    variance = np.where(both, np.clip(small.sigma.astype(float) ** 2 - large.sigma.astype(float) ** 2, 0.0, 1.0), 0.0)
    padded = [np.pad(a, 4) for a in (difference, variance, both.astype(float))]
    total, noise, count = (np.lib.stride_tricks.sliding_window_view(a, (9, 9)).sum(axis=(-1, -2)) for a in padded)
    count = np.maximum(count, 1.0)
    offset = np.sqrt(np.maximum((total / count) ** 2 - noise / count, 0.0))  # the small fits' own noise taken out
    refined = across & (plain.disparity != start)
    assert refined.sum() > 0.9 * across.sum()
    # A pixel that took the small patch's fit straddles the line when that patch does
    straddles = np.abs(u - 159.5) < np.where(plain.disparity != large.disparity, 4.5, 15.5)
    expected = np.where(straddles, np.hypot(plain.sigma, offset), plain.sigma)
    np.testing.assert_allclose(split.sigma[refined], expected[refined], rtol=1e-4, atol=1e-6)
    # The disparity has no kink at this line: the offsets are the small fits' noise, and most stds stay as they were
    # (with that noise left in the offset, 99 % of them grew)
    assert np.mean(split.sigma[refined] == plain.sigma[refined]) > 0.5


def test_a_match_off_the_plane_of_its_patch_is_refined_or_flagged_off_the_surface():
    """SGBM matches 1.5 to 3 px off an inclined plane, on isolated pixels: each is either refined onto the plane
    (its patch's fit, from its correct neighbours, kept) or, where no fit could be kept, flagged `off_surface`;
    none keeps its wrong value unflagged. Correct matches are flagged neither on the plane nor on a bump on a
    plane (the small patch, which follows the bump, judges them)."""
    left, right, start, truth = _inclined_pair(seed=5)
    rng = np.random.default_rng(6)
    inner = (slice(40, H - 40), slice(60, W - 60))
    rows, cols = np.mgrid[inner]
    pick = rng.choice(rows.size, 150, replace=False)
    v, u = rows.ravel()[pick], cols.ravel()[pick]
    wrong = start.copy()
    wrong[v, u] += (rng.uniform(1.5, 3.0, v.size) * rng.choice([-1, 1], v.size)).astype(np.float32)
    result = refine_disparity(left, right, wrong, with_sigma=True)
    corrected = np.abs(result.disparity[v, u] - truth[v, u]) < 0.2
    flagged = result.off_surface[v, u]
    assert np.all(corrected | flagged), np.count_nonzero(~(corrected | flagged))
    assert flagged.sum() > 0  # the fits that moved more than 1 px are not kept: those are flagged
    clean = np.ones_like(start, bool)
    clean[v, u] = False
    assert np.mean(result.off_surface[inner][clean[inner]]) < 1e-3
    left, right, start, truth = _bumped_pair(seed=7)
    for window in (31, 63):  # over 63 px patches the plane is flat around the bump: its top was flagged when the
        # large patch judged first (0.15 % of the pixels, measured)
        bumped = refine_disparity(left, right, start, window=window, with_sigma=True)
        assert np.mean(bumped.off_surface[20:-20, 40:-40]) < 1e-3, window
    plain = refine_disparity(left, right, start, with_sigma=True, subpixel=False)
    assert plain.off_surface is None  # SGBM's values as they are: nothing judged
