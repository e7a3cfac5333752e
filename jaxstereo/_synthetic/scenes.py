"""Synthetic flume scenes: deterministic from a spec and a seed, serialisable as JSON.

Kinds: a flat textured floor, the paper's sloping board, and a rubble-mound breakwater model whose
armour units are rough ellipsoids, with optional damage (units removed around the still water level
and some deposited lower down).
"""

from __future__ import annotations

import dataclasses
import json

import numpy as np
from jaxtyping import ArrayLike
from scipy import ndimage

from .._geometry.errors import JaxStereoError
from .heightfield import Heightfield


@dataclasses.dataclass(frozen=True)
class Extent:
    """The rectangle of the flume floor a scene covers (metres) and its grid spacing (metres)."""

    x_min: float = -0.75
    x_max: float = 0.75
    y_min: float = -0.5
    y_max: float = 0.5
    spacing: float = 1.0e-3

    def grid(self) -> tuple[np.ndarray, np.ndarray]:
        nx = int(round((self.x_max - self.x_min) / self.spacing)) + 1
        ny = int(round((self.y_max - self.y_min) / self.spacing)) + 1
        if nx < 2 or ny < 2:
            raise JaxStereoError(f"scene extent {self} holds fewer than 2x2 grid nodes")
        x = self.x_min + self.spacing * np.arange(nx)
        y = self.y_min + self.spacing * np.arange(ny)
        return x, y


@dataclasses.dataclass(frozen=True)
class FlatFloor:
    """A flat textured floor at height `z_m`."""

    z_m: float = 0.0
    extent: Extent = Extent()
    seed: int = 0
    kind: str = "flat-floor"


@dataclasses.dataclass(frozen=True)
class SlopingBoard:
    """The paper's sloping board: a plank rising `rise_m` over `run_m` (along +X) from the floor at `toe_x_m`."""

    rise_m: float = 0.31
    run_m: float = 0.69
    toe_x_m: float = -0.35
    extent: Extent = Extent()
    seed: int = 0
    kind: str = "sloping-board"

    def height(self, x: ArrayLike) -> np.ndarray:
        """Exact board height (metres) at world x (any shape)."""
        return np.clip((np.asarray(x) - self.toe_x_m) / self.run_m, 0.0, 1.0) * self.rise_m


@dataclasses.dataclass(frozen=True)
class Damage:
    """Units removed around the still water level (SWL) of a breakwater, some deposited lower down.

    Units whose centre lies inside an ellipse on the slope centred at the SWL (half-axes
    `half_length_dn50` along the slope and `half_width_dn50` across, in units of Dn50) are removed, the
    top layer first and the under layer where their centre is within `deep_fraction` of the ellipse;
    a fraction `deposit_fraction` of them is placed back further down the slope.
    """

    center_y_m: float = 0.0
    half_length_dn50: float = 2.0
    half_width_dn50: float = 3.0
    deep_fraction: float = 0.0
    deposit_fraction: float = 0.5
    swl_m: float = 0.158

    def __post_init__(self):
        for name in ("half_length_dn50", "half_width_dn50"):
            if not getattr(self, name) > 0:
                raise JaxStereoError(f"damage {name} must be positive, got {getattr(self, name)}")


@dataclasses.dataclass(frozen=True)
class Breakwater:
    """A rubble-mound breakwater model: a core under two layers of rough armour units.

    The seaward slope (1:`slope`, i.e. `slope` horizontal for 1 vertical) rises along +X from its toe
    at `toe_x_m` on the flume floor (z = 0) to the crest at `crest_height_m`, `crest_width_m` wide.
    Armour units have nominal diameters around `dn50_m` (spread `dn_spread`, relative).
    """

    dn50_m: float = 0.036
    slope: float = 2.0
    crest_height_m: float = 0.31
    crest_width_m: float = 0.15
    toe_x_m: float = -0.45
    dn_spread: float = 0.12
    damage: Damage | None = None
    extent: Extent = Extent()
    seed: int = 0
    kind: str = "breakwater"

    def __post_init__(self):
        if not self.dn50_m > 0:
            raise JaxStereoError(f"dn50_m must be positive, got {self.dn50_m}")
        if not 1.0 <= self.slope <= 5.0:
            raise JaxStereoError(f"breakwater slope must be 1:1 to 1:5 (cotangent 1-5), got {self.slope}")

    def envelope(self, x: ArrayLike) -> np.ndarray:
        """Design (outer) profile z(x), metres: floor, slope, crest, then the lee slope at 1:1.5."""
        x = np.asarray(x, dtype=np.float64)
        rise = (x - self.toe_x_m) / self.slope
        crest_end = self.toe_x_m + self.slope * self.crest_height_m + self.crest_width_m
        lee = self.crest_height_m - (x - crest_end) / 1.5
        return np.clip(np.minimum(rise, lee), 0.0, self.crest_height_m)


SceneSpec = FlatFloor | SlopingBoard | Breakwater


@dataclasses.dataclass(frozen=True)
class Scene:
    """A built scene: its spec, its heightfield and, for breakwaters, the armour units.

    **Fields:** `spec`; `heightfield`; `rocks` a dict of arrays (`center` (n, 3) m, `axes` (n, 3) m,
    `rotation` (n, 3, 3), `layer` (n,), `removed` (n,) bool, `deposited` (n,) bool) or None.
    """

    spec: SceneSpec
    heightfield: Heightfield
    rocks: dict | None = None


def _texture_noise(rng, shape, scales_m, spacing):
    """Fractal noise in [0, 1] (shape), sum of smoothed white noise at several scales (metres)."""
    total = np.zeros(shape)
    weight = 0.0
    for k, scale in enumerate(scales_m):
        sigma = max(scale / spacing, 0.5)
        layer = ndimage.gaussian_filter(rng.standard_normal(shape), sigma, mode="wrap")
        layer /= layer.std() + 1e-12
        total += layer / (k + 1)
        weight += 1.0 / (k + 1)
    total /= weight
    return 1.0 / (1.0 + np.exp(-1.6 * total))


def _speckle_albedo(rng, shape, spacing, base, contrast=0.8, scales=(0.012, 0.004, 0.0015)):
    noise = _texture_noise(rng, shape, scales, spacing)
    tint = np.asarray(base)[None, None, :]
    return np.clip(tint * ((1 - contrast) + contrast * 1.6 * noise[..., None]), 0.0, 1.0)


def build_scene(spec: SceneSpec) -> Scene:
    """Build the heightfield (and armour units) of a scene spec. Deterministic from `spec.seed`."""
    x, y = spec.extent.grid()
    shape = (y.size, x.size)
    rng = np.random.default_rng(spec.seed)
    if isinstance(spec, FlatFloor):
        z = np.full(shape, spec.z_m)
        albedo = _speckle_albedo(rng, shape, spec.extent.spacing, (0.75, 0.7, 0.6))
        return Scene(spec, Heightfield(z, albedo, x[0], y[0], spec.extent.spacing))
    if isinstance(spec, SlopingBoard):
        z = np.broadcast_to(spec.height(x)[None, :], shape).copy()
        # A painted random speckle, as used on lab test boards: fine and contrasted.
        albedo = _speckle_albedo(rng, shape, spec.extent.spacing, (0.8, 0.72, 0.55), scales=(0.0015, 0.004))
        return Scene(spec, Heightfield(z, albedo, x[0], y[0], spec.extent.spacing))
    if isinstance(spec, Breakwater):
        return _build_breakwater(spec, x, y, rng)
    raise JaxStereoError(f"unknown scene spec {type(spec).__name__}")


def _random_rotations(rng, n):
    q = rng.standard_normal((n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    w, a, b, c = q.T
    return np.stack([
        np.stack([1 - 2 * (b * b + c * c), 2 * (a * b - c * w), 2 * (a * c + b * w)], -1),
        np.stack([2 * (a * b + c * w), 1 - 2 * (a * a + c * c), 2 * (b * c - a * w)], -1),
        np.stack([2 * (a * c - b * w), 2 * (b * c + a * w), 1 - 2 * (a * a + b * b)], -1),
    ], 1)


def _place_units(spec: Breakwater, rng, y_min, y_max):
    """Unit centres on two jittered lattices parallel to the envelope, and their shapes."""
    dn = spec.dn50_m
    cot = spec.slope
    # Along-profile arclength parameterisation of the envelope, from the toe apron to the crest's end.
    x_start = spec.toe_x_m - 1.5 * dn
    x_end = spec.toe_x_m + cot * spec.crest_height_m + spec.crest_width_m + 1.0 * dn
    xs = np.linspace(x_start, x_end, 4000)
    zs = spec.envelope(xs)
    arc = np.concatenate([[0.0], np.cumsum(np.hypot(np.diff(xs), np.diff(zs)))])
    centers, layers = [], []
    spacing = 0.95 * dn
    for layer, depth in ((0, 1.45 * dn), (1, 0.5 * dn)):
        offset = 0.5 * spacing * layer
        rows = np.arange(arc[0] + offset, arc[-1], spacing * 0.87)
        for r_i, s in enumerate(rows):
            shift = (r_i % 2) * 0.5 * spacing + offset
            ys = np.arange(y_min + shift, y_max, spacing)
            for yv in ys:
                ss = s + rng.uniform(-0.15, 0.15) * spacing
                xv = np.interp(ss, arc, xs)
                # Inward normal of the envelope at this point.
                k = min(max(np.searchsorted(xs, xv), 1), xs.size - 1)
                tx, tz = xs[k] - xs[k - 1], zs[k] - zs[k - 1]
                norm = np.hypot(tx, tz)
                nx, nz = -tz / norm, tx / norm
                zc = np.interp(xv, xs, zs)
                centers.append([xv - nx * depth, yv + rng.uniform(-0.15, 0.15) * spacing, zc - nz * depth])
                layers.append(layer)
    centers = np.asarray(centers)
    n = centers.shape[0]
    diam = dn * np.exp(rng.normal(0.0, spec.dn_spread, n))
    shape = rng.uniform([1.0, 0.75, 0.55], [1.35, 1.0, 0.8], (n, 3))
    shape /= np.cbrt(np.prod(shape, axis=1, keepdims=True))
    axes = shape * (diam * np.cbrt(3.0 / (4.0 * np.pi)))[:, None]
    return centers, axes, _random_rotations(rng, n), np.asarray(layers)


def _rasterise_units(z, labels, x0, y0, spacing, centers, axes, rotations, ids, units_per_batch=64):
    """Raise `z` (ny, nx) to the upper surface of each ellipsoidal unit; record the unit id in `labels`.

    Units go `units_per_batch` at a time (a window of nodes around each, as wide as the largest unit), so that
    the arrays of a batch stay small; within a batch the highest surface over a node wins, then it replaces
    the node's height where it is higher.
    """
    if len(ids) == 0:
        return
    ny, nx = z.shape
    radius = axes.max()
    half = int(np.ceil(radius / spacing)) + 1
    offs = np.arange(-half, half + 1)
    oj, oi = np.meshgrid(offs, offs)
    zf = z.reshape(-1)
    lf = labels.reshape(-1)
    ids = np.asarray(ids)
    for start in range(0, len(ids), units_per_batch):
        batch = ids[start:start + units_per_batch]
        c = centers[batch]
        A = np.einsum("nij,nj,nkj->nik", rotations[batch], 1.0 / axes[batch] ** 2, rotations[batch])
        cj = np.round((c[:, 0] - x0) / spacing).astype(int)
        ci = np.round((c[:, 1] - y0) / spacing).astype(int)
        J = cj[:, None, None] + oj[None]
        I = ci[:, None, None] + oi[None]
        dx = x0 + J * spacing - c[:, 0, None, None]
        dy = y0 + I * spacing - c[:, 1, None, None]
        azz = A[:, 2, 2, None, None]
        b = A[:, 0, 2, None, None] * dx + A[:, 1, 2, None, None] * dy
        cc = (A[:, 0, 0, None, None] * dx * dx + 2 * A[:, 0, 1, None, None] * dx * dy
              + A[:, 1, 1, None, None] * dy * dy - 1)
        disc = b * b - azz * cc
        ok = (disc > 0) & (I >= 0) & (I < ny) & (J >= 0) & (J < nx)
        top = (np.broadcast_to(c[:, 2, None, None], ok.shape)[ok]
               + (-b[ok] + np.sqrt(disc[ok])) / np.broadcast_to(azz, ok.shape)[ok])
        flat = (I * nx + J)[ok]
        who = np.broadcast_to(batch[:, None, None], ok.shape)[ok]
        # Ascending order: the highest surface over a node is written last and wins.
        order = np.argsort(top, kind="stable")
        nodes, tops, owners = flat[order], top[order], who[order]
        best = np.full(zf.shape, -np.inf)
        best[nodes] = tops
        owner = np.full(zf.shape, -1)
        owner[nodes] = owners
        wins = nodes[best[nodes] > zf[nodes]]  # a node can appear more than once: the same value each time
        zf[wins] = best[wins]
        lf[wins] = owner[wins]


def _build_breakwater(spec: Breakwater, x, y, rng) -> Scene:
    spacing = spec.extent.spacing
    shape = (y.size, x.size)
    dn = spec.dn50_m
    X = np.broadcast_to(x[None, :], shape)
    envelope = spec.envelope(x)
    # Core: the envelope lowered by the armour thickness (2 Dn50 measured normal to the slope).
    cos_a = spec.slope / np.hypot(spec.slope, 1.0)
    core = np.maximum(envelope - 2.0 * dn / cos_a, 0.0)
    z = np.broadcast_to(core[None, :], shape).copy()
    labels = np.full(shape, -1)
    margin = 2 * dn
    centers, axes, rotations, layers = _place_units(spec, rng, y[0] - margin, y[-1] + margin)
    n = centers.shape[0]
    removed = np.zeros(n, bool)
    deposited = np.zeros(n, bool)
    palette = np.array([[0.58, 0.57, 0.55], [0.56, 0.46, 0.36], [0.36, 0.36, 0.38], [0.62, 0.48, 0.42],
                        [0.70, 0.66, 0.58]])
    colours = palette[rng.integers(0, len(palette), n)] * rng.uniform(0.65, 1.25, (n, 1))
    colours = np.clip(colours + rng.normal(0.0, 0.03, (n, 3)), 0.05, 0.95)
    if spec.damage is not None:
        removed, deposited, centers = _apply_damage(spec, spec.damage, centers, axes, layers, rng)
    keep = np.nonzero(~removed | deposited)[0]
    static = keep[~deposited[keep]]
    _rasterise_units(z, labels, x[0], y[0], spacing, centers, axes, rotations, static)
    moved = np.nonzero(deposited)[0]
    if moved.size:
        # Deposited units settle on the surface that is already there.
        zi = ndimage.map_coordinates(z, [(centers[moved, 1] - y[0]) / spacing, (centers[moved, 0] - x[0]) / spacing],
                                     order=1, mode="nearest")
        centers[moved, 2] = zi + 0.35 * axes[moved].min(axis=1)
        _rasterise_units(z, labels, x[0], y[0], spacing, centers, axes, rotations, moved)
    # Fine roughness on the stones, then texture: each stone its own colour, with grain.
    grain = _texture_noise(rng, shape, (0.006, 0.002), spacing)
    on_rock = labels >= 0
    z = z + np.where(on_rock, 0.0012 * (grain - 0.5), 0.0)
    base = np.where(on_rock[..., None], colours[np.maximum(labels, 0)], np.array([0.45, 0.42, 0.38]))
    fine = _texture_noise(rng, shape, (0.004, 0.0012), spacing)
    albedo = np.clip(base * (0.45 + 0.9 * fine[..., None]), 0.0, 1.0)
    rocks = dict(center=centers, axes=axes, rotation=rotations, layer=layers, removed=removed & ~deposited,
                 deposited=deposited, colour=colours)
    del X
    return Scene(spec, Heightfield(z, albedo, x[0], y[0], spacing), rocks)


def _apply_damage(spec: Breakwater, damage: Damage, centers, axes, layers, rng):
    dn = spec.dn50_m
    # Position along the slope of each unit relative to the SWL crossing of the envelope.
    x_swl = spec.toe_x_m + spec.slope * damage.swl_m
    along = (centers[:, 0] - x_swl) * np.hypot(1.0, 1.0 / spec.slope)
    across = centers[:, 1] - damage.center_y_m
    r = np.hypot(along / (damage.half_length_dn50 * dn), across / (damage.half_width_dn50 * dn))
    removed = ((layers == 1) & (r < 1.0)) | ((layers == 0) & (r < damage.deep_fraction))
    idx = np.nonzero(removed)[0]
    deposited = np.zeros_like(removed)
    centers = centers.copy()
    if idx.size:
        pick = rng.permutation(idx)[: int(round(damage.deposit_fraction * idx.size))]
        deposited[pick] = True
        # Roll the deposited units down the slope, below the damage zone.
        drop = (damage.half_length_dn50 + rng.uniform(1.0, 3.0, pick.size)) * dn
        centers[pick, 0] -= drop / np.hypot(1.0, 1.0 / spec.slope)
        centers[pick, 1] += rng.uniform(-0.5, 0.5, pick.size) * dn
    return removed, deposited, centers


def scene_to_json(spec: SceneSpec) -> str:
    """Serialise a scene spec (JSON text); `scene_from_json` rebuilds it exactly."""
    return json.dumps(dataclasses.asdict(spec), indent=2, sort_keys=True)


def scene_from_json(text: str) -> SceneSpec:
    """The scene spec serialised by `scene_to_json`."""
    data = json.loads(text)
    kind = data.pop("kind", None)
    extent = Extent(**data.pop("extent"))
    if kind == "flat-floor":
        return FlatFloor(extent=extent, **data)
    if kind == "sloping-board":
        return SlopingBoard(extent=extent, **data)
    if kind == "breakwater":
        damage = data.pop("damage")
        return Breakwater(extent=extent, damage=Damage(**damage) if damage else None, **data)
    raise JaxStereoError(f"scene JSON has unknown kind {kind!r}")
