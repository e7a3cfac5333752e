"""Error bars of the damage figures, by sampling the surveys' errors through the whole damage computation.

The damage figures are not smooth functions of the surfaces (erosion is where one profile passes below the
other; the largest zone is picked; the profiler's foot closes crevices), so the DEMs' errors are sampled
rather than linearised: each draw perturbs both DEMs with

- the matching errors: a Gaussian field with each cell's `sigma_match`, correlated over the matching window's
  footprint (`correlation_m`: white noise averaged over a box that wide, as the window averages the pixels);
- the calibration's and the water level's errors: shared by every cell of a survey, one normal deviate per
  survey times each cell's `sigma_calibration` / `sigma_level`; the same deviate in both surveys when they
  share the calibration (the same rig) or the water level (the same level, known to the same std), so that a
  common error cancels in the difference as it does in reality;
- the sub-pixel estimators' systematic disagreement (`dz_subpixel`, signed): one deviate common to both
  surveys (the same method errs the same way on the same texture, so it cancels where nothing changed);
- the hollows the matching window cannot resolve (`hollow_depth`: how far each cell lies below the mean of
  the window's footprint around it): one deviate common to both surveys, so that the rubble's own crevices
  cancel and an eroded hole, present in one survey only, does not. Without it the true S lay above the
  measured S at all 8 eroded stages of 4 synthetic trials, by 0.5-2.1 sigma (`experiments/uncertainty.py`);
- the cells seen only in part, filled from their neighbours or straddling a step (`sigma_coverage`, see
  `coverage.py`): an independent deviate per cell and survey (which side of a rock's edge a cell shows depends
  on the view). Without it the POV-Ray flume's undamaged model, dry survey against wet, reported per-profile S
  up to 1.37 with sigma 0.18. The damage now takes the change in such cells from the cells around them that
  both surveys saw wholly (`seen_change.py`), so in each draw they take their neighbours' perturbed change and
  this term acts only on the cells a `seen_tolerance_m` above zero lets through;

and the damage is computed again. Each figure's sigma is the standard deviation over the draws, and its 95 %
interval the wider of value +- 2 sigma and the middle 95 % of the draws; a zone's length and depth reach down to
zero where its size's interval does (`DamageSigma.interval`). The draws of a figure need not be
Gaussian: where the errors may lift the difference between two pits to zero or not, half-way along an erosion
zone, some draws split the zone and the others do not, and L_e and A_e come out in two groups. A standard
deviation understates such a spread: on the POV-Ray flume's stage II hole the central profile's L_e read
179 +- 38 mm against 70 mm true (2.9 sigma), with a fifth of the draws splitting the zone there as the truth
does; its interval, 56 to 254 mm, holds the truth.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import numpy as np
from scipy import ndimage

from .._geometry.errors import JaxStereoError
from .damage_report import StretchDamage, profile_figures
from .grid import DEM

DRAWS = 48

FIGURES = ("A_e_m2", "L_e_m", "d_e_m", "S", "E2D", "S_mean_above_threshold", "S_max", "L_e_max_m", "d_e_max_m",
           "eroded_volume_m3", "accreted_volume_m3", "E3D")
PROFILE_FIGURES = ("A_e_m2", "L_e_m", "d_e_m", "S", "E2D")  # each profile's, with a sigma per profile
DRAWS_MIDDLE = (2.5, 97.5)  # percentiles of the draws that bound a figure's 95 % interval
# The figures that describe the largest erosion zone's shape, each with the figure of its size: where the size's
# interval reaches zero, no zone may be there at all, and the shape's interval reaches zero too.
ZONE_SIZE = {"L_e_m": "A_e_m2", "d_e_m": "A_e_m2", "E2D": "A_e_m2", "L_e_max_m": "S_max", "d_e_max_m": "S_max"}


@dataclasses.dataclass(frozen=True)
class DamageSigma:
    """Standard deviations of a `StretchDamage`'s figures.

    **Fields:** `sigma` figure name (`FIGURES`: the averaged profile's `A_e_m2`, `L_e_m`, `d_e_m`, `S`, `E2D`,
    then the stretch's) -> standard deviation in the figure's unit (None where a draw could not compute it);
    `profile_sigma` profile y (m, rounded to 1 um) -> {figure (`PROFILE_FIGURES`) -> standard deviation} for the
    profiles computed in at least half the draws; `draws` the number of draws that computed; `failed` those that
    did not; `shared_calibration` and `shared_level` whether those errors were taken as common to both surveys;
    `spread` and `profile_spread` the same keys -> (low, high), the draws' `DRAWS_MIDDLE` percentiles (see
    `interval`); `values` and `profile_values` the same keys -> the figures measured (empty where not given:
    then a zone's shape is bounded on its own draws alone, see `interval`).
    """

    sigma: dict
    profile_sigma: dict
    draws: int
    failed: int
    shared_calibration: bool
    shared_level: bool
    spread: dict = dataclasses.field(default_factory=dict)
    profile_spread: dict = dataclasses.field(default_factory=dict)
    values: dict = dataclasses.field(default_factory=dict)
    profile_values: dict = dataclasses.field(default_factory=dict)

    @property
    def profile_S(self) -> dict:
        """Profile y (m) -> the standard deviation of its S."""
        return {y: figures["S"] for y, figures in self.profile_sigma.items()}

    def interval(self, key: str, value: float | None, y: float | None = None) -> tuple[float, float] | None:
        """The 95 % interval of a figure (its unit) measured as `value`: the wider of value +- 2 sigma and the
        middle 95 % of the draws, clipped at zero (every damage figure is >= 0). `key` from `FIGURES`, or from
        `PROFILE_FIGURES` with the profile's `y`. None where the figure or its sigma is not known.

        A zone's length and depth (`ZONE_SIZE`'s keys) reach down to zero where its size's interval does (the
        measured size taken from `values` / `profile_values`): if the data allow no erosion there, the zone
        the sweep found may be the surveys' noise, and its length and depth zero. The draws alone never say
        so, as every draw's noise makes some zone. On the POV-Ray flume's undamaged model the stretch's
        largest L_e read 215 mm, [131, 281] on its draws, with the largest S 0.07 [0, 0.68]."""
        if y is None:
            sigma, spread = self.sigma.get(key), self.spread.get(key)
        else:
            sigma = self.profile_sigma.get(round(y, 6), {}).get(key)
            spread = self.profile_spread.get(round(y, 6), {}).get(key)
        if value is None or sigma is None or spread is None:
            return None
        low, high = max(0.0, min(value - 2 * sigma, spread[0])), max(value + 2 * sigma, spread[1])
        size = ZONE_SIZE.get(key)
        measured = (self.values if y is None else self.profile_values.get(round(y, 6), {})).get(size)
        if size is not None and measured is not None:
            bounds = self.interval(size, measured, y)
            if bounds is not None and bounds[0] == 0.0:
                low = 0.0
        return low, high

    def intervals(self, values: dict, y: float | None = None) -> dict:
        """`interval` of each figure in `values` (name -> value) that has one: name -> [low, high]."""
        out = {}
        for key, value in values.items():
            bounds = self.interval(key, value, y)
            if bounds is not None:
                out[key] = [bounds[0], bounds[1]]
        return out

    def stretch_intervals(self, report: dict) -> dict:
        """The 95 % intervals of a stretch's figures (`FIGURES`), from its `StretchDamage.to_dict()`: name ->
        [low, high]."""
        return self.intervals({**report["averaged_profile"], **{key: report[key] for key in FIGURES if key in report}})


def correlated_noise(shape: tuple[int, int], width_cells: float, rng: np.random.Generator) -> np.ndarray:
    """A unit-variance Gaussian field (shape) correlated over `width_cells`: white noise averaged over a box of
    that width (cells), rescaled."""
    w = max(1, int(round(width_cells)))
    white = rng.standard_normal(shape)
    if w == 1:
        return white
    return ndimage.uniform_filter(white, size=w, mode="wrap") * w


def _footprint_cells(dem: DEM) -> float:
    """The matching window's footprint (`correlation_m`) in cells; 1 when unknown."""
    return dem.correlation_m / dem.spacing if np.isfinite(dem.correlation_m) else 1.0


def hollow_depth(dem: DEM) -> np.ndarray:
    """How high a survey may read each cell of a hollow (m, the DEM's shape, >= 0): the DEM's mean over a box as
    wide as the matching window's footprint (`correlation_m`) less the DEM, where positive; zero elsewhere and
    where the DEM has no height. A window that straddles a hollow's rim takes part of the rim's disparity, and
    the hollow's floor beside a wall is hidden from one camera, so hollows narrower than the footprint read too
    shallow; crests are seen by both cameras and are not raised. The DEM is itself smoothed, so this is a lower
    estimate of the hollow. Cells whose box is not wholly known (edges, holes) get zero."""
    w = 2 * round(_footprint_cells(dem) / 2) + 1  # odd: a plane's box mean is its centre's height
    known = np.isfinite(dem.z)
    if w == 1 or not known.any():
        return np.zeros(dem.z.shape)
    z = np.where(known, dem.z, 0.0)
    mean = ndimage.uniform_filter(z, size=w, mode="constant")
    whole = ndimage.uniform_filter(known.astype(float), size=w, mode="constant") > 1 - 0.5 / w**2
    return np.where(whole, np.maximum(mean - z, 0.0), 0.0)  # only where the whole box is known


def _figures(result: StretchDamage) -> tuple[dict, dict]:
    d = result.to_dict()
    values = profile_figures(result.averaged)
    values.update({key: d[key] for key in FIGURES if key not in values})
    per_profile = {round(y, 6): profile_figures(p) for y, p in result.profiles}
    return values, per_profile


def damage_sigma(before: DEM, after: DEM, compute: Callable[[DEM, DEM], StretchDamage], shared_calibration: bool,
                 shared_level: bool, draws: int = DRAWS, seed: int = 0) -> DamageSigma:
    """Sample the DEMs' errors through `compute` (the damage computation, e.g. a `stretch_damage` call with its
    settings) `draws` times; the standard deviation of each figure.

    **Arguments:** the DEMs with their sigma layers (from `grid_survey`); `compute(before, after)`;
    `shared_calibration` / `shared_level`: the surveys share that error (the same rig; the same level and its
    std), so one deviate serves both; `draws`; `seed` of the random draws (reproducible).

    Raises `JaxStereoError` if a DEM has no sigma layers, or if fewer than half the draws could be computed.
    """
    for name, dem in (("before", before), ("after", after)):
        if not dem.has_sigma:
            raise JaxStereoError(f"the {name} surface has no sigma layers: grid a survey made with error bars "
                                 "(jaxstereo reconstruct writes them) to get the damage's")
    rng = np.random.default_rng(seed)
    hollows = [hollow_depth(dem) for dem in (before, after)]
    samples, profiles, failed = [], [], 0
    for _ in range(draws):
        common = rng.standard_normal(4)
        perturbed = []
        for dem, hollow in zip((before, after), hollows):
            own = rng.standard_normal(2)
            e_cal = common[0] if shared_calibration else own[0]
            e_level = common[1] if shared_level else own[1]
            width = _footprint_cells(dem)
            noise = (dem.sigma_match * correlated_noise(dem.z.shape, width, rng)
                     + e_cal * dem.sigma_calibration + e_level * dem.sigma_level)
            if dem.dz_subpixel is not None:
                noise = noise + common[2] * dem.dz_subpixel
            noise = noise + common[3] * hollow
            if dem.sigma_coverage is not None:
                noise = noise + dem.sigma_coverage * correlated_noise(dem.z.shape, width, rng)
            perturbed.append(dataclasses.replace(dem, z=dem.z + np.nan_to_num(noise)))
        try:
            values, per_profile = _figures(compute(*perturbed))
        except JaxStereoError:
            failed += 1
            continue
        samples.append(values)
        profiles.append(per_profile)
    if len(samples) < max(2, draws // 2):
        raise JaxStereoError(f"the damage could be computed in only {len(samples)} of {draws} draws of the surveys' "
                             "errors: its uncertainty is not determined")
    sigma, spread = {}, {}
    for key in FIGURES:
        column = [s[key] for s in samples]
        known = not any(v is None for v in column)
        sigma[key] = float(np.std(column, ddof=1)) if known else None
        spread[key] = _middle(column) if known else None
    ys = set().union(*(set(p) for p in profiles))
    profile_sigma, profile_spread = {}, {}
    for y in sorted(ys):
        computed = [p[y] for p in profiles if y in p]
        if len(computed) >= max(2, len(profiles) // 2):  # computed in half the draws
            profile_sigma[y] = {key: float(np.std([c[key] for c in computed], ddof=1)) for key in PROFILE_FIGURES}
            profile_spread[y] = {key: _middle([c[key] for c in computed]) for key in PROFILE_FIGURES}
    return DamageSigma(sigma, profile_sigma, len(samples), failed, shared_calibration, shared_level, spread,
                       profile_spread)


def _middle(values) -> tuple[float, float]:
    """The `DRAWS_MIDDLE` percentiles of a figure's draws."""
    low, high = np.percentile(np.asarray(values, dtype=np.float64), DRAWS_MIDDLE)
    return float(low), float(high)


def shares_errors(before: DEM, after: DEM) -> tuple[bool, bool]:
    """Whether two surveys share the calibration's errors (the same cameras) and the water level's (the same
    level to the last digit in both: one estimate, the refined rig's or one gauge reading)."""
    calibration = bool(before.calibration_id) and before.calibration_id == after.calibration_id
    level = bool(np.isfinite(before.water_level) and before.water_level == after.water_level)
    return calibration, level


def stretch_damage_with_sigma(before: DEM, after: DEM, *args, draws: int = DRAWS, **kwargs
                              ) -> tuple[StretchDamage, DamageSigma | None]:
    """`stretch_damage(before, after, *args, **kwargs)` and, when both DEMs carry sigma layers, its figures'
    standard deviations (`damage_sigma`; None otherwise). The draws keep the direction in which the design slope
    rises as the result found it."""
    from .damage_report import stretch_damage

    result = stretch_damage(before, after, *args, **kwargs)
    if not (before.has_sigma and after.has_sigma):
        return result, None
    kwargs = {**kwargs, "rises_toward": result.rises_toward}
    calibration, level = shares_errors(before, after)
    sigma = damage_sigma(before, after, lambda b, a: stretch_damage(b, a, *args, **kwargs), calibration, level, draws)
    values, per_profile = _figures(result)
    return result, dataclasses.replace(sigma, values=values, profile_values=per_profile)
