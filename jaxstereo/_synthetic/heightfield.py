"""Textured heightfields z(x, y) on a regular grid: the synthetic flume's scene geometry."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float

from .._geometry.errors import JaxStereoError
from .._geometry.module import Module, field


class Heightfield(Module):
    """A surface `z = height(x, y)` sampled on a regular grid, bilinear in between, with an albedo map.

    Grid node `(i, j)` (row `i`, column `j`) sits at `x = x0 + j * spacing`, `y = y0 + i * spacing`.
    Outside the grid the surface does not exist (rays miss it).

    **Fields:**

    - `z`: heights (ny, nx), world metres (Z up).
    - `albedo`: RGB reflectance in [0, 1] (ny, nx, 3).
    - `x0`, `y0`: world coordinates of node (0, 0), metres.
    - `spacing`: grid spacing, metres.
    - `block`: side of the coarse blocks (in nodes) of the max map used to skip empty space.
    - `z_min`, `z_max`: the height range, metres (static).
    - `block_max`: max height over each coarse block and its 8 neighbours (nby, nbx), metres.
    - `fine_block`: side of the fine blocks (in nodes), `FINE_BLOCK`.
    - `fine_max`: the same bound over fine blocks (nfy, nfx), metres: it lets a ray that has come below a coarse
      block's bound (beside a rock) still skip, where the rock is no nearer than a fine block.
    - `cell_max`: the same bound over single grid cells (ny - 1, nx - 1), metres.
    """

    z: Float[Array, "ny nx"]
    albedo: Float[Array, "ny nx 3"]
    x0: float = field(static=True)
    y0: float = field(static=True)
    spacing: float = field(static=True)
    block: int = field(static=True)
    z_min: float = field(static=True)
    z_max: float = field(static=True)
    block_max: Float[Array, "nby nbx"]
    fine_block: int = field(static=True)
    fine_max: Float[Array, "nfy nfx"]
    cell_max: Float[Array, "ncy ncx"]

    def __init__(self, z: Float[ArrayLike, "ny nx"], albedo: Float[ArrayLike, "ny nx 3"], x0: float, y0: float,
                 spacing: float, block: int = 16):
        z = np.asarray(z, dtype=np.float64)
        albedo = np.asarray(albedo, dtype=np.float32)
        if z.ndim != 2 or min(z.shape) < 2:
            raise JaxStereoError(f"heightfield z must be a 2-D grid of at least 2x2 nodes, got shape {z.shape}")
        if albedo.shape != z.shape + (3,):
            raise JaxStereoError(f"heightfield albedo must have shape {z.shape + (3,)}, got {albedo.shape}")
        if not np.all(np.isfinite(z)):
            raise JaxStereoError("heightfield z contains NaN or infinite values")
        if not spacing > 0:
            raise JaxStereoError(f"heightfield spacing must be positive, got {spacing}")
        self.z = jnp.asarray(z)
        self.albedo = jnp.asarray(albedo)
        self.x0, self.y0, self.spacing, self.block = float(x0), float(y0), float(spacing), int(block)
        self.z_min, self.z_max = float(z.min()), float(z.max())
        self.block_max = jnp.asarray(_dilated_block_max(z, self.block))
        self.fine_block = min(FINE_BLOCK, self.block)
        self.fine_max = jnp.asarray(_dilated_block_max(z, self.fine_block))
        self.cell_max = jnp.asarray(_dilated_block_max(z, 1))

    @property
    def shape(self) -> tuple[int, int]:
        """(ny, nx) nodes."""
        return self.z.shape

    @property
    def x(self) -> np.ndarray:
        """Node x coordinates (nx,), metres."""
        return self.x0 + self.spacing * np.arange(self.z.shape[1])

    @property
    def y(self) -> np.ndarray:
        """Node y coordinates (ny,), metres."""
        return self.y0 + self.spacing * np.arange(self.z.shape[0])

    @property
    def z_range(self) -> tuple[float, float]:
        """(min, max) height, metres."""
        return self.z_min, self.z_max

    def _cell(self, xy):
        ny, nx = self.z.shape
        gx = (xy[..., 0] - self.x0) / self.spacing
        gy = (xy[..., 1] - self.y0) / self.spacing
        inside = (gx >= 0) & (gx <= nx - 1) & (gy >= 0) & (gy <= ny - 1)
        j = jnp.clip(jnp.floor(gx), 0, nx - 2).astype(jnp.int32)
        i = jnp.clip(jnp.floor(gy), 0, ny - 2).astype(jnp.int32)
        return i, j, gx - j, gy - i, inside

    def height_at(self, xy: Float[ArrayLike, "*#batch 2"]) -> tuple[Float[Array, "*#batch"], Bool[Array, "*#batch"]]:
        """Bilinear height (metres) at world points (..., 2); returns `(z, inside)`."""
        i, j, fx, fy, inside = self._cell(xy)
        z = self.z
        z00, z01, z10, z11 = z[i, j], z[i, j + 1], z[i + 1, j], z[i + 1, j + 1]
        h = (z00 * (1 - fx) + z01 * fx) * (1 - fy) + (z10 * (1 - fx) + z11 * fx) * fy
        return h, inside

    def normal_at(self, xy: Float[ArrayLike, "*#batch 2"]) -> Float[Array, "*#batch 3"]:
        """Unit surface normal (..., 3) of the bilinear surface at world points (..., 2), pointing up."""
        i, j, fx, fy, _ = self._cell(xy)
        z = self.z
        z00, z01, z10, z11 = z[i, j], z[i, j + 1], z[i + 1, j], z[i + 1, j + 1]
        dzdx = ((z01 - z00) * (1 - fy) + (z11 - z10) * fy) / self.spacing
        dzdy = ((z10 - z00) * (1 - fx) + (z11 - z01) * fx) / self.spacing
        n = jnp.stack([-dzdx, -dzdy, jnp.ones_like(dzdx)], axis=-1)
        return n / jnp.linalg.norm(n, axis=-1, keepdims=True)

    def albedo_at(self, xy: Float[ArrayLike, "*#batch 2"]) -> Float[Array, "*#batch 3"]:
        """Bilinear albedo (..., 3) at world points (..., 2)."""
        i, j, fx, fy, _ = self._cell(xy)
        a = self.albedo
        fx = fx[..., None].astype(a.dtype)
        fy = fy[..., None].astype(a.dtype)
        return (a[i, j] * (1 - fx) + a[i, j + 1] * fx) * (1 - fy) + (a[i + 1, j] * (1 - fx) + a[i + 1, j + 1] * fx) * fy

    def block_max_at(self, xy: Float[ArrayLike, "*#batch 2"]) -> Float[Array, "*#batch"]:
        """Upper bound on the height within one block side (`block * spacing` m) of each point (..., 2)."""
        return _bound_at(self.block_max, self.block * self.spacing, self.x0, self.y0, xy)

    def fine_max_at(self, xy: Float[ArrayLike, "*#batch 2"]) -> Float[Array, "*#batch"]:
        """Upper bound on the height within one fine block side (`fine_block * spacing` m) of each point (..., 2)."""
        return _bound_at(self.fine_max, self.fine_block * self.spacing, self.x0, self.y0, xy)

    def cell_max_at(self, xy: Float[ArrayLike, "*#batch 2"]) -> Float[Array, "*#batch"]:
        """Upper bound on the height within one grid spacing of each point (..., 2)."""
        return _bound_at(self.cell_max, self.spacing, self.x0, self.y0, xy)


FINE_BLOCK = 4  # nodes: the middle level of the bounds that let a ray skip empty space


def _bound_at(bound, size, x0, y0, xy):
    """`bound` (nby, nbx) of blocks `size` metres wide from (x0, y0), looked up at points (..., 2)."""
    nby, nbx = bound.shape
    bj = jnp.clip(jnp.floor((xy[..., 0] - x0) / size), 0, nbx - 1).astype(jnp.int32)
    bi = jnp.clip(jnp.floor((xy[..., 1] - y0) / size), 0, nby - 1).astype(jnp.int32)
    return bound[bi, bj]


def _dilated_block_max(z: np.ndarray, block: int) -> np.ndarray:
    """Max over each block x block tile (tiles include the shared boundary node), then over 3x3 tiles."""
    ny, nx = z.shape
    nby = -(-(ny - 1) // block)
    nbx = -(-(nx - 1) // block)
    padded = np.full((nby * block + 1, nbx * block + 1), -np.inf)
    padded[:ny, :nx] = z
    # Tile (bi, bj) covers nodes [bi*block, (bi+1)*block] inclusive: cells of the tile and its edge nodes.
    core = padded[:-1, :-1].reshape(nby, block, nbx, block).max(axis=(1, 3))
    edge_row = padded[block::block, :-1].reshape(nby, nbx, block).max(axis=2)
    edge_col = padded[:-1, block::block].reshape(nby, block, nbx).max(axis=1)
    corner = padded[block::block, block::block]
    tile = np.maximum.reduce([core, edge_row, edge_col, corner])
    out = tile.copy()
    p = np.pad(tile, 1, constant_values=-np.inf)
    for di in (-1, 0, 1):
        for dj in (-1, 0, 1):
            out = np.maximum(out, p[1 + di : 1 + di + nby, 1 + dj : 1 + dj + nbx])
    return out
