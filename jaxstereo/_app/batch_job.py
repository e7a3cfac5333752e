"""One pair of a campaign as a job: plan (fingerprints), skip when finished, run (never raises).

A job writes into its pair's folder: `survey.npz`, `preview.png`, `dem.npz` (on the grid of its test's
reference stage), `damage/` and, last, `result.json` with the fingerprint of its inputs (image stamps,
rig digest, settings, the reference stage's fingerprint). A pair is finished when, and only when, that
file exists with the current fingerprint. A failed pair's folder is removed: it leaves no files.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import shutil
import time
from pathlib import Path

import numpy as np

from .._geometry.errors import JaxStereoError
from .io import write_text_atomic
from .manifest import DamageSettings, Manifest, PairEntry

RESULT = "result.json"


@dataclasses.dataclass(frozen=True)
class PairJob:
    """Everything one worker needs for one pair (picklable): the manifest entry, the pair's output
    folder, the rig file, reconstruction and grid settings (metres), damage settings, the reference
    stage's output folder (None for a reference stage) and the inputs' fingerprint."""

    pair: PairEntry
    out_dir: Path
    rig: Path
    model: str
    z_range: tuple[float, float] | None
    spacing: float
    max_gap: float
    damage: DamageSettings | None
    reference_dir: Path | None
    fingerprint: str


def _file_digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _image_stamp(path: Path) -> list:
    try:
        st = path.stat()
        return [str(path), st.st_size, st.st_mtime_ns]
    except OSError:
        return [str(path), None, None]


def plan_jobs(manifest: Manifest, output: Path) -> list[PairJob]:
    """One job per pair, reference stages first; fingerprints cover inputs and settings."""
    rig_digest = _file_digest(manifest.rig)
    settings = {"model": manifest.model, "z_range": manifest.z_range, "spacing": manifest.spacing,
                "max_gap": manifest.max_gap, "rig": rig_digest,
                "damage": dataclasses.asdict(manifest.damage) if manifest.damage else None}
    jobs: dict[str, PairJob] = {}
    for pair in manifest.pairs:
        ref = None if pair.reference else jobs[manifest.reference_of(pair.test).key]
        stamp = {"settings": settings, "left": _image_stamp(pair.left), "right": _image_stamp(pair.right),
                 "water_level": pair.water_level, "reference": ref.fingerprint if ref else None}
        fingerprint = hashlib.sha256(json.dumps(stamp, sort_keys=True, default=str).encode()).hexdigest()[:16]
        jobs[pair.key] = PairJob(pair, output / pair.test / pair.stage, manifest.rig, manifest.model, manifest.z_range,
                                 manifest.spacing, manifest.max_gap, manifest.damage,
                                 ref.out_dir if ref else None, fingerprint)
    return list(jobs.values())


def finished_row(job: PairJob) -> dict | None:
    """The saved row of a finished pair whose inputs have not changed, else None."""
    path = job.out_dir / RESULT
    if not path.is_file():
        return None
    try:
        row = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    if row.get("fingerprint") != job.fingerprint:
        return None
    if row.get("damage_waiting_for_reference") and job.reference_dir and (job.reference_dir / RESULT).is_file():
        return None  # the reference has been done since: compute the damage now
    return row


_RIGS: dict[str, object] = {}


def _load_rig_cached(path: Path):
    from .._calibration.rig import load_rig

    key = f"{path}:{path.stat().st_mtime_ns}"
    if key not in _RIGS:
        _RIGS.clear()
        _RIGS[key] = load_rig(path)
    return _RIGS[key]


def run_pair(job: PairJob) -> dict:
    """Process one pair; never raises: a failure comes back as a row with status "failed" and the error."""
    import jax

    started = time.perf_counter()
    try:
        with jax.enable_x64(True):
            row = _process_pair(job)
    except JaxStereoError as err:
        row = {"status": "failed", "error": str(err)}
    except Exception as err:  # one broken pair must not stop a campaign: record what happened
        row = {"status": "failed", "error": f"{err.__class__.__name__}: {err}"}
    if row["status"] == "failed":
        shutil.rmtree(job.out_dir, ignore_errors=True)  # what it wrote before failing is not a result
    row.update(test=job.pair.test, stage=job.pair.stage, reference=job.pair.reference,
               seconds=round(time.perf_counter() - started, 3))
    return row


def _process_pair(job: PairJob) -> dict:
    from .._stereo.reconstruct import ReconstructOptions, reconstruct
    from .._stereo.survey import plot_survey_preview, save_survey
    from .._surface.grid import grid_survey_filled, load_dem, save_dem
    from .images import check_pair, read_image

    pair = job.pair
    seconds: dict[str, float] = {}
    clock = [time.perf_counter()]

    def lap(name):
        now = time.perf_counter()
        seconds[name] = seconds.get(name, 0.0) + now - clock[0]
        clock[0] = now

    _remove_stale_temporaries(job.out_dir)
    rig = _load_rig_cached(job.rig)
    left, right = read_image(pair.left), read_image(pair.right)
    check_pair(left, right, rig.image_size, f"left image {str(pair.left)!r}", f"right image {str(pair.right)!r}")
    lap("load (s)")
    survey, info = reconstruct(left, right, rig, pair.water_level,
                               ReconstructOptions(model=job.model, z_range_m=job.z_range))
    clock[0] = time.perf_counter()
    seconds.update(info["seconds"])
    out = job.out_dir
    save_survey(survey, out / "survey.npz")
    lap("write survey (s)")
    plot_survey_preview(survey, rig.image_size, out / "preview.png",
                        f"{pair.test} stage {pair.stage}: {len(survey)} points")
    lap("preview figure (s)")
    reference_dem = None
    if job.reference_dir is not None and (job.reference_dir / RESULT).is_file():
        reference_dem = load_dem(job.reference_dir / "dem.npz")
    axes = (reference_dem.x, reference_dem.y) if reference_dem is not None else (None, None)
    dem = grid_survey_filled(survey, job.spacing, job.max_gap, *axes)
    save_dem(dem, out / "dem.npz")
    lap("grid (s)")
    row = {"status": "ok", "points": len(survey), "submerged_fraction": round(info["submerged_fraction"], 4),
           "water_level_m": survey.water_level, "survey": str(out / "survey.npz"), "dem": str(out / "dem.npz"),
           "stage_seconds": seconds, "warnings": info["warnings"]}
    if job.damage is not None and job.reference_dir is not None:
        if reference_dem is None:
            row["damage_waiting_for_reference"] = True
            row["error"] = "no damage: the reference stage has not been surveyed"
        elif not np.any(np.isfinite(reference_dem.z) & np.isfinite(dem.z)):
            raise JaxStereoError(f"survey of {pair.key} does not overlap its reference stage's DEM")
        else:
            row.update(_damage_row(job.damage, reference_dem, dem, out, lap))
    row["fingerprint"] = job.fingerprint
    write_text_atomic(out / RESULT, json.dumps({**row, "test": pair.test, "stage": pair.stage,
                                                "reference": pair.reference}, indent=2, default=float) + "\n")
    return row


def _damage_row(d, reference_dem, dem, out: Path, lap) -> dict:
    """Damage of `dem` against the test's reference DEM with the manifest's settings `d`; the report is
    written to `out/damage`; returns the summary row's damage columns."""
    from .._surface.damage import parse_slope
    from .._surface.damage_report import (
        ACTIVE_ZONE_DN50,
        _column_mean,
        fit_design_slope,
        write_damage_report,
    )
    from .._surface.damage_uncertainty import stretch_damage_with_sigma

    cot = parse_slope(d.slope)
    origin = d.slope_origin
    if d.fit_slope:
        origin, _ = fit_design_slope(reference_dem.x, _column_mean(reference_dem.z), cot, d.swl, d.dn50)
    result, sigma = stretch_damage_with_sigma(reference_dem, dem, d.dn50, cot, d.swl, origin, d.profile_spacing,
                                              stretch=d.stretch, active_zone_dn50=d.active_zone or ACTIVE_ZONE_DN50)
    lap("damage and its error bars (s)")
    write_damage_report(result, reference_dem, dem, out / "damage", sigma)
    lap("damage report and figures (s)")
    a = result.averaged
    s_sigma = sigma.sigma["S"] if sigma is not None else None
    intervals = {}  # each figure's 95 % interval, None where unknown
    for key, value in (("S", a.S), ("E2D", a.E2D), ("E3D", result.volumes.E3D)):
        low, high = (sigma.interval(key, value) if sigma is not None else None) or (None, None)
        intervals.update({f"{key}_low": low, f"{key}_high": high})
    return dict(A_e_m2=a.A_e, L_e_m=a.L_e, d_e_m=a.d_e, S=a.S, S_sigma=s_sigma, **intervals,
                S_max=result.S_max, E2D=a.E2D,
                E3D=result.volumes.E3D, eroded_volume_m3=result.volumes.eroded_m3,
                accreted_volume_m3=result.volumes.accreted_m3, damage_level=result.level,
                stretch_y_m=f"{result.stretch[0]:.3f} to {result.stretch[1]:.3f}"
                + (" (whole width)" if result.whole_width else ""),
                active_zone_z_m=f"{result.active_zone[0]:.3f} to {result.active_zone[1]:.3f}")


def _remove_stale_temporaries(folder: Path) -> None:
    """Delete temporary files an interrupted run left in a pair's folder (`atomic_path` names them `.NAME.*`)."""
    if folder.is_dir():
        for path in list(folder.glob(".*")) + list(folder.glob("damage/.*")):
            if path.is_file():
                path.unlink(missing_ok=True)
