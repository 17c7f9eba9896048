"""A fine source-plane grid stored only where rays read it: square tiles, allocated once.

The clumps' source-plane grid (0.25 mas pixels over the whole galaxy: ~4e7
pixels for the paper's scene) is read only by the rays that land near a
ray-traced clump. At build time the rays are known, so the model keeps only the
tiles their bilinear neighbours touch; stamps are scattered into those tiles
(light falling in other tiles is read by no ray and is dropped) and rays gather
from them. Memory and time then follow the area the rays cover, not the grid.

Coordinates are fractional pixel indices of the (padded) grid, (0, 0) the
centre of pixel [0, 0]; positions outside are clamped to the edge, as in
`lensing.grid.bilinear_interpolate_channels`.
"""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import numpy as np

from .lensing.grid import bilinear_gather, bilinear_neighbours


@dataclasses.dataclass(frozen=True)
class TileLayout:
    """Static shape of a tiled grid: grid [ny, nx] in tiles of side `tile`, `slots` allocated."""

    ny: int
    nx: int
    tile: int
    slots: int

    @property
    def tiles_x(self):
        return -(-self.nx // self.tile)

    @property
    def size(self):
        """Length of the flat storage (one spare row: where dropped light goes)."""
        return self.slots * self.tile * self.tile + 1


def active_tiles(x_pix, y_pix, shape, tile: int = 32, chunk: int = 1 << 22):
    """(TileLayout, slot map [tiles] int32, −1 where unused) for rays at (x_pix, y_pix) (numpy)."""
    ny, nx = shape
    tx = -(-nx // tile)
    used = np.zeros((-(-ny // tile)) * tx, bool)
    xf, yf = np.ravel(x_pix), np.ravel(y_pix)
    for s in range(0, xf.size, chunk):
        _, _, i0, j0, i1, j1 = bilinear_neighbours(xf[s:s + chunk], yf[s:s + chunk], ny, nx, np)
        for j in (j0, j1):
            for i in (i0, i1):
                used[(j // tile) * tx + i // tile] = True
    slot_map = np.full(used.size, -1, np.int32)
    slot_map[used] = np.arange(int(used.sum()), dtype=np.int32)
    return TileLayout(ny, nx, tile, int(used.sum())), slot_map


def flat_index(layout: TileLayout, slot_map, rows, cols):
    """Index in the flat storage of grid pixels (rows, cols); the spare row where unstored."""
    t = layout.tile
    inside = (rows >= 0) & (rows < layout.ny) & (cols >= 0) & (cols < layout.nx)
    r = jnp.clip(rows, 0, layout.ny - 1)
    c = jnp.clip(cols, 0, layout.nx - 1)
    slot = slot_map[(r // t) * layout.tiles_x + c // t]
    flat = slot * (t * t) + (r % t) * t + c % t
    return jnp.where(inside & (slot >= 0), flat, layout.size - 1)


def scatter_stamps(layout: TileLayout, slot_map, stamps, i0, j0, weights, storage=None):
    """Add Σ_k weights[k, c] × stamps[k] (origins (i0, j0) in grid pixels) to the tiles.

    storage: [size, C] to add to (zeros if None). The spare row collects what falls
    outside the stored tiles (no ray reads it).
    """
    n, s, _ = stamps.shape
    k = jnp.arange(s)
    rows = j0[:, None, None] + k[None, :, None]
    cols = i0[:, None, None] + k[None, None, :]
    idx = flat_index(layout, slot_map, rows, cols)
    vals = stamps[..., None] * weights[:, None, None, :]
    if storage is None:
        storage = jnp.zeros((layout.size, weights.shape[1]), vals.dtype)
    return storage.at[idx.ravel()].add(vals.reshape(-1, weights.shape[1]))


def bilinear(layout: TileLayout, slot_map, storage, x_pix, y_pix):
    """Bilinear interpolation [..., C] of the tiled grid at fractional pixel indices."""
    return bilinear_gather(lambda j, i: storage[flat_index(layout, slot_map, j, i)],
                           x_pix, y_pix, layout.ny, layout.nx)
