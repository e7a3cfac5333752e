"""Damage over a stretch of breakwater: per-profile values, averaged profile, 3-D volumes, report files."""

from __future__ import annotations

import csv
import dataclasses
import io
import json
from pathlib import Path

import numpy as np

from ._damage import DemDamage, ProfileDamage, damage_level, dem_damage, profile_damage
from ._errors import JaxStereoError
from ._grid import DEM
from ._io import write_text_atomic


@dataclasses.dataclass(frozen=True)
class StretchDamage:
    """Damage of a stretch: `profiles` (y (m), ProfileDamage) per cross-shore section; `averaged` the
    width-averaged profile's damage; `S_mean` mean of per-profile S above `threshold`; `S_max`,
    `L_e_max`, `d_e_max` over the profiles; `volumes` (DemDamage); `level` of the averaged S; the design
    slope (`cot`, `origin`), `dn50`, `swl`."""

    profiles: list[tuple[float, ProfileDamage]]
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

    def to_dict(self) -> dict:
        return {
            "dn50_m": self.dn50, "slope_cot": self.cot, "swl_m": self.swl,
            "design_slope_origin_xz_m": list(self.origin),
            "averaged_profile": {"A_e_m2": self.averaged.A_e, "L_e_m": self.averaged.L_e, "d_e_m": self.averaged.d_e,
                                 "S": self.averaged.S, "E2D": self.averaged.E2D},
            "S_mean_above_threshold": self.S_mean, "S_threshold": self.threshold, "S_max": self.S_max,
            "L_e_max_m": self.L_e_max, "d_e_max_m": self.d_e_max,
            "eroded_volume_m3": self.volumes.eroded_m3, "accreted_volume_m3": self.volumes.accreted_m3,
            "E3D": self.volumes.E3D, "E3D_at_xy_m": list(self.volumes.E3D_xy), "damage_level": self.level,
            "profiles": [{"y_m": y, "A_e_m2": p.A_e, "L_e_m": p.L_e, "d_e_m": p.d_e, "S": p.S, "E2D": p.E2D,
                          "erosion_zones": len(p.erosion), "accretion_zones": len(p.accretion)}
                         for y, p in self.profiles],
        }


def fit_design_slope(x: np.ndarray, z: np.ndarray, cot: float, swl: float, dn50: float) -> tuple[float, float]:
    """A point `(x0, 0)` of the design slope line `z = (x - x0) / cot`, fitted (median) to the profile's
    points within 3 Dn50 of the still water level."""
    ok = np.isfinite(z) & (np.abs(z - swl) <= 3 * dn50)
    if ok.sum() < 3:
        raise JaxStereoError("the initial profile has too few points near the still water level to place the "
                             "design slope; give its origin explicitly")
    return float(np.median(x[ok] - cot * z[ok])), 0.0


def _column_mean(z: np.ndarray) -> np.ndarray:
    """Mean over rows ignoring NaN; NaN for columns without data (no warning)."""
    count = np.isfinite(z).sum(axis=0)
    total = np.nansum(z, axis=0)
    return np.where(count > 0, total / np.maximum(count, 1), np.nan)


def _cross_shore(dem: DEM, row: int):
    return dem.x, dem.z[row]


def stretch_damage(before: DEM, after: DEM, dn50: float, cot: float, swl: float, origin=None,
                   profile_spacing_m: float | None = None, threshold: float = 0.5) -> StretchDamage:
    """Damage between two DEMs on one grid (x cross-shore, y along the breakwater).

    Cross-shore profiles are taken every `profile_spacing_m` (default Dn50) along y; the design slope
    passes through `origin` (x, z) or is fitted to the width-averaged initial profile near the SWL.
    """
    if before.z.shape != after.z.shape:
        raise JaxStereoError("the two surfaces are not on the same grid")
    both = np.isfinite(before.z) & np.isfinite(after.z)
    rows = np.nonzero(both.sum(axis=1) >= 0.2 * both.shape[1])[0]
    if rows.size == 0:
        raise JaxStereoError("the before and after surfaces do not overlap")
    mean_before = _column_mean(np.where(both[rows], before.z[rows], np.nan))
    mean_after = _column_mean(np.where(both[rows], after.z[rows], np.nan))
    if origin is None:
        origin = fit_design_slope(before.x, mean_before, cot, swl, dn50)
    averaged = profile_damage((before.x, mean_before), (before.x, mean_after), dn50, cot, origin)
    step = max(1, int(round((profile_spacing_m or dn50) / before.spacing)))
    profiles = []
    for r in rows[::step]:
        try:
            profiles.append((float(before.y[r]), profile_damage(_cross_shore(before, r), _cross_shore(after, r), dn50,
                                                                cot, origin)))
        except JaxStereoError:
            continue
    s_values = np.array([p.S for _, p in profiles]) if profiles else np.zeros(1)
    above = s_values[s_values > threshold]
    volumes = dem_damage(before, after, dn50)
    return StretchDamage(
        profiles=profiles, averaged=averaged, S_mean=float(above.mean()) if above.size else 0.0,
        S_max=float(s_values.max()), L_e_max=max((p.L_e for _, p in profiles), default=0.0),
        d_e_max=max((p.d_e for _, p in profiles), default=0.0), volumes=volumes,
        level=damage_level(averaged.S, cot), cot=cot, origin=tuple(float(v) for v in origin), dn50=dn50, swl=swl,
        threshold=threshold,
    )


def write_damage_report(result: StretchDamage, before: DEM, after: DEM, out_dir) -> list[Path]:
    """Write `damage.json`, `profiles.csv`, `profile.png` (averaged profiles, eroded area shaded) and
    `difference.png` (DEM difference map) to `out_dir`, each atomically. Returns the paths."""
    from ._plots import new_figure, save_figure

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    write_text_atomic(out / "damage.json", json.dumps(result.to_dict(), indent=2) + "\n")
    paths.append(out / "damage.json")
    buf = io.StringIO()
    writer = csv.writer(buf)
    writer.writerow(["y_m", "A_e_m2", "L_e_m", "d_e_m", "S", "E2D"])
    for y, p in result.profiles:
        writer.writerow([f"{y:.4f}", f"{p.A_e:.6g}", f"{p.L_e:.5g}", f"{p.d_e:.5g}", f"{p.S:.4g}", f"{p.E2D:.4g}"])
    write_text_atomic(out / "profiles.csv", buf.getvalue())
    paths.append(out / "profiles.csv")
    both = np.isfinite(before.z) & np.isfinite(after.z)
    zb = _column_mean(np.where(both, before.z, np.nan))
    za = _column_mean(np.where(both, after.z, np.nan))
    fig, ax = new_figure(figsize=(9, 4.2))
    ax.plot(before.x, zb, color="0.3", label="initial (width-averaged)")
    ax.plot(before.x, za, color="tab:red", label="final (width-averaged)")
    ax.fill_between(before.x, za, zb, where=za < zb, color="tab:red", alpha=0.3, label="eroded")
    ax.fill_between(before.x, za, zb, where=za > zb, color="tab:blue", alpha=0.3, label="accreted")
    x0, z0 = result.origin
    xs = np.array([before.x[0], before.x[-1]])
    ax.plot(xs, z0 + (xs - x0) / result.cot, ls="--", color="0.6", lw=0.8, label=f"design slope 1:{result.cot:g}")
    ax.axhline(result.swl, color="tab:blue", lw=0.8, ls=":", label="SWL")
    lo, hi = np.nanmin(zb), np.nanmax(zb)
    ax.set_ylim(lo - 0.05, hi + 0.05)
    ax.set_xlabel("x (m)")
    ax.set_ylabel("z (m)")
    ax.set_title(f"S = {result.averaged.S:.2f}, E2D = {result.averaged.E2D:.2f}, E3D = {result.volumes.E3D:.2f} "
                 f"({result.level})")
    ax.legend(fontsize=8, loc="upper left")
    ax.grid(alpha=0.3)
    save_figure(fig, out / "profile.png")
    paths.append(out / "profile.png")

    fig, ax = new_figure(figsize=(8, 5))
    diff = 1e3 * (after.z - before.z)
    lim = np.nanpercentile(np.abs(diff), 99) if np.isfinite(diff).any() else 1.0
    im = ax.imshow(diff, origin="lower", cmap="RdBu", vmin=-lim, vmax=lim,
                   extent=(before.x[0], before.x[-1], before.y[0], before.y[-1]))
    ax.plot(*result.volumes.E3D_xy, "k+", ms=12, label="E3D location")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(f"DEM difference (mm): eroded {1e6 * result.volumes.eroded_m3:.0f} cm^3, "
                 f"accreted {1e6 * result.volumes.accreted_m3:.0f} cm^3")
    ax.legend(fontsize=8)
    fig.colorbar(im, ax=ax, label="after - before (mm)")
    save_figure(fig, out / "difference.png")
    paths.append(out / "difference.png")
    return paths
