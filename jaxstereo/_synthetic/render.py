"""Ray-cast rendering of heightfield scenes seen through a flat water surface, with exact ground truth.

Each pixel's ray is refracted exactly at the interface (vector Snell's law, as in the refraction core)
and intersected with the bilinear heightfield: marched with steps that skip empty space (dilated max maps
over blocks of 16 and 4 nodes and over single cells bound the surface), then the last step, which brackets
the surface, is narrowed by bisection and solved by false position (Illinois): within nanometres of the
surface, within 10 um where the bracket holds a vertical step of it (a few pixels in a million). Where a
ray's path through the surface is shorter than the 1 mm fine step (a rock's edge grazed), the sampling may
miss it and find the surface behind: measured in 25 of 500,000 pixels of a breakwater view.
"""

from __future__ import annotations

import dataclasses
import logging
import time

import jax
import jax.numpy as jnp
import numpy as np

from .._geometry.camera import Camera
from .._geometry.errors import JaxStereoError
from .._geometry.interface import Interface, check_camera_above
from .._geometry.precision import float64
from .._geometry.refraction import intersect_plane, refract_directions
from .heightfield import Heightfield

log = logging.getLogger("jaxstereo")

# Water absorption per metre of path, red, green, blue (gives depth a blue-green cast).
WATER_ATTENUATION = (2.0, 0.7, 0.5)
# Narrowing the bracketing step: halvings, then false-position (Illinois) steps.
ROOT_BISECTIONS = 3
ROOT_SECANTS = 5


@dataclasses.dataclass(frozen=True)
class RenderOptions:
    """How to render.

    **Fields:** `fine_step_m` marching step near the surface (m); `supersample` odd number of rays
    per pixel side; `light` unit direction towards the light (world); `ambient` fraction of light that
    is ambient; `noise_dn` sensor noise standard deviation (8-bit digital numbers); `seed` for the noise;
    `chunk` rays per compiled batch; `pool` rays of a batch traced at once (a finished ray's place goes to
    the next one); `max_steps` cap on marching steps per ray; `skip_levels` how many of the heightfield's
    bounds (blocks of 16 nodes, of 4, single cells) set the steps that skip empty space: 1 marches in 1 mm steps
    wherever a ray is below a 16-node block's top (beside a rock); 3 rendered an 864x576 breakwater pair in
    0.79x the time wet and 0.83x dry (`benchmarks/bench_render.py`).
    """

    fine_step_m: float = 1.0e-3
    supersample: int = 1
    light: tuple[float, float, float] = (0.35, -0.25, 0.9)
    ambient: float = 0.3
    noise_dn: float = 1.0
    seed: int = 0
    chunk: int = 1 << 19
    pool: int = 1 << 13
    max_steps: int = 2000
    skip_levels: int = 3

    def __post_init__(self):
        if self.supersample < 1 or self.supersample % 2 == 0:
            raise JaxStereoError(f"supersample must be an odd positive integer, got {self.supersample}")
        if not self.fine_step_m > 0:
            raise JaxStereoError(f"fine_step_m must be positive, got {self.fine_step_m}")
        if self.chunk < 1 or self.pool < 1:
            raise JaxStereoError(f"chunk and pool must be positive ray counts, got {self.chunk} and {self.pool}")
        if self.skip_levels not in (1, 2, 3):
            raise JaxStereoError(f"skip_levels must be 1, 2 or 3, got {self.skip_levels}")


@dataclasses.dataclass(frozen=True)
class RenderedView:
    """One rendered camera view with its ground truth, all (height, width, ...) arrays.

    **Fields:** `image` uint8 RGB (h, w, 3); `points` world metres of the surface seen through each
    pixel centre (h, w, 3), NaN where nothing is hit; `depth` camera-frame z of those points (h, w), m;
    `hit` (h, w) bool; `submerged` (h, w) bool, true where the point lies under the water plane.
    """

    image: np.ndarray
    points: np.ndarray
    depth: np.ndarray
    hit: np.ndarray
    submerged: np.ndarray


def _march(hf: Heightfield, origin, direction, s_max, fine_step, max_steps, pool, skip_levels):
    """First intersection of rays (n, 3) with the heightfield within `[0, s_max]`; returns `(s, hit)` (n,).

    A ray is marched with steps that skip empty space; where a sample first lies under the surface, the last
    step brackets it and is narrowed (`ROOT_BISECTIONS` halvings, then `ROOT_SECANTS` Illinois steps).
    Rays need from a few samples to a few hundred, so they are traced by a pool of `pool` slots rather than
    all at once: a slot whose ray is done (hit, past `s_max`, or `max_steps` samples without a hit) waits
    until a quarter of the pool has, and then those slots take the next rays in line, so that most of each
    iteration's work goes to rays that still need it. `s` is meaningful where `hit` is true.
    """
    n = origin.shape[0]
    pool = min(pool, n)
    block_m = hf.block * hf.spacing
    solve_steps = ROOT_BISECTIONS + ROOT_SECANTS

    def refill(slots, next_ray, s_out, hit_out):
        # Record the finished rays, then hand their slots (and the empty ones) the next rays in line.
        at = jnp.where(slots["done"], slots["ray"], n)
        s_out = s_out.at[at].set(slots["a"], mode="drop")
        hit_out = hit_out.at[at].set(slots["k"] >= 0, mode="drop")
        free = slots["done"] | (slots["ray"] >= n)
        fresh = next_ray + jnp.cumsum(free) - 1
        ray = jnp.where(free, jnp.where(fresh < n, fresh, n), slots["ray"])
        r = jnp.minimum(ray, n - 1)
        d = direction[r]
        new = {
            "ray": ray, "o": origin[r], "d": d, "end": jnp.where(ray < n, s_max[r], 0.0),
            # The longest step that stays within one block horizontally, and 1 / rate of descent.
            "xy_limit": block_m / jnp.maximum(jnp.linalg.norm(d[:, :2], axis=-1), 1e-12),
            "inv_descent": jnp.where(d[:, 2] < 0, 1.0 / jnp.maximum(-d[:, 2], 1e-12), jnp.inf),
            "a": jnp.zeros_like(slots["a"]), "b": jnp.zeros_like(slots["b"]),
            "g_a": jnp.ones_like(slots["g_a"]), "g_b": jnp.ones_like(slots["g_b"]),
            "k": jnp.full_like(slots["k"], -1), "side": jnp.zeros_like(slots["side"]),
            "steps": jnp.zeros_like(slots["steps"]), "done": jnp.zeros_like(slots["done"]),
        }
        slots = {key: jnp.where(free.reshape(-1, *[1] * (v.ndim - 1)), new[key], v) for key, v in slots.items()}
        return slots, jnp.minimum(next_ray + jnp.sum(free), n), s_out, hit_out

    def cond(state):
        slots, next_ray, _, _ = state
        return jnp.any(~slots["done"] & (slots["ray"] < n)) | (next_ray < n)

    def body(state):
        slots, next_ray, s_out, hit_out = state
        # Marching (k < 0): a is the current sample, b the previous one, g_b its height above the surface.
        # Solving (k >= 0): [a, b] brackets the surface (g_a > 0 >= g_b), after k steps. A finished slot keeps
        # its result (s in a; k >= 0 if hit) until its slot is refilled.
        a, b, g_a, g_b, k, side = (slots[key] for key in ("a", "b", "g_a", "g_b", "k", "side"))
        working = ~slots["done"] & (slots["ray"] < n)
        marching = k < 0
        fraction = jnp.where(g_a - g_b > 0, g_a / (g_a - g_b), 0.5)
        fraction = jnp.where(k < ROOT_BISECTIONS, 0.5, jnp.clip(fraction, 0.0, 1.0))
        t = jnp.where(marching, a, a + fraction * (b - a))
        p = slots["o"] + t[:, None] * slots["d"]
        h, inside = hf.height_at(p[:, :2])
        below = inside & (p[:, 2] <= h)
        g = jnp.where(below, jnp.minimum(p[:, 2] - h, 0.0), jnp.maximum(p[:, 2] - h, 1e-12))
        # The longest step that keeps the ray above every bound it may reach: a block's (or a fine block's, or
        # a cell's) bound holds within one block side of the point, and the ray drops gap / descent meanwhile.
        step = jnp.zeros_like(a)
        levels = ((hf.block_max_at, 1.0), (hf.fine_max_at, hf.fine_block / hf.block), (hf.cell_max_at, 1.0 / hf.block))
        for bound, side in levels[:skip_levels]:
            gap = p[:, 2] - bound(p[:, :2])
            safe = jnp.minimum(gap * slots["inv_descent"], side * slots["xy_limit"])
            step = jnp.maximum(step, jnp.where(gap > 0, safe, 0.0))
        step = jnp.maximum(step, fine_step)
        # Marching: where a sample first lies below the surface, [previous, current] brackets it.
        alive = slots["end"] > 0
        found = marching & alive & below
        missed = marching & ~found & (~alive | (a >= slots["end"]) | (slots["steps"] + 1 >= max_steps))
        march_a = jnp.where(found, b, jnp.minimum(a + step, slots["end"]))
        march_g_a = jnp.where(found, g_b, g_a)
        # Solving: the new point replaces the end on its side; an end kept twice in a row has its g halved.
        secant = k >= ROOT_BISECTIONS
        solve_a = jnp.where(below, a, t)
        solve_b = jnp.where(below, t, b)
        solve_g_a = jnp.where(below, jnp.where(secant & (side > 0), 0.5 * g_a, g_a), g)
        solve_g_b = jnp.where(below, g, jnp.where(secant & (side < 0), 0.5 * g_b, g_b))
        k_next = jnp.where(found, 0, jnp.where(marching, k, k + 1))
        located = ~marching & (k_next >= solve_steps)
        update = {
            "a": jnp.where(marching, jnp.where(missed, a, march_a), jnp.where(located, t, solve_a)),
            "b": jnp.where(marching, a, solve_b),
            "g_a": jnp.where(marching, march_g_a, solve_g_a),
            "g_b": jnp.where(marching, g, solve_g_b),
            "k": k_next,
            "side": jnp.where(marching, 0, jnp.where(below, 1, -1)),
            "steps": slots["steps"] + marching,
            "done": missed | located,
        }
        slots = dict(slots, **{key: jnp.where(working, v, slots[key]) for key, v in update.items()})
        idle = slots["done"] | (slots["ray"] >= n)
        return jax.lax.cond(4 * jnp.sum(idle) >= pool, lambda state: refill(*state), lambda state: state,
                            (slots, next_ray, s_out, hit_out))

    zeros = jnp.zeros(pool, origin.dtype)
    slots = {"ray": jnp.full(pool, n), "o": jnp.zeros((pool, 3), origin.dtype), "d": jnp.zeros((pool, 3), origin.dtype),
             "end": zeros, "xy_limit": zeros, "inv_descent": zeros, "a": zeros, "b": zeros, "g_a": zeros, "g_b": zeros,
             "k": jnp.zeros(pool, jnp.int32), "side": jnp.zeros(pool, jnp.int32), "steps": jnp.zeros(pool, jnp.int32),
             "done": jnp.zeros(pool, bool)}
    state = refill(slots, jnp.asarray(0), jnp.zeros(n, origin.dtype), jnp.zeros(n, bool))
    state = jax.lax.while_loop(cond, body, state)
    _, _, s, hit = refill(*state)
    return s, hit


def _trace(camera: Camera, hf: Heightfield, interface: Interface | None, pixels, fine_step, max_steps, pool,
           skip_levels):
    """Trace pixel rays (n, 2) to the surface: returns points (n, 3), hit (n,), submerged (n,), water path (n,)."""
    origin, d = camera.backproject(pixels)
    z_lo, z_hi = hf.z_range
    z_top = z_hi + 1e-3
    z_bottom = z_lo - 1e-3
    dz = jnp.minimum(d[:, 2], -1e-12)
    # Start where the ray descends through the top of the scene.
    s0 = jnp.maximum((origin[:, 2] - z_top) / -dz, 0.0)
    start = origin + s0[:, None] * d
    s_floor = jnp.maximum((start[:, 2] - z_bottom) / -dz, 0.0)
    if interface is None:
        s_air = s_floor
    else:
        _, s_if = intersect_plane(origin, d, interface.normal, interface.level)
        reaches = jnp.isfinite(s_if) & (s_if > 0)
        s_air = jnp.where(reaches, jnp.clip(s_if - s0, 0.0, s_floor), s_floor)
    s_air = jnp.where(d[:, 2] < 0, s_air, 0.0)
    s1, hit1 = _march(hf, start, d, s_air, fine_step, max_steps, pool, skip_levels)
    p_air = start + s1[:, None] * d
    if interface is None:
        return p_air, hit1, jnp.zeros_like(hit1), jnp.zeros_like(s1)
    # The refraction happens where the ray crosses the interface, also when the whole scene lies under it.
    surface = origin + jnp.where(reaches, s_if, 0.0)[:, None] * d
    d_w, ok = refract_directions(d, interface.normal, interface.n_air, interface.n_water)
    dzw = jnp.minimum(d_w[:, 2], -1e-12)
    s_w_max = jnp.where(~hit1 & ok & reaches & (d[:, 2] < 0), jnp.maximum((surface[:, 2] - z_bottom) / -dzw, 0.0), 0.0)
    s2, hit2 = _march(hf, surface, d_w, s_w_max, fine_step, max_steps, pool, skip_levels)
    p_w = surface + s2[:, None] * d_w
    hit = hit1 | hit2
    points = jnp.where(hit1[:, None], p_air, p_w)
    submerged = ~hit1 & hit2
    return points, hit, submerged, jnp.where(submerged, s2, 0.0)


def _shade(hf: Heightfield, points, hit, water_path, light, ambient):
    xy = points[:, :2]
    albedo = hf.albedo_at(xy).astype(points.dtype)
    n = hf.normal_at(xy)
    lam = jnp.clip(n @ light, 0.0, 1.0)
    radiance = albedo * (ambient + (1.0 - ambient) * lam)[:, None]
    radiance = radiance * jnp.exp(-water_path[:, None] * jnp.asarray(WATER_ATTENUATION, points.dtype))
    return jnp.where(hit[:, None], radiance, 0.0)


@float64
def render_view(
    camera: Camera,
    heightfield: Heightfield,
    interface: Interface | None = None,
    options: RenderOptions = RenderOptions(),
    progress: bool = False,
) -> RenderedView:
    """Render what `camera` sees of `heightfield`, through `interface` if given (None: a dry flume).

    **Arguments:**

    - `camera`: the camera; its `image_size` sets the output size.
    - `heightfield`: the scene.
    - `interface`: the water surface, or None for no water.
    - `options`: `RenderOptions`.
    - `progress`: log one line per tenth of the work (logger "jaxstereo").

    **Returns:** a `RenderedView` with the 8-bit image and per-pixel ground truth.
    """
    if interface is not None:
        check_camera_above(camera.center, interface)
    w, h = camera.image_size
    colour, points, hit, submerged = _trace_pixels(camera, heightfield, interface, options, progress)
    rng = np.random.default_rng(options.seed)
    srgb = np.clip(colour, 0.0, 1.0) ** (1 / 2.2) * 255.0
    if options.noise_dn > 0:
        srgb = srgb + rng.normal(0.0, options.noise_dn, srgb.shape)
    image = np.clip(np.round(srgb), 0, 255).astype(np.uint8).reshape(h, w, 3)
    points = points.reshape(h, w, 3)
    pc = points @ np.asarray(camera.pose.R).T + np.asarray(camera.pose.t)
    return RenderedView(image=image, points=points, depth=pc[..., 2], hit=hit.reshape(h, w),
                        submerged=submerged.reshape(h, w))


def _trace_pixels(camera: Camera, hf: Heightfield, interface, options: RenderOptions, progress: bool):
    """Trace every pixel in fixed-size chunks (one compilation per chunk size), `supersample`^2 rays each.

    **Returns:** per pixel (row-major, w * h): linear colour (n, 3) averaged over the sub-rays, and the
    centre ray's surface point (n, 3) world metres (NaN where it hit nothing), hit and submerged flags (n,).
    """
    w, h = camera.image_size
    ss = options.supersample
    offsets = (np.arange(ss) + 0.5) / ss - 0.5
    ox, oy = np.meshgrid(offsets, offsets)
    centre = ss * ss // 2  # the middle sub-ray is the pixel centre (odd supersampling)
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    n_pix = w * h
    # Batches of `chunk` rays, or fewer for a small image: its pixel count rounded up to a power of two, so that
    # a small image is not padded to a whole batch and few batch shapes are compiled.
    chunk_pixels = max(1, min(options.chunk // (ss * ss), 1 << int(np.ceil(np.log2(n_pix)))))
    light = np.asarray(options.light, dtype=np.float64)
    light = jnp.asarray(light / np.linalg.norm(light))
    step_fn = _render_chunk_fn(ss, options.fine_step_m, options.max_steps, float(options.ambient), options.pool,
                               options.skip_levels)
    colour = np.zeros((n_pix, 3), np.float64)
    points = np.full((n_pix, 3), np.nan)
    hit = np.zeros(n_pix, bool)
    submerged = np.zeros(n_pix, bool)
    flat_u, flat_v = u.ravel(), v.ravel()
    sub = np.stack([ox.ravel(), oy.ravel()], axis=-1)
    started = time.perf_counter()
    n_chunks = -(-n_pix // chunk_pixels)
    for k, start in enumerate(range(0, n_pix, chunk_pixels)):
        stop = min(start + chunk_pixels, n_pix)
        m = stop - start
        pix = np.zeros((chunk_pixels, 2))
        pix[:m] = np.stack([flat_u[start:stop], flat_v[start:stop]], axis=-1)
        rays = (pix[:, None, :] + sub[None, :, :]).reshape(-1, 2)
        c, p, ht, sm = step_fn(camera, hf, interface, jnp.asarray(rays), light)
        colour[start:stop] = np.asarray(c).reshape(chunk_pixels, ss * ss, 3).mean(axis=1)[:m]
        ht = np.asarray(ht).reshape(chunk_pixels, ss * ss)[:m, centre]
        p = np.asarray(p).reshape(chunk_pixels, ss * ss, 3)[:m, centre]
        points[start:stop] = np.where(ht[:, None], p, np.nan)
        hit[start:stop] = ht
        submerged[start:stop] = np.asarray(sm).reshape(chunk_pixels, ss * ss)[:m, centre]
        if progress and (k + 1) % max(1, n_chunks // 10) == 0:
            log.info("render %dx%d: %d%% (%.1f s)", w, h, 100 * stop // n_pix, time.perf_counter() - started)
    return colour, points, hit, submerged


_CHUNK_FNS: dict = {}


def _render_chunk_fn(ss, fine_step, max_steps, ambient, pool, skip_levels):
    key = (ss, fine_step, max_steps, ambient, pool, skip_levels)
    if key not in _CHUNK_FNS:

        @jax.jit
        def fn(camera, hf, interface, pixels, light):
            points, hit, submerged, water_path = _trace(camera, hf, interface, pixels, fine_step, max_steps, pool,
                                                        skip_levels)
            colour = _shade(hf, points, hit, water_path, light, ambient)
            return colour, points, hit, submerged

        _CHUNK_FNS[key] = fn
    return _CHUNK_FNS[key]
