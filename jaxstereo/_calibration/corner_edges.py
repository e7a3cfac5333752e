"""Chessboard corners from the board's edges: each corner is the intersection of the two edge lines through it.

A corner detector that looks only at the few pixels around a saddle point is limited by how those pixels were
sampled: on a sharp image an edge crosses a single pixel, and on the POV-Ray flume's calibration boards OpenCV's
`findChessboardCornersSB` (accuracy mode) is off by 0.03-0.10 px RMS, 0.2 px at worst. Those errors are few
hundredths of a pixel, yet they move a calibration's focal length by 0.05-0.1 %, and every distance with it.

Here every pixel along the four half-edges that leave a corner contributes. Each pixel row (or column) that crosses
an edge gives the edge's position there exactly, for any blur symmetric about the edge and for area-sampled
pixels: the sum, across the crossing, of each pixel's share of the first side's level. A straight line through
the crossings on both sides of the corner gives each edge, and the corner is where the two lines meet.

Measured against exact corners: 0.015 px RMS on the POV-Ray flume's 50 board views (OpenCV alone 0.041 px), 0.007
px on this project's renders of a realistic rig with JPEG, blurred or not (OpenCV 0.041-0.043 px). Lens
distortion bends the edges: with k1 = -0.3 at 640x480 (a strong wide-angle lens) the straight lines leave 0.036 px
(OpenCV 0.053 px); a curved fit was tried and rejected, its variance costs more than the bend on every other set.
On OpenCV's own stereo chessboard photographs (blurred, k1 -0.3) the calibration's RMS drops from 0.24 to 0.17 px.
Intensities are used as they are: decoding them as sRGB helped on renders and hurt on those photographs.
"""

from __future__ import annotations

import numpy as np

MIN_SAMPLES = 8  # crossings per edge line
MAX_FIT_RMS_PX = 0.25  # an edge whose crossings scatter more than this is not a clean edge
MAX_HALF_WIDTH = 8  # pixels scanned on each side of an edge, at most
MAX_MOVE_PX = 1.5  # a refined corner further than this from the detector's is not the same corner


def _half_edges(grid: np.ndarray, r: int, c: int, axis: int) -> list[np.ndarray]:
    """The vectors (pixels) from corner (r, c) to its two neighbours along `axis` (0: rows, 1: columns); at the
    board's border the missing neighbour is the mirror of the other one (the outer squares are as large)."""
    rows, cols = grid.shape[:2]
    step = (1, 0) if axis == 0 else (0, 1)
    out = []
    for sign in (1, -1):
        rr, cc = r + sign * step[0], c + sign * step[1]
        if 0 <= rr < rows and 0 <= cc < cols:
            out.append(grid[rr, cc] - grid[r, c])
        else:
            rr, cc = r - sign * step[0], c - sign * step[1]
            out.append(grid[r, c] - grid[rr, cc])
    return out


def _scan(grey: np.ndarray, p: np.ndarray, u: np.ndarray, q: np.ndarray, half_width: int):
    """The pixels across the edge through `p` along unit `u`, on the pixel row (or column, for an edge nearer
    the horizontal) nearest the point `q`: `(profile, first pixel's index across, row, across index, row index,
    the edge's predicted position across)`, or None where the scan leaves the image."""
    scan_rows = abs(u[1]) >= abs(u[0])
    a_idx, b_idx = (0, 1) if scan_rows else (1, 0)  # a: the coordinate scanned across, b: the row's own
    line = round(q[b_idx])
    across = p[a_idx] + (line - p[b_idx]) * u[a_idx] / u[b_idx]
    lo = int(np.floor(across)) - half_width
    hi = int(np.floor(across)) + half_width + 1
    if lo < 0 or hi >= grey.shape[b_idx] or not 0 <= line < grey.shape[1 - b_idx]:
        return None
    profile = grey[line, lo:hi + 1] if scan_rows else grey[lo:hi + 1, line]
    return profile, lo, line, a_idx, b_idx, across


def _crossings(grey: np.ndarray, p: np.ndarray, u: np.ndarray, s: np.ndarray, other: np.ndarray, far: np.ndarray,
               half_width: int) -> np.ndarray:
    """Where the edge leaving `p` along unit `u` crosses the pixel rows (or columns) at distances `s` (n,) along it,
    in pixels.

    `other` is the direction of the corner's other edge; `far` the neighbouring corner at the half-edge's end,
    whose own other edge crosses the same rows. Returns (x, y, contrast) rows (k, 3), in the order of `s`, for
    the distances whose scan sees one clean step: not another edge, inside the image, with contrast.
    """
    scan_rows = abs(u[1]) >= abs(u[0])
    a_idx, b_idx = (0, 1) if scan_rows else (1, 0)  # a: the coordinate scanned across, b: the row's own
    line = np.round(p[b_idx] + s * u[b_idx])
    across = p[a_idx] + (line - p[b_idx]) * u[a_idx] / u[b_idx]
    lo = np.floor(across).astype(np.int64) - half_width
    ok = (lo >= 0) & (lo + 2 * half_width + 1 < grey.shape[b_idx]) & (line >= 0) & (line < grey.shape[1 - b_idx])
    if abs(other[b_idx]) > 1e-9:
        for start in (p, far):  # the corner's other edge and the far corner's, where they cross these rows
            where = start[a_idx] + (line - start[b_idx]) * other[a_idx] / other[b_idx]
            ok &= ~(np.abs(where - across) < half_width + 2)
    line, lo, across = line[ok].astype(np.int64), lo[ok], across[ok]
    index = lo[:, None] + np.arange(2 * half_width + 2)
    profile = grey[line[:, None], index] if scan_rows else grey[index, line[:, None]]
    first, last = profile[:, :2].mean(axis=1), profile[:, -2:].mean(axis=1)
    contrast = np.abs(last - first)
    with np.errstate(divide="ignore", invalid="ignore"):  # a flat profile: no step, dropped below
        share = (profile - last[:, None]) / (first - last)[:, None]  # each pixel's share of the first side
        # One clean step: not flat, and no texture or other edge (shares outside [-0.25, 1.25]).
        clean = (contrast != 0) & (share.min(axis=1) >= -0.25) & (share.max(axis=1) <= 1.25)
        position = lo - 0.5 + share.sum(axis=1)
    out = np.empty((line.size, 3))
    out[:, a_idx], out[:, b_idx], out[:, 2] = position, line, contrast
    return out[clean]


def _edge_line(grey, p, vectors, other_axis_dir, half_width):
    """The edge through corner `p` along its two half-edge `vectors` (pixels), near the corner: (point, unit
    direction), or None; `other_axis_dir` is the direction of the corner's other edge."""
    direction = vectors[0] - vectors[1]
    direction /= np.linalg.norm(direction)
    normal = np.array([-direction[1], direction[0]])
    samples = []
    for v in vectors:
        length = float(np.linalg.norm(v))
        s = np.arange(half_width + 2.5, length - half_width - 2.5, 1.0)
        samples.append(_crossings(grey, p, v / length, s, other_axis_dir, p + v, half_width))
    pts = np.concatenate(samples)
    if len(pts) < MIN_SAMPLES:
        return None
    keep = pts[:, 2] >= 0.5 * np.median(pts[:, 2])  # crossings with the board's own contrast
    rel = pts[keep, :2] - p
    t, n = rel @ direction, rel @ normal
    if t.size < MIN_SAMPLES:
        return None
    design = np.stack([np.ones_like(t), t], axis=1)
    coef = np.linalg.lstsq(design, n, rcond=None)[0]
    residual = n - design @ coef
    inliers = np.abs(residual) <= max(3.0 * 1.4826 * float(np.median(np.abs(residual))), 0.05)
    if inliers.sum() < MIN_SAMPLES:
        return None
    coef = np.linalg.lstsq(design[inliers], n[inliers], rcond=None)[0]
    if np.sqrt(np.mean((n[inliers] - design[inliers] @ coef) ** 2)) > MAX_FIT_RMS_PX:
        return None
    point = p + coef[0] * normal
    tangent = direction + coef[1] * normal
    return point, tangent / np.linalg.norm(tangent)


def edge_blur_px(grey: np.ndarray, grid: np.ndarray) -> float:
    """How wide the board's edges are (pixels): the median, over the middle of each edge between two neighbouring
    corners of `grid` (rows, cols, 2), of the standard deviation of the step's derivative across the edge (its
    part above a tenth of its peak, so that the plateaus' noise does not count)."""
    grey = np.asarray(grey, dtype=np.float64)
    spreads = []
    for axis in (0, 1):
        starts = grid[:-1] if axis == 0 else grid[:, :-1]
        ends = grid[1:] if axis == 0 else grid[:, 1:]
        for p, q in zip(starts.reshape(-1, 2), ends.reshape(-1, 2)):
            scanned = _scan(grey, p, (q - p) / np.linalg.norm(q - p), 0.5 * (p + q), MAX_HALF_WIDTH)
            if scanned is None:
                continue
            step = np.abs(np.diff(scanned[0]))
            step = np.maximum(step - 0.1 * step.max(), 0.0)  # the plateaus' noise is not the edge's width
            if step.sum() <= 0:
                continue
            x = np.arange(step.size) + 0.5
            centre = float(np.sum(step * x) / step.sum())
            spreads.append(float(np.sqrt(np.sum(step * (x - centre) ** 2) / step.sum())))
    return float(np.median(spreads)) if spreads else 1.0


def refine_chessboard_corners(grey: np.ndarray, pixels: np.ndarray, rows: int, cols: int,
                              half_width: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Corners of a detected chessboard as the intersections of its edge lines.

    **Parameters:** `grey` (h, w) image; `pixels` (rows * cols, 2) the detector's corners in row-major grid
    order (x, y pixels, pixel centres at integers); `half_width` the pixels scanned on each side of an edge
    (default: 2.5 times the edges' blur, `edge_blur_px`, plus one, 2 to 8 px: a blurred edge's whole step).

    **Returns:** `(refined (n, 2), refined_mask (n,))`: a corner keeps the detector's position where either of
    its edges has too few clean crossings (`MIN_SAMPLES`), scatters by more than `MAX_FIT_RMS_PX`, or the
    intersection lands more than `MAX_MOVE_PX` away.
    """
    grey = np.asarray(grey, dtype=np.float64)
    grid = np.asarray(pixels, dtype=np.float64).reshape(rows, cols, 2)
    if half_width is None:
        half_width = int(np.clip(np.ceil(2.5 * edge_blur_px(grey, grid) + 1.0), 2, MAX_HALF_WIDTH))
    refined = grid.reshape(-1, 2).copy()
    mask = np.zeros(rows * cols, dtype=bool)
    for r in range(rows):
        for c in range(cols):
            along_rows = _half_edges(grid, r, c, 0)
            along_cols = _half_edges(grid, r, c, 1)
            dir_rows = along_rows[0] - along_rows[1]
            dir_cols = along_cols[0] - along_cols[1]
            first = _edge_line(grey, grid[r, c], along_cols, dir_rows, half_width)
            second = _edge_line(grey, grid[r, c], along_rows, dir_cols, half_width)
            if first is None or second is None:
                continue
            (p1, d1), (p2, d2) = first, second
            matrix = np.stack([d1, -d2], axis=1)
            if abs(np.linalg.det(matrix)) < 1e-3:
                continue
            s1, _ = np.linalg.solve(matrix, p2 - p1)
            corner = p1 + s1 * d1
            if np.linalg.norm(corner - grid[r, c]) <= MAX_MOVE_PX:
                refined[r * cols + c] = corner
                mask[r * cols + c] = True
    return refined, mask
