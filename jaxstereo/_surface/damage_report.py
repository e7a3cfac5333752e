"""Damage over a stretch of breakwater: per-profile values, averaged profile, 3-D volumes, report files."""

from __future__ import annotations

import csv
import dataclasses
import io
import json
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view
from scipy import ndimage

from .._app.io import write_text_atomic
from .._geometry.errors import JaxStereoError
from .._geometry.types import PathLike, Vector2
from .damage import DemDamage, ProfileDamage, damage_level, dem_damage, profile_damage, slope_abscissa, to_slope_frame
from .grid import DEM
from .nan_median import nan_median
from .seen_change import SEEN_TOLERANCE_M, change_where_seen, on_common_cells
from .slope_direction import DIRECTIONS, mirrored_in_x, slope_direction

if TYPE_CHECKING:
    from .damage_uncertainty import DamageSigma

ACTIVE_ZONE_DN50 = (6.0, 4.0)  # erosion counted from 6 Dn50 below to 4 Dn50 above the SWL, along the slope


@dataclasses.dataclass(frozen=True)
class StretchDamage:
    """Damage of a tested stretch between two DEMs.

    **Fields:** `profiles` (y (m), ProfileDamage) per cross-shore section inside the stretch; `skipped`
    (y (m), reason) for the sections that could not be computed; `averaged` the damage of the profile
    averaged over the stretch's width (the stretch's characteristic S); `S_mean` mean of per-profile S
    above `threshold`; `S_max`, `L_e_max`, `d_e_max` over the profiles (`S_max_y` where S is largest);
    `volumes` (DemDamage, E3D None when not measurable); `level` the damage level of the characteristic S on
    this slope; `stretch` (y0, y1) metres and `whole_width` (True when no stretch was given: the whole
    surveyed width); `active_zone` (z_low, z_high) metres: the heights on the design slope between which
    erosion is counted; the design slope (`cot`, `origin`), `dn50`, `swl`; `seen_tolerance` (m) and `carried`:
    the share of the compared cells (0-1) where one survey did not see the surface wholly and the change was
    carried from the cells around it that both saw (see `seen_change.py`); `rises_toward` the direction along x in
    which the design slope rises ("+x" or "-x", see `slope_direction`).
    """

    profiles: list[tuple[float, ProfileDamage]]
    skipped: list[tuple[float, str]]
    averaged: ProfileDamage
    S_mean: float
    S_max: float
    L_e_max: float
    d_e_max: float
    volumes: DemDamage
    level: str
    cot: float
    origin: tuple[float, float]
    dn50: float
    swl: float
    threshold: float
    stretch: tuple[float, float]
    whole_width: bool
    active_zone: tuple[float, float]
    seen_tolerance: float = float("inf")
    carried: float = 0.0
    rises_toward: str = "+x"

    @property
    def S_max_y(self) -> float:
        """The y (m) of the profile with the largest S (the first such profile on a tie)."""
        return max(self.profiles, key=lambda item: item[1].S)[0]

    def to_dict(self) -> dict:
        return {
            "dn50_m": self.dn50, "slope_cot": self.cot, "swl_m": self.swl,
            "design_slope_origin_xz_m": list(self.origin), "slope_rises_toward": self.rises_toward,
            "stretch_y_m": list(self.stretch), "whole_surveyed_width": self.whole_width,
            "active_zone_z_m": list(self.active_zone),
            "change_carried_from_seen_cells": {
                "share_of_cells": self.carried,
                "coverage_tolerance_m": self.seen_tolerance if np.isfinite(self.seen_tolerance) else None},
            "averaged_profile": profile_figures(self.averaged),
            "S_mean_above_threshold": self.S_mean, "S_threshold": self.threshold, "S_max": self.S_max,
            "S_max_at_y_m": self.S_max_y,
            "L_e_max_m": self.L_e_max, "d_e_max_m": self.d_e_max,
            "eroded_volume_m3": self.volumes.eroded_m3, "accreted_volume_m3": self.volumes.accreted_m3,
            "E3D": self.volumes.E3D, "E3D_at_xy_m": list(self.volumes.E3D_xy) if self.volumes.E3D_xy else None,
            "damage_level": self.level,
            "profiles": [{"y_m": y, **profile_figures(p),
                          "damage_level": damage_level(p.S, self.cot), "erosion_zones": len(p.erosion),
                          "accretion_zones": len(p.accretion), "erosion": [_zone_dict(z) for z in p.erosion]}
                         for y, p in self.profiles],
            "profiles_not_computed": [{"y_m": y, "reason": why} for y, why in self.skipped],
        }


def profile_figures(p) -> dict:
    """A `ProfileDamage`'s figures by their report names: `A_e_m2`, `L_e_m`, `d_e_m` (metres), `S`, `E2D`."""
    return {"A_e_m2": p.A_e, "L_e_m": p.L_e, "d_e_m": p.d_e, "S": p.S, "E2D": p.E2D}


def _zone_dict(zone) -> dict:
    """One erosion zone for the report: its ends along the slope (m, `slope_abscissa`'s), area and depth."""
    return {"start_m": zone.start, "end_m": zone.end, "A_e_m2": zone.area, "d_e_m": zone.depth}


def fit_design_slope(x: np.ndarray, z: np.ndarray, cot: float, swl: float, dn50: float) -> tuple[tuple[float, float], float]:
    """The design slope line `z = (x - x0) / cot`, or `z = (x0 - x) / cot` (a slope rising toward -x), whichever
    fits the better, fitted (median) to a profile's points within 3 Dn50 of the still water level. **Returns:**
    `((x0, 0), rms)`: a point of the line and the RMS distance (m) of those points from it, normal to the slope."""
    ok = np.isfinite(z) & (np.abs(z - swl) <= 3 * dn50)
    if ok.sum() < 3:
        raise JaxStereoError("the initial profile has too few points near the still water level to fit the "
                             "design slope; give its origin instead")
    fits = []
    for run in (cot, -cot):  # x per metre of rise
        x0 = float(np.median(x[ok] - run * z[ok]))
        normal = (z[ok] - (x[ok] - x0) / run) * cot / np.hypot(cot, 1.0)
        fits.append(((x0, 0.0), float(np.sqrt(np.mean(normal**2)))))
    return min(fits, key=lambda fit: fit[1])


def despike(dem: DEM, tolerance_m: float) -> DEM:
    """Remove single-cell spikes: a cell more than `tolerance_m` above all of its 8 neighbours, or below all
    of them, takes the nearest neighbour value. Such cells are survey outliers (mismatches at the edges of
    armour units), not surface; steep but continuous surfaces (the walls of a hole) are left alone."""
    z = dem.z
    finite = np.isfinite(z)
    around = np.ones((3, 3), bool)
    around[1, 1] = False  # the 8 neighbours
    high = ndimage.maximum_filter(np.where(finite, z, -np.inf), footprint=around, mode="constant", cval=-np.inf)
    low = ndimage.minimum_filter(np.where(finite, z, np.inf), footprint=around, mode="constant", cval=np.inf)
    enough = ndimage.correlate(finite.astype(np.int32), around.astype(np.int32), mode="constant") >= 5
    peak = enough & finite & (z - high > tolerance_m)
    pit = enough & finite & (low - z > tolerance_m)
    return DEM(dem.x, dem.y, np.where(peak, high, np.where(pit, low, z)), dem.spacing)


FOOT_STEPS_PER_RADIUS = 3  # the ball is closed on a grid with at least this many steps along its radius


def profiler_foot(dem: DEM, radius_m: float) -> DEM:
    """The surface as a profiler's ball foot of radius `radius_m` sees it: single-cell spikes removed
    (`despike`), then a grey closing with that ball, which bridges crevices narrower than the foot
    between armour units (NaN cells stay NaN and do not pull their neighbours down).

    The closing runs on the DEM's bilinear surface sampled at least `FOOT_STEPS_PER_RADIUS` times along the
    radius, and is read back at the cells' centres. On the cells themselves a ball of Dn50 / 4 on a 5 mm DEM is
    three heights (9, 7.5 and 5.6 mm) that sink between them into pits the ball cannot enter. On the POV-Ray
    flume's true stage I and III surfaces, as 5 mm DEMs of cell medians, `stretch_damage`'s 25 profiles within
    60 mm of the hole then put `d_e` 3.9 mm RMS off the one the ball gives on the true 1 mm surfaces (`A_e`
    5.2 % RMS); closed on 2.5 mm steps, 3.3 mm (`A_e` 3.1 %). From the wet surveys, over all 115 profiles,
    `d_e` 6.1 -> 5.5 mm RMS. A DEM coarser than the radius is closed the same way (it was left as it was).
    """
    if radius_m <= 0:
        return dem
    dem = despike(dem, radius_m)
    factor = int(np.ceil(FOOT_STEPS_PER_RADIUS * dem.spacing / radius_m))
    z = _refined(dem.z, factor)
    step = dem.spacing / factor
    r = int(np.floor(radius_m / step))
    yy, xx = np.mgrid[-r : r + 1, -r : r + 1] * step
    inside = xx**2 + yy**2 <= radius_m**2
    ball = np.where(inside, np.sqrt(np.clip(radius_m**2 - xx**2 - yy**2, 0.0, None)), 0.0)
    missing = ~np.isfinite(z)
    big = 1e6
    raised = ndimage.grey_dilation(np.where(missing, -big, z), footprint=inside, structure=ball)
    raised = np.where(raised < -big / 2, big, raised)
    closed = ndimage.grey_erosion(raised, footprint=inside, structure=ball)[::factor, ::factor]
    return DEM(dem.x, dem.y, np.where(np.isfinite(dem.z), closed, np.nan), dem.spacing)


def _refined(z: np.ndarray, factor: int) -> np.ndarray:
    """The bilinear surface through the cells' heights `z` (ny, nx) sampled `factor` times finer, on
    ((ny - 1) factor + 1, (nx - 1) factor + 1) points; every `factor`-th is a cell's centre. NaN wherever a cell
    that weighs in is NaN."""
    if factor == 1:
        return z
    for axis in (0, 1):
        z = np.moveaxis(z, axis, 0)
        t = (np.arange(1, factor) / factor)[None, :, None]
        between = (1 - t) * z[:-1, None] + t * z[1:, None]  # (n - 1, factor - 1, m)
        fine = np.concatenate([z[:-1, None], between], axis=1).reshape(-1, z.shape[1])
        z = np.moveaxis(np.concatenate([fine, z[-1:]]), 0, axis)
    return z


def _column_mean(z: np.ndarray) -> np.ndarray:
    """Mean over rows ignoring NaN; NaN for columns without data (no warning)."""
    count = np.isfinite(z).sum(axis=0)
    total = np.nansum(z, axis=0)
    return np.where(count > 0, total / np.maximum(count, 1), np.nan)


# An initial cross-section is the armour's when the sections within Dn50 of it lie, median over the active zone,
# at most 1 Dn50 under the design slope (deeper: the underlayer beside the armour, the floor before the toe) and at
# most 2 Dn50 over it (the armour's rocks stand over the line by up to their size).
ON_SLOPE_DN50 = (1.0, 2.0)


def _off_the_slope(x, z, cot, origin, zone, dn50, spacing: float) -> dict[int, str]:
    """Why each initial cross-section (the rows of `z` (m, n) over the abscissae `x` (n,), metres; rows `spacing`
    metres apart, in order) is not one of the structure's, for those that are not (row -> reason): each section's
    median signed distance from the design slope line over the active zone (positive outwards), and the median of
    these over the strip of sections within Dn50 of it must lie within `ON_SLOPE_DN50` (under, over) Dn50 of the
    line. Sections past the sides of the model (the underlayer beside the armour, the bare floor) fail this.

    The strip, signed, and not the section's distance alone: a 5 mm section can run along the flank of one rock,
    and with the active zone high on the slope (a deep SWL) over the crest's edge too. On the POV-Ray flume's
    stage I, with the SWL given at 0.25 m and the test on each section's median distance (within 1 Dn50), two
    sections through the stage III hole's rows lay 46 and 58 mm off the slope; with their neighbours within Dn50
    the hole itself was left out, and the profile nearest it read none of its eroded area. The strips there lie
    10-44 mm over the line; with the SWL anywhere from 0.08 to 0.28 m, in the wet and the dry surveys, the
    armour's strips away from its sides lie between 16 mm under it and 44 mm over it, the underlayer's past the
    model's sides 58 mm or more under it. (The median of the sections' medians, not of the strip's cells: on a 1 mm
    DEM the strip holds 73 sections, and its cells took 1 GB.)
    """
    X, Z = to_slope_frame(np.broadcast_to(x, z.shape), z, cot, origin)
    inside = np.isfinite(z) & (X >= zone[0]) & (X <= zone[1])
    count = inside.sum(axis=1)
    section = nan_median(np.where(inside, Z, np.nan), axis=1)  # each section's own median (m,)
    k = int(np.rint(dn50 / spacing))
    offset = nan_median(sliding_window_view(np.pad(section, k, constant_values=np.nan), 2 * k + 1), axis=1)
    under, over = ON_SLOPE_DN50
    reasons = {}
    for r in range(z.shape[0]):
        if count[r] < 3:
            reasons[r] = "no initial data in the active zone"
        elif not -under * dn50 <= offset[r] <= over * dn50:
            side = "under" if offset[r] < 0 else "over"
            reasons[r] = (f"the initial sections within Dn50 of it lie {1e3 * abs(offset[r]):.0f} mm (median) {side} "
                          "the design slope: not a cross-section of the structure")
    return reasons


def _section_rows(before: DEM, after: DEM, cot, origin, zone, dn50, stretch):
    """The DEM rows that are cross-sections of the structure inside the stretch, the (y, reason) of those left
    out, and the stretch's extent (y0, y1)."""
    both = np.isfinite(before.z) & np.isfinite(after.z)
    covered = both.sum(axis=1) >= 0.2 * both.shape[1]
    if not covered.any():
        raise JaxStereoError("the before and after surfaces do not overlap (no cross-section with data in both)")
    off_the_slope = _off_the_slope(before.x, before.z, cot, origin, zone, dn50, before.spacing)
    reasons = {r: why for r, why in off_the_slope.items() if covered[r]}
    structure = covered.copy()
    structure[list(reasons)] = False
    if not structure.any():
        raise JaxStereoError(f"no cross-section of the initial survey follows the design slope: {next(iter(reasons.values()))}")
    # Sections within Dn50 of the structure's sides see its side faces, where a lateral shift between the
    # surveys would read as erosion: they are left out too.
    margin = int(round(dn50 / before.spacing))
    inner = ndimage.binary_erosion(structure, np.ones(2 * margin + 1, bool), border_value=0)
    for r in np.nonzero(structure & ~inner)[0]:
        reasons[r] = "within Dn50 of the side of the surveyed structure"
    if not inner.any():
        raise JaxStereoError("the surveyed structure is narrower than 2 Dn50: no cross-section away from its sides")
    if stretch is not None:
        y0, y1 = sorted(float(v) for v in stretch)
        in_stretch = (before.y >= y0) & (before.y <= y1)
        if not (in_stretch & covered).any():
            raise JaxStereoError(f"the stretch y {y0:.3f} to {y1:.3f} m lies outside the surveys (y "
                                 f"{before.y[0]:.3f} to {before.y[-1]:.3f} m)")
        rows = np.nonzero(inner & in_stretch)[0]
        if rows.size == 0:
            raise JaxStereoError(f"no cross-section of the structure in the stretch y {y0:.3f} to {y1:.3f} m")
        extent = (y0, y1)
    else:
        rows = np.nonzero(inner)[0]
        extent = (float(before.y[rows[0]]), float(before.y[rows[-1]]))
    skipped = sorted((float(before.y[r]), why) for r, why in reasons.items() if extent[0] <= before.y[r] <= extent[1])
    return rows, skipped, extent


def stretch_damage(before: DEM, after: DEM, dn50: float, cot: float, swl: float, origin: Vector2 | None,
                   profile_spacing_m: float | None = None, threshold: float = 0.5,
                   stretch: tuple[float, float] | None = None,
                   active_zone_dn50: tuple[float, float] = ACTIVE_ZONE_DN50,
                   foot_radius_m: float | None = None, seen_tolerance_m: float | None = None,
                   rises_toward: str | None = None) -> StretchDamage:
    """Damage of a tested stretch between two DEMs on one grid (x cross-shore, y along the breakwater).

    **Arguments:** the DEMs; `dn50` (m); `cot` the design slope's cotangent; `swl` still water level (m); `origin`
    (x, z) a point of the design slope line, e.g. its toe (see `fit_design_slope` to fit one); `profile_spacing_m`
    between cross-sections (default Dn50); `threshold` of per-profile S for `S_mean`; `stretch` (y0, y1) the tested
    stretch (characterisation width), metres (None: the whole surveyed width); `active_zone_dn50` (below, above):
    the erosion zones counted are those reaching into the zone from `below` Dn50 under the SWL to `above` Dn50 over
    it, along the design slope, each whole (`profile_damage`); `foot_radius_m` the radius of the profiler's foot the
    surfaces are seen with (default Dn50 / 4; 0: the raw DEMs), see `profiler_foot`; `seen_tolerance_m`: a cell
    whose coverage std (`sigma_coverage`, metres) exceeds it in either survey takes the change of the cells around
    it that both saw wholly (default 0: any cell not seen wholly; `math.inf`: every cell compared as surveyed), see
    `seen_change.py`; `rises_toward` "+x" or "-x", the direction along x in which the design slope rises (None:
    the one the initial DEM follows, see `slope_direction`; a slope rising toward -x is computed on the DEMs
    mirrored in x, and the result given back in the DEMs' own frame).

    The two DEMs are compared on the cells both hold (`on_common_cells`): a cell one survey lacks has no change.
    The characteristic S is that of the profile averaged over the stretch (de Almeida, van Gent and
    Hofland 2019); its damage level uses the thresholds of this slope. A cross-section that cannot be
    computed is listed with its reason; none at all is an error.
    """
    if before.z.shape != after.z.shape:
        raise JaxStereoError("the two surfaces are not on the same grid")
    if origin is None:
        raise JaxStereoError("give the design slope's origin (a point of the slope line, e.g. its toe), or fit "
                             "one with fit_design_slope")
    below, above = (float(v) for v in active_zone_dn50)
    if below < 0 or above < 0 or below + above <= 0:
        raise JaxStereoError(f"the active zone must extend below and/or above the SWL, got {active_zone_dn50} Dn50")
    if rises_toward is not None and rises_toward not in DIRECTIONS:
        raise JaxStereoError(f"rises_toward must be one of {', '.join(DIRECTIONS)} (or None), got {rises_toward!r}")
    direction = rises_toward or slope_direction(before, cot, swl, origin, dn50)
    if direction == "-x":
        result = stretch_damage(mirrored_in_x(before), mirrored_in_x(after), dn50, cot, swl, (-origin[0], origin[1]),
                                profile_spacing_m, threshold=threshold, stretch=stretch,
                                active_zone_dn50=active_zone_dn50, foot_radius_m=foot_radius_m,
                                seen_tolerance_m=seen_tolerance_m, rises_toward="+x")
        xy = result.volumes.E3D_xy
        volumes = dataclasses.replace(result.volumes, E3D_xy=None if xy is None else (-xy[0], xy[1]))
        return dataclasses.replace(result, origin=(float(origin[0]), float(origin[1])), volumes=volumes,
                                   rises_toward="-x")
    tolerance = SEEN_TOLERANCE_M if seen_tolerance_m is None else float(seen_tolerance_m)
    after, carried = change_where_seen(before, after, tolerance, dn50)
    before, after = on_common_cells(before, after)  # a cell one survey lacks has no change to measure
    foot = dn50 / 4 if foot_radius_m is None else float(foot_radius_m)
    before, after = profiler_foot(before, foot), profiler_foot(after, foot)
    x_swl = slope_abscissa(swl, cot, origin)
    zone = (x_swl - below * dn50, x_swl + above * dn50)
    norm = float(np.hypot(cot, 1.0))
    zone_z = (swl - below * dn50 / norm, swl + above * dn50 / norm)
    rows, skipped, extent = _section_rows(before, after, cot, origin, zone, dn50, stretch)
    both = np.isfinite(before.z) & np.isfinite(after.z)
    mean_before = _column_mean(np.where(both[rows], before.z[rows], np.nan))
    mean_after = _column_mean(np.where(both[rows], after.z[rows], np.nan))
    averaged = profile_damage((before.x, mean_before), (before.x, mean_after), dn50, cot, origin, zone)
    step = max(1, int(round((profile_spacing_m or dn50) / before.spacing)))
    profiles = []
    for r in rows[::step]:
        try:
            profiles.append((float(before.y[r]), profile_damage((before.x, before.z[r]), (after.x, after.z[r]), dn50,
                                                                cot, origin, zone)))
        except JaxStereoError as err:
            skipped.append((float(before.y[r]), str(err)))
    if not profiles:
        raise JaxStereoError(f"no cross-section could be computed: {skipped[0][1]}")
    s_values = np.array([p.S for _, p in profiles])
    above_threshold = s_values[s_values > threshold]
    outside = (before.y < extent[0]) | (before.y > extent[1])
    volumes = dem_damage(*(DEM(d.x, d.y, np.where(outside[:, None], np.nan, d.z), d.spacing) for d in (before, after)),
                         dn50)
    return StretchDamage(
        profiles=profiles, skipped=skipped, averaged=averaged,
        S_mean=float(above_threshold.mean()) if above_threshold.size else 0.0, S_max=float(s_values.max()),
        L_e_max=max(p.L_e for _, p in profiles), d_e_max=max(p.d_e for _, p in profiles), volumes=volumes,
        level=damage_level(averaged.S, cot), cot=cot, origin=tuple(float(v) for v in origin), dn50=dn50, swl=swl,
        threshold=threshold, stretch=extent, whole_width=stretch is None, active_zone=zone_z,
        seen_tolerance=tolerance, carried=_carried_share(carried, before, after, extent),
    )


def _carried_share(carried: np.ndarray, before: DEM, after: DEM, extent: tuple[float, float]) -> float:
    """The share (0-1) of the cells with data in both DEMs, inside the stretch `extent` (y0, y1), whose change
    was carried from a seen cell."""
    inside = ((before.y >= extent[0]) & (before.y <= extent[1]))[:, None]
    compared = inside & np.isfinite(before.z) & np.isfinite(after.z)
    return float((carried & compared).sum() / max(compared.sum(), 1))


def write_damage_report(result: StretchDamage, before: DEM, after: DEM, out_dir: PathLike,
                        sigma: "DamageSigma | None" = None) -> list[Path]:
    """Write `damage.json`, `profiles.csv`, `profile.png` (averaged profiles, eroded area shaded) and
    `difference.png` (DEM difference map) to `out_dir`, each atomically. With `sigma` (a `DamageSigma`), every
    figure's standard deviation goes beside it (`"sigma"` in the JSON, for the stretch and for each profile, with
    `S_sigma` per profile; a `*_sigma` column beside each profile's figure in the CSV; value +- sigma and 2-sigma
    bands on the figure), and its 95 % interval (`DamageSigma.interval`: `"interval_95"` in the JSON, `*_low` and
    `*_high` columns in the CSV, on the figure's title for S). Returns the paths."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    report = result.to_dict()
    if sigma is not None:
        report["sigma"] = sigma.sigma
        report["interval_95"] = sigma.stretch_intervals(report)
        report["sigma_from"] = {"draws": sigma.draws, "failed_draws": sigma.failed,
                                "calibration_shared_by_both_surveys": sigma.shared_calibration,
                                "water_level_shared_by_both_surveys": sigma.shared_level,
                                "interval_95": "the wider of value +- 2 sigma and the middle 95 % of the draws"}
        for row in report["profiles"]:
            figures = sigma.profile_sigma.get(round(row["y_m"], 6))
            row["S_sigma"] = None if figures is None else figures["S"]
            row["sigma"] = figures
            row["interval_95"] = sigma.intervals({key: row[key] for key in (figures or {})}, row["y_m"]) or None
    write_text_atomic(out / "damage.json", json.dumps(report, indent=2) + "\n")
    write_text_atomic(out / "profiles.csv", _profiles_csv(result, sigma))
    compared, _ = change_where_seen(before, after, result.seen_tolerance, result.dn50)  # the after-surface used
    _plot_averaged_profile(result, before, compared, out / "profile.png", sigma)
    _plot_difference(result, before, compared, out / "difference.png")
    return [out / name for name in ("damage.json", "profiles.csv", "profile.png", "difference.png")]


_CSV_FIGURES = (("A_e_m2", "A_e_{}_m2", "{:.6g}"), ("L_e_m", "L_e_{}_m", "{:.5g}"), ("d_e_m", "d_e_{}_m", "{:.5g}"),
                ("S", "S_{}", "{:.4g}"), ("E2D", "E2D_{}", "{:.4g}"))


def _profiles_csv(result: StretchDamage, sigma=None) -> str:
    """One row per profile (y order): its damage, each figure with its standard deviation and the low and high
    ends of its 95 % interval when known (metres, square metres), and its level; or why it was not computed."""
    buf = io.StringIO()
    writer = csv.writer(buf)
    writer.writerow(["y_m", *(name for key, column, _ in _CSV_FIGURES
                              for name in (key, *(column.format(part) for part in ("sigma", "low", "high")))),
                     "damage_level", "note"])
    rows = [(y, p, "") for y, p in result.profiles] + [(y, None, why) for y, why in result.skipped]
    for y, p, why in sorted(rows, key=lambda r: r[0]):
        if p is None:
            writer.writerow([f"{y:.4f}", *[""] * (4 * len(_CSV_FIGURES)), "not computed", why])
            continue
        values = profile_figures(p)
        sigmas = sigma.profile_sigma.get(round(y, 6)) if sigma is not None else None
        cells = []
        for key, _, fmt in _CSV_FIGURES:
            bounds = sigma.interval(key, values[key], y) if sigma is not None else None
            cells += [fmt.format(values[key]), "" if sigmas is None else f"{sigmas[key]:.3g}",
                      *(["", ""] if bounds is None else [f"{bound:.3g}" for bound in bounds])]
        writer.writerow([f"{y:.4f}", *cells, damage_level(p.S, result.cot), ""])
    return buf.getvalue()


def averaged_profile_sigma(dem: DEM, rows: np.ndarray) -> np.ndarray | None:
    """The vertical std (nx,) metres of a DEM's profile averaged over `rows`: the matching part averages over the
    rows' independent stretches (one per `correlation_m`), the shared parts do not. None without sigma layers."""
    if not dem.has_sigma:
        return None
    ok = np.isfinite(dem.z[rows])
    n = ok.sum(axis=0)
    independent = np.maximum(1.0, n * dem.spacing / dem.correlation_m) if np.isfinite(dem.correlation_m) else n
    match = np.sqrt(_column_mean(np.where(ok, dem.sigma_match[rows] ** 2, np.nan)) / np.maximum(independent, 1.0))
    shared = [_column_mean(np.where(ok, getattr(dem, key)[rows], np.nan)) for key in ("sigma_calibration", "sigma_level")]
    return np.sqrt(match**2 + shared[0] ** 2 + shared[1] ** 2)


def _plot_averaged_profile(result: StretchDamage, before: DEM, after: DEM, path: Path, sigma=None) -> None:
    """The stretch's averaged profiles before and after (with 2-sigma bands when known), the active zone, eroded
    and accreted areas shaded."""
    from .._app.plots import new_figure, save_figure

    in_stretch = (before.y >= result.stretch[0]) & (before.y <= result.stretch[1])
    both = np.isfinite(before.z) & np.isfinite(after.z) & in_stretch[:, None]
    zb = _column_mean(np.where(both, before.z, np.nan))
    za = _column_mean(np.where(both, after.z, np.nan))
    fig, ax = new_figure(figsize=(9, 4.2))
    width = "whole surveyed width" if result.whole_width else "tested stretch"
    ax.plot(before.x, zb, color="0.3", label=f"initial (averaged, {width})")
    ax.plot(before.x, za, color="tab:red", label=f"final (averaged, {width})")
    rows = np.nonzero(in_stretch)[0]
    for dem, z, colour in ((before, zb, "0.3"), (after, za, "tab:red")):
        band = averaged_profile_sigma(dem, rows)
        if band is not None:
            ax.fill_between(before.x, z - 2 * band, z + 2 * band, color=colour, alpha=0.15, lw=0,
                            label="2 sigma" if dem is before else None)
    x0, z0 = result.origin
    run = result.cot if result.rises_toward == "+x" else -result.cot  # x per metre of rise along the design slope
    zone_x = sorted(x0 + (z - z0) * run for z in result.active_zone)
    ax.axvspan(*zone_x, color="0.85", zorder=0,
               label=f"active zone (z {result.active_zone[0]:.3f} to {result.active_zone[1]:.3f} m)")
    ax.fill_between(before.x, za, zb, where=za < zb, color="tab:red", alpha=0.3, label="eroded")
    ax.fill_between(before.x, za, zb, where=za > zb, color="tab:blue", alpha=0.3, label="accreted")
    xs = np.array([before.x[0], before.x[-1]])
    ax.plot(xs, z0 + (xs - x0) / run, ls="--", color="0.6", lw=0.8,
            label=f"design slope 1:{result.cot:g}, rising toward {result.rises_toward}")
    ax.axhline(result.swl, color="tab:blue", lw=0.8, ls=":", label="SWL")
    ax.set_ylim(np.nanmin(zb) - 0.05, np.nanmax(zb) + 0.05)
    ax.set_xlabel("x (m)")
    ax.set_ylabel("z (m)")
    e3d = "not measurable" if result.volumes.E3D is None else f"{result.volumes.E3D:.2f}"
    s_text = f"{result.averaged.S:.2f}"
    bounds = sigma.interval("S", result.averaged.S) if sigma is not None else None
    if bounds is not None:
        s_text += f" +- {sigma.sigma['S']:.2f} (95 %: {bounds[0]:.2f} to {bounds[1]:.2f})"
    ax.set_title(f"y {result.stretch[0]:.3f} to {result.stretch[1]:.3f} m ({width}): S = {s_text}\n"
                 f"{result.level} on 1:{result.cot:g}, E2D = {result.averaged.E2D:.2f}, E3D = {e3d}", fontsize=9)
    ax.legend(fontsize=8, loc="upper left")
    ax.grid(alpha=0.3)
    save_figure(fig, path)


def _plot_difference(result: StretchDamage, before: DEM, after: DEM, path: Path) -> None:
    """Map of the DEM difference (mm), the stretch's edges and the E3D disc's place."""
    from .._app.plots import new_figure, save_figure

    fig, ax = new_figure(figsize=(8, 5))
    diff = 1e3 * (after.z - before.z)
    lim = np.nanpercentile(np.abs(diff), 99) if np.isfinite(diff).any() else 1.0
    im = ax.imshow(diff, origin="lower", cmap="RdBu", vmin=-lim, vmax=lim,
                   extent=(before.x[0], before.x[-1], before.y[0], before.y[-1]))
    if result.volumes.E3D_xy is not None:
        ax.plot(*result.volumes.E3D_xy, "k+", ms=12, label="E3D location")
    for k, y in enumerate(result.stretch):
        ax.axhline(y, color="k", lw=0.8, ls="--",
                   label=None if k else ("whole surveyed width" if result.whole_width else "tested stretch"))
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(f"DEM difference (mm): eroded {1e6 * result.volumes.eroded_m3:.0f} cm^3, "
                 f"accreted {1e6 * result.volumes.accreted_m3:.0f} cm^3\n{100 * result.carried:.0f} % of the cells "
                 "take the change of the cells around them that both surveys saw wholly", fontsize=9)
    ax.legend(fontsize=8)
    fig.colorbar(im, ax=ax, label="after - before (mm)")
    save_figure(fig, path)
