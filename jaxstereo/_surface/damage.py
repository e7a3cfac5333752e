"""Damage of an armour layer from an initial and a final profile or DEM (the paper's section 4.2).

Profile method: both profiles are rotated into the frame of the design slope (X' along the slope,
Z' normal to it, outwards), their abscissae merged, and the difference `final - initial` swept for
sign changes. Where a profile drops more steeply than the design slope rises (the landward face of a
rock), its rotated polyline folds back along X'; each profile is then taken as its outer envelope (the
largest Z' over every part of the polyline above an abscissa), the surface a probe coming along the
slope's normal touches; it jumps at the edge of such a face, and the difference is swept through each
jump's two sides, not bridged to the next vertex. An edge of the final envelope within a sample of one of the
initial's is one face's edge that the two surveys place apart: the difference is drawn straight across the two,
not read as a sliver as deep as the face is high. Each negative stretch is an erosion zone with its
area `A_e`, length `L_e` (along the slope) and maximum depth `d_e` (normal to the slope); the largest is
reported.
`S = A_e / Dn50^2`, `E2D = d_e / Dn50`. Over a stretch, 3-D volumes and `E3D` come from DEM differences.
"""

from __future__ import annotations

import dataclasses
import re

import numpy as np
from jaxtyping import ArrayLike
from scipy import ndimage

from .._geometry.errors import JaxStereoError
from .._geometry.types import Vector2
from .grid import DEM

# Damage levels for rock armour (van der Meer): S at start of damage, intermediate range, failure, by slope
# (cotangent), from 1:1.5 to 1:6.
_DAMAGE_LEVELS = {1.5: (2.0, (3.0, 5.0), 8.0), 2.0: (2.0, (4.0, 6.0), 8.0), 3.0: (2.0, (6.0, 9.0), 12.0),
                  4.0: (3.0, (8.0, 12.0), 17.0), 6.0: (3.0, (8.0, 12.0), 17.0)}


def parse_slope(text: str | float) -> float:
    """Slope as its cotangent: '1:2' (vertical:horizontal), '2' or 2.0 -> 2.0; `JaxStereoError` otherwise."""
    if isinstance(text, (int, float)) and not isinstance(text, bool):
        value = float(text)
    else:
        m = re.fullmatch(r"\s*(?:(\d+(?:\.\d*)?)\s*:\s*)?(\d+(?:\.\d*)?)\s*", str(text))
        if not m:
            raise JaxStereoError(f"slope {text!r} does not parse: give the cotangent (e.g. 2) or V:H (e.g. 1:2)")
        value = float(m.group(2)) / (float(m.group(1)) if m.group(1) else 1.0)
    if not np.isfinite(value) or value <= 0:
        raise JaxStereoError(f"slope {text!r} must be positive (cotangent of the slope angle)")
    return value


@dataclasses.dataclass(frozen=True)
class Zone:
    """One erosion (or accretion) zone: `start`, `end` abscissae along the slope (m), `length` (m),
    `area` (m^2, positive), `depth` (m, the largest normal distance between the profiles)."""

    start: float
    end: float
    length: float
    area: float
    depth: float


@dataclasses.dataclass(frozen=True)
class ProfileDamage:
    """Damage of one cross-section: every erosion and accretion zone, and the largest erosion zone's
    `A_e` (m^2), `L_e` (m), `d_e` (m), with `S` and `E2D` for the given Dn50; `swept` the (start, end)
    abscissae along the slope (m) that the sweep covered (where both profiles have data; with an active zone,
    only the zones that reach into it are listed and counted, each whole)."""

    erosion: list[Zone]
    accretion: list[Zone]
    A_e: float
    L_e: float
    d_e: float
    S: float
    E2D: float
    swept: tuple[float, float] = (float("nan"), float("nan"))


def to_slope_frame(x, z, cot: float, origin=(0.0, 0.0)):
    """Rotate profile points (x, z) into the design-slope frame: X' along the slope (rising with x),
    Z' normal to it (positive outside the structure), with `origin` a point of the slope line."""
    norm = np.hypot(cot, 1.0)
    t = np.array([cot, 1.0]) / norm
    n = np.array([-1.0, cot]) / norm
    dx = np.asarray(x, dtype=np.float64) - origin[0]
    dz = np.asarray(z, dtype=np.float64) - origin[1]
    return dx * t[0] + dz * t[1], dx * n[0] + dz * n[1]


def _zones(X, D) -> tuple[list[Zone], list[Zone]]:
    """Erosion zones (where D < 0) and accretion zones (D > 0) on the piecewise-linear difference D(X), crossing
    points inserted.

    A zone runs on while one end of each piece of D is on its side: where the profiles only touch (D reaches
    zero at one abscissa and turns back) it goes on, as the paper's sweep has it; it ends where D crosses to the
    other side or stays at zero over a stretch."""
    X, D = np.asarray(X, dtype=np.float64), np.asarray(D, dtype=np.float64)
    x0, x1, v0, v1 = X[:-1], X[1:], D[:-1], D[1:]
    # A piece whose ends lie on opposite sides is cut where it crosses zero: pieces (a, b, va, vb), in order.
    crosses = v0 * v1 < 0
    with np.errstate(invalid="ignore", divide="ignore"):
        xc = np.where(crosses, x0 + (x1 - x0) * v0 / np.where(crosses, v0 - v1, 1.0), x1)
    real = np.stack([np.ones_like(crosses), crosses], axis=1).ravel()  # the second piece exists where it crosses
    a = np.stack([x0, xc], axis=1).ravel()[real]
    b = np.stack([xc, x1], axis=1).ravel()[real]
    va = np.stack([v0, np.zeros_like(v0)], axis=1).ravel()[real]
    vb = np.stack([np.where(crosses, 0.0, v1), v1], axis=1).ravel()[real]
    return _zones_on_side(a, b, -va, -vb), _zones_on_side(a, b, va, vb)


def _zones_on_side(a, b, va, vb) -> list[Zone]:
    """The zones where the pieces (from `a` to `b`, values `va` to `vb`, in order along the slope; a piece's ends
    on one side of zero or at it) are positive."""
    on_side = (va > 0) | (vb > 0)
    ends = ~on_side & (b > a)  # a stretch at zero or beyond (not one abscissa's two sides) ends a zone
    group = np.cumsum(ends)[on_side]  # the zone each piece on the side belongs to
    a, b, va, vb = a[on_side], b[on_side], va[on_side], vb[on_side]
    if a.size == 0:
        return []
    first = np.flatnonzero(np.diff(group, prepend=-1))
    last = np.append(first[1:] - 1, a.size - 1)
    area = np.add.reduceat(0.5 * (np.maximum(va, 0.0) + np.maximum(vb, 0.0)) * (b - a), first)
    depth = np.maximum.reduceat(np.maximum(va, vb), first)
    return [Zone(float(s), float(e), float(e - s), float(ar), float(dp))
            for s, e, ar, dp in zip(a[first], b[last], area, depth)]


def _monotonic_runs(X: np.ndarray, Z: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """A polyline (vertices `X`, `Z` in order along the profile) cut where it turns back along X' into
    monotonic runs, each returned as `(xs, zs)` with `xs` increasing."""
    step = np.sign(np.diff(X))
    # A segment normal to the slope (no step along it) continues the run before it.
    step = step[np.maximum.accumulate(np.where(step != 0, np.arange(step.size), 0))]
    cuts = np.nonzero(step[1:] != step[:-1])[0] + 1
    runs = []
    for start, end in zip(np.concatenate([[0], cuts]), np.concatenate([cuts, [step.size]])):
        xs, zs = X[start : end + 1], Z[start : end + 1]
        runs.append((xs[::-1], zs[::-1]) if xs[-1] < xs[0] else (xs, zs))
    return runs


def _run_values(runs, at: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each run's Z' at the abscissae `at` (n_runs, n), NaN outside the run's closed range, and the runs'
    first and last abscissae (n_runs, 1)."""
    values = np.array([np.interp(at, xs, zs, left=np.nan, right=np.nan) for xs, zs in runs])
    starts = np.array([xs[0] for xs, _ in runs])[:, None]
    ends = np.array([xs[-1] for xs, _ in runs])[:, None]
    return values, starts, ends


def _envelope_sides(runs, at: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The outer envelope's limits from the left and from the right at each abscissa `at` (n,): the largest
    Z' over the runs that reach the point from that side (NaN where none does). They differ where a run
    ends: the edge of a face that overhangs the slope, where the envelope jumps."""
    values, starts, ends = _run_values(runs, at)
    left = np.where((starts < at) & (at <= ends), values, -np.inf).max(axis=0)
    right = np.where((starts <= at) & (at < ends), values, -np.inf).max(axis=0)
    return np.where(np.isfinite(left), left, np.nan), np.where(np.isfinite(right), right, np.nan)


def _with_crossings(at: np.ndarray, runs) -> np.ndarray:
    """`at` (sorted, holding every vertex of the runs) with the points added where the highest run changes
    between two neighbours: the envelope's kinks, so that it is linear between the returned abscissae."""
    values, starts, ends = _run_values(runs, at)
    a, b = at[:-1], at[1:]
    covers = (starts <= a) & (b <= ends)  # the runs over each whole interval (n_runs, n - 1)
    if not covers.any():
        return at
    start_vals = np.where(covers, values[:, :-1], -np.inf)
    end_vals = np.where(covers, values[:, 1:], -np.inf)
    top_a, top_b = start_vals.argmax(axis=0), end_vals.argmax(axis=0)
    k = np.nonzero(covers.any(axis=0) & (top_a != top_b))[0]
    d0 = values[top_a[k], k] - values[top_b[k], k]  # >= 0: run top_a leads at the interval's start
    d1 = values[top_a[k], k + 1] - values[top_b[k], k + 1]  # <= 0: run top_b leads at its end
    with np.errstate(invalid="ignore", divide="ignore"):
        t = d0 / (d0 - d1)
    inside = np.isfinite(t) & (t > 0) & (t < 1)
    k, t = k[inside], t[inside]
    return np.unique(np.concatenate([at, a[k] + t * (b[k] - a[k])]))


EDGE_JUMP_M = 1e-9  # an envelope whose limits from the two sides differ by more has an edge there
# A piece of an envelope that falls more than this many times as far as it advances along the slope is a face seen
# edge-on (within 6 degrees of the slope's normal): an edge too, as a jump is.
EDGE_STEEPNESS = 10.0


def _envelope_edges(X: np.ndarray, left: np.ndarray, right: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Where an envelope (its `left` and `right` limits (n,) at the abscissae `X` (n,)) falls by a face's height
    within next to no distance along the slope: `(first, last)`, index arrays into `X` of each edge's ends. A jump
    (the edge of a face that overhangs the slope) is one abscissa, first == last; a run of pieces each falling
    `EDGE_STEEPNESS` times as far as it advances (a face nearly normal to the slope, which one survey may see
    overhang and the other not) spans them. The jumps come first, then the runs (`_paired_edges` orders them)."""
    jumps = np.flatnonzero(np.nan_to_num(right - left, nan=0.0) < -EDGE_JUMP_M)
    fall = np.nan_to_num(right[:-1] - left[1:], nan=0.0)
    steep = (fall > EDGE_JUMP_M) & (np.diff(X) * EDGE_STEEPNESS < fall)
    starts = np.flatnonzero(steep & ~np.concatenate([[False], steep[:-1]]))
    ends = np.flatnonzero(steep & ~np.concatenate([steep[1:], [False]])) + 1
    return np.concatenate([jumps, starts]), np.concatenate([jumps, ends])


def _paired_edges(X: np.ndarray, initial: tuple[np.ndarray, np.ndarray], final: tuple[np.ndarray, np.ndarray],
                  tolerance: float) -> list[tuple[int, int]]:
    """Index spans `(k1, k2)`, k1 < k2, into the abscissae `X` (n,), each over edges of both envelopes
    (`_envelope_edges`) that lie within `tolerance` (m along the slope) of each other: one face's edge, placed apart
    by the two surveys. `initial` and `final` are the envelopes' (left, right) limits at `X`. The edges of both,
    in order along the slope, are gathered into groups no wider than `tolerance` from the first edge's start to
    the last one's end (a group of one envelope's edges that the next edge does not fit starts again at its last
    edge where that one fits); a group holding edges of both envelopes is one span.

    Until round 67 an edge was a jump alone, and each final edge was paired with the nearest initial one, a pair
    overlapping a closer one left out. On the POV-Ray development flume's undamaged model (dry survey against wet)
    slivers were left, each between a face's edge in one survey and the same face in the other: where the face
    stepped down twice within a sample (two edges in each envelope, the pairs nested), a profile's d_e of 25.9 mm
    over 0.2 mm; where the face overhung the slope in one survey and stood 2 degrees short of its normal in the
    other (no jump there), 17.1 mm over 0.7 mm."""
    edges = [_envelope_edges(X, left, right) for left, right in (initial, final)]
    if any(first.size == 0 for first, _ in edges) or not tolerance > 0:
        return []
    first = np.concatenate([edges[0][0], edges[1][0]])
    last = np.concatenate([edges[0][1], edges[1][1]])
    which = np.concatenate([np.zeros(edges[0][0].size, int), np.ones(edges[1][0].size, int)])
    groups: list[list] = []  # [first, last, the envelopes whose edges it holds]
    previous = None
    for k in np.argsort(first, kind="stable"):
        edge = (int(first[k]), int(last[k]), int(which[k]))
        group = groups[-1] if groups else None
        if group is not None and X[max(edge[1], group[1])] - X[group[0]] <= tolerance:
            group[1], group[2] = max(group[1], edge[1]), group[2] | {edge[2]}
        elif (group is not None and len(group[2]) == 1 and previous is not None
              and X[max(edge[1], previous[1])] - X[previous[0]] <= tolerance):
            # one envelope's edges so far: the group starts again at the last of them, the one nearest this edge
            groups[-1] = [previous[0], max(previous[1], edge[1]), {previous[2], edge[2]}]
        else:
            groups.append([edge[0], edge[1], {edge[2]}])
        previous = edge
    return [(start, end) for start, end, envelopes in groups if len(envelopes) == 2 and end > start]


def _bridged(X: np.ndarray, D: np.ndarray, pairs: list[tuple[int, int]]) -> np.ndarray:
    """The difference `D` (2n,), each abscissa's limits from the left and the right of `X` (n,), drawn straight
    across each pair of edges (`_paired_edges`): from the left limit at the first edge to the right limit at the
    second."""
    D = D.copy()
    for k1, k2 in pairs:
        a, b = 2 * k1, 2 * k2 + 1
        if np.isfinite(D[a]) and np.isfinite(D[b]):
            t = (X[k1 + 1 : k2 + 1] - X[k1]) / (X[k2] - X[k1])
            inner = np.concatenate([[0.0], np.repeat(t[:-1], 2), [1.0]])
            D[a + 1 : b] = D[a] + inner * (D[b] - D[a])
    return D


def _sampling_step(X: np.ndarray) -> float:
    """The median distance between consecutive abscissae `X` (m): a profile's sampling step along the slope."""
    steps = np.abs(np.diff(X))
    steps = steps[steps > 0]
    return float(np.median(steps)) if steps.size else 0.0


def slope_abscissa(z: float, cot: float, origin=(0.0, 0.0)) -> float:
    """Abscissa along the design slope (m, the frame of `to_slope_frame`) of the slope line's point at height z."""
    return (z - origin[1]) * float(np.hypot(cot, 1.0))


def profile_damage(initial: tuple[ArrayLike, ArrayLike], final: tuple[ArrayLike, ArrayLike], dn50: float, cot: float,
                   origin: Vector2 = (0.0, 0.0),
                   active_zone: tuple[float, float] | None = None,
                   edge_tolerance_m: float | None = None) -> ProfileDamage:
    """Damage between two cross-sections, as the paper's section 4.2 sweeps them.

    **Arguments:**

    - `initial`, `final`: `(x, z)` pairs of arrays (metres) along the profile, taken in order of x (NaNs are
      dropped).
    - `dn50`: nominal diameter of the armour units, metres.
    - `cot`: the design slope's cotangent (2 for 1:2).
    - `origin`: a point `(x, z)` on the design slope line.
    - `active_zone`: `(start, end)` abscissae along the slope (metres, see `slope_abscissa`): the erosion and
      accretion zones counted are those that reach into it (the zone around the still water level), each
      whole; None: every zone where the profiles overlap.
    - `edge_tolerance_m`: edges of the final and the initial envelope (where a face that overhangs the slope
      ends and the envelope jumps, or where it falls nearly normal to the slope, see `_envelope_edges`) within
      this distance along the slope of each other are one face's edge, placed apart by the two surveys: the
      difference is drawn straight across them (`_paired_edges`). None: the profiles' sampling step along the
      slope (the larger of their median vertex spacings), below which the samples cannot tell two edges from
      one; 0: none drawn across.

    Two surveys of one rock place the edge of its overhanging face a little apart (on a 5 mm DEM a cell's
    height differing by 1 mm moves it 0.45 mm along a 1:2 slope). Between the two edges one envelope is on the
    face's top and the other below it: the difference there reads as deep as the face is high, over a sliver
    of that width. On the POV-Ray flume's undamaged model (dry against wet survey, 5 mm profiles) such
    slivers, all narrower than 2.5 mm, gave profiles `d_e` of up to 110 mm (E2D 3.1); drawn across, 19 mm,
    with the stage III hole's central profile unchanged (8.3 mm since round 67's edges).

    A zone that reaches into the active zone is measured whole, beyond the active zone's ends too: a hole is
    one, and cutting it where the zone ends would count a part of it that depends on the water level. On the
    POV-Ray flume's stage III hole (about 0.13 m along the slope, from 3.1 Dn50 under the SWL to 0.4 Dn50 over
    it), the zone as a cut took 35 % off the central profile's A_e with the SWL given 5.5 cm higher and 5 % with
    it 6.5 cm lower; counted whole, A_e is the same (1.7 % under the truth) at any SWL from 0.06 to 0.26 m.
    """
    if not (np.isfinite(dn50) and dn50 > 0):
        raise JaxStereoError(f"Dn50 must be positive (metres), got {dn50}")
    frames = []
    for name, (x, z) in (("initial", initial), ("final", final)):
        x, z = np.asarray(x, dtype=np.float64), np.asarray(z, dtype=np.float64)
        ok = np.isfinite(x) & np.isfinite(z)
        if ok.sum() < 2:
            raise JaxStereoError(f"the {name} profile has fewer than 2 valid points")
        order = np.argsort(x[ok], kind="stable")
        frames.append(to_slope_frame(x[ok][order], z[ok][order], cot, origin))
    (Xi, Zi), (Xf, Zf) = frames
    lo, hi = max(Xi.min(), Xf.min()), min(Xi.max(), Xf.max())
    if hi <= lo:
        raise JaxStereoError("the initial and final profiles do not overlap along the slope")
    if active_zone is not None and min(hi, active_zone[1]) <= max(lo, active_zone[0]):
        raise JaxStereoError(f"the profiles do not reach the active zone ({active_zone[0]:.3f} to "
                             f"{active_zone[1]:.3f} m along the slope)")
    runs_i, runs_f = _monotonic_runs(Xi, Zi), _monotonic_runs(Xf, Zf)
    X = np.unique(np.concatenate([Xi, Xf, [lo, hi]]))
    X = _with_crossings(_with_crossings(X, runs_i), runs_f)
    X = X[(X >= lo) & (X <= hi)]
    # Both envelopes are linear between these abscissae but may jump at them (the edge of an overhanging
    # face): the difference is swept through each abscissa's limit from the left, then from the right.
    (left_i, right_i), (left_f, right_f) = _envelope_sides(runs_i, X), _envelope_sides(runs_f, X)
    tolerance = (max(_sampling_step(Xi), _sampling_step(Xf)) if edge_tolerance_m is None
                 else float(edge_tolerance_m))
    pairs = _paired_edges(X, (left_i, right_i), (left_f, right_f), tolerance)
    D = _bridged(X, np.stack([left_f - left_i, right_f - right_i], axis=1).ravel(), pairs)
    X = np.repeat(X, 2)
    D[0] = D[-1] = np.nan  # the sweep starts at lo and ends at hi: nothing from beyond them
    known = np.isfinite(D)
    X, D = X[known], D[known]
    erosion, accretion = _zones(X, D)
    if active_zone is not None:
        erosion, accretion = ([zn for zn in zones if zn.end > active_zone[0] and zn.start < active_zone[1]]
                              for zones in (erosion, accretion))
    biggest = max(erosion, key=lambda zn: zn.area) if erosion else Zone(0.0, 0.0, 0.0, 0.0, 0.0)
    return ProfileDamage(erosion, accretion, biggest.area, biggest.length, biggest.depth,
                         biggest.area / dn50**2, biggest.depth / dn50, (float(lo), float(hi)))


def damage_thresholds(cot: float) -> tuple[float, tuple[float, float], float]:
    """Van der Meer's damage levels of rock armour for a slope: (start of damage, (intermediate range),
    failure) in S. Tabulated for slopes 1:1.5, 1:2, 1:3, 1:4 and 1:6; between them, linear in the
    cotangent. Steeper or flatter slopes are outside the table: `JaxStereoError`."""
    slopes = sorted(_DAMAGE_LEVELS)
    if not slopes[0] - 1e-9 <= cot <= slopes[-1] + 1e-9:
        raise JaxStereoError(f"van der Meer's damage levels cover slopes from 1:{slopes[0]:g} to 1:{slopes[-1]:g}; "
                             f"the slope 1:{cot:g} is outside them")
    rows = [_DAMAGE_LEVELS[c] for c in slopes]
    table = np.array([[r[0], r[1][0], r[1][1], r[2]] for r in rows])
    start, lo, hi, failure = (float(np.interp(cot, slopes, table[:, k])) for k in range(4))
    return start, (lo, hi), failure


def damage_level(S: float, cot: float) -> str:
    """Damage level of rock armour from S on a slope of cotangent `cot` (see `damage_thresholds`)."""
    start, (lo, hi), failure = damage_thresholds(cot)
    if S < start:
        return "no damage"
    if S < lo:
        return "start of damage"
    if S <= hi:
        return "intermediate damage"
    if S < failure:
        return "advanced damage"
    return "failure"


@dataclasses.dataclass(frozen=True)
class DemDamage:
    """3-D damage from a DEM difference: `eroded_m3`, `accreted_m3`, and `E3D` (the largest erosion
    depth averaged over a circle of diameter Dn50, divided by Dn50) at `E3D_xy`; `E3D` is None (not
    measurable) when no Dn50 circle is covered by data in both DEMs."""

    eroded_m3: float
    accreted_m3: float
    E3D: float | None
    E3D_xy: tuple[float, float] | None


def dem_damage(before: DEM, after: DEM, dn50: float) -> DemDamage:
    """Eroded and accreted volumes and E3D (Hofland et al.) from two DEMs on the same grid."""
    if before.z.shape != after.z.shape or not np.allclose(before.x, after.x) or not np.allclose(before.y, after.y):
        raise JaxStereoError("the two DEMs are not on the same grid")
    if not (np.isfinite(dn50) and dn50 > 0):
        raise JaxStereoError(f"Dn50 must be positive (metres), got {dn50}")
    diff = after.z - before.z
    valid = np.isfinite(diff)
    if not valid.any():
        raise JaxStereoError("the two DEMs do not overlap (no cell has data in both)")
    cell = before.spacing**2
    eroded = float(-np.sum(np.minimum(diff[valid], 0.0)) * cell)
    accreted = float(np.sum(np.maximum(diff[valid], 0.0)) * cell)
    radius = dn50 / 2 / before.spacing
    r = int(np.ceil(radius))
    yy, xx = np.mgrid[-r : r + 1, -r : r + 1]
    disk = (xx**2 + yy**2 <= radius**2).astype(np.float64)
    depth = np.where(valid, -diff, 0.0)
    total = ndimage.convolve(depth, disk, mode="constant")
    count = ndimage.convolve(valid.astype(np.float64), disk, mode="constant")
    full = count >= 0.9 * disk.sum()
    if not full.any():
        return DemDamage(eroded, accreted, None, None)
    mean = np.where(full, total / np.maximum(count, 1), -np.inf)
    k = int(np.argmax(mean))
    i, j = np.unravel_index(k, mean.shape)
    return DemDamage(eroded, accreted, float(max(mean[i, j], 0.0) / dn50), (float(before.x[j]), float(before.y[i])))
