"""Accuracy against ground truth: errors per layer of depth below the water."""

from __future__ import annotations

import numpy as np

from .._geometry.errors import JaxStereoError


def layer_errors(points: np.ndarray, true_z: np.ndarray, water_level: float, layer_m: float = 0.05,
                 min_points: int = 50) -> list[dict]:
    """Vertical errors of surveyed points grouped in layers of depth below the water.

    **Arguments:** `points` (N, 3) world metres; `true_z` (N,) the true surface height under each
    point, metres (NaN where unknown: such points are left out); `water_level` metres; `layer_m` layer
    thickness; layers with fewer than `min_points` points are left out.

    **Returns:** one dict per layer (shallowest first, emerged layers have negative depth) with
    `depth_from_m`, `depth_to_m`, `n`, `median_mm`, `rmse_mm`, `max_abs_mm`, `p95_abs_mm`. The layers' edges
    are whole multiples of `layer_m` (each computed as one product, not summed up from the shallowest), so that
    two surveys' layers share the same edges to the last digit, whatever depths each of them reaches.
    """
    err = points[:, 2] - true_z
    depth = water_level - true_z
    known = np.isfinite(err) & np.isfinite(depth)
    if not known.any():
        raise JaxStereoError(f"no point with a finite height and true height to evaluate ({len(err)} points given)")
    err, depth = err[known], depth[known]
    rows = []
    for k in range(int(np.floor(depth.min() / layer_m)), int(np.floor(depth.max() / layer_m)) + 1):
        start, stop = k * layer_m, (k + 1) * layer_m
        m = (depth >= start) & (depth < stop)
        if m.sum() < min_points:
            continue
        e = err[m]
        rows.append(dict(depth_from_m=float(start), depth_to_m=float(stop), n=int(m.sum()),
                         median_mm=float(1e3 * np.median(e)), rmse_mm=float(1e3 * np.sqrt(np.mean(e**2))),
                         max_abs_mm=float(1e3 * np.max(np.abs(e))), p95_abs_mm=float(1e3 * np.percentile(np.abs(e), 95))))
    return rows


def layer_table_markdown(results: dict[str, list[dict]], column: str = "median_mm") -> str:
    """One Markdown table, a row per depth layer and a column per model, of `column` (mm)."""
    models = list(results)
    layers = sorted({(r["depth_from_m"], r["depth_to_m"]) for rows in results.values() for r in rows})
    lines = ["| depth below water (m) | " + " | ".join(f"{m} {column.replace('_mm', '')} (mm)" for m in models) + " |",
             "|---|" + "---:|" * len(models)]
    for a, b in layers:
        cells = []
        for m in models:
            match = [r for r in results[m] if abs(r["depth_from_m"] - a) < 1e-9]
            cells.append(f"{match[0][column]:+.2f}" if match else "")
        lines.append(f"| {a:+.2f} to {b:+.2f} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def uncertainty_coverage(errors: np.ndarray, sigma: np.ndarray, heights: np.ndarray, layer_m: float = 0.05,
                         z_from: float = 0.0, z_to: float = 0.30, outlier_m: float = 0.02,
                         min_points: int = 500) -> list[dict]:
    """How honest predicted standard deviations are, per layer of height: predicted against measured error.

    **Arguments:** `errors` (N,) the points' true errors, `sigma` (N,) their predicted standard deviations
    along the same direction, `heights` (N,) world z, all metres; layers of `layer_m` from `z_from` to
    `z_to`; points off by more than `outlier_m` (gross mismatches, counted apart) are left out of the RMS.

    **Returns:** one dict per layer with at least `min_points` points: `z_from_m`, `n`, `within_2_sigma`
    (fraction of all points with |error| <= 2 sigma), `measured_rms_mm` and `predicted_rms_mm` (root mean
    square of the errors and of sigma, over points within `outlier_m`), and their `ratio` (predicted / measured).
    """
    rows = []
    for lo in np.arange(z_from, z_to - 1e-12, layer_m):
        m = (heights >= lo) & (heights < lo + layer_m)
        if m.sum() < min_points:
            continue
        e, s = errors[m], sigma[m]
        inlier = np.abs(e) < outlier_m
        measured = float(1e3 * np.sqrt(np.mean(e[inlier] ** 2)))
        predicted = float(1e3 * np.sqrt(np.mean(s[inlier] ** 2)))
        rows.append(dict(z_from_m=float(lo), n=int(m.sum()), within_2_sigma=float(np.mean(np.abs(e) <= 2 * s)),
                         measured_rms_mm=measured, predicted_rms_mm=predicted, ratio=predicted / measured))
    return rows
