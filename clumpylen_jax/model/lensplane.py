"""The traced lens plane inside a model: which lens-plane pixels receive source light, the
rays in them, and how lens-plane images reach each band's sub-grid.

The geometry (tracing, footprints, interpolation of the traced corners) is
`lensing/tracing.py`; this Module keeps what the renderers read at run time.
"""

from __future__ import annotations

from typing import Optional

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from ..lensing import tracing
from ..lensing.grid import bilinear_patch
from ..pixels import Grid, gauss_legendre_offsets, rebin_sparse, sparse_rebin_operators


def _cols(a, lo, hi):
    """Columns lo:hi of a [T, n] operator array, or None."""
    return None if a is None else a[:, lo:hi]


def ray_cell_covariance(corner_b1, corner_b2, rows, cols, offsets, lens_subsampling: int):
    """(s11, s12, s22) [M, R] (arcsec²): second moment of the source-plane image of each ray's
    cell, a square of 1/lens_subsampling of its lens pixel (variance (side)²/12 per axis),
    through the local bilinear map of the pixel's traced corners: S = (dx dxᵀ + dy dyᵀ)/(12 n²)
    with dx, dy the β change across the whole pixel along x and y at the ray."""
    fx = (offsets[0] + 0.5)[None, :]
    fy = (offsets[1] + 0.5)[None, :]
    _, dx1, dy1 = bilinear_patch(corner_b1, rows[:, None], cols[:, None], fx, fy)
    _, dx2, dy2 = bilinear_patch(corner_b2, rows[:, None], cols[:, None], fx, fy)
    k = 1.0 / (12.0 * lens_subsampling ** 2)
    return (k * (dx1 * dx1 + dy1 * dy1), k * (dx1 * dx2 + dy1 * dy2), k * (dx2 * dx2 + dy2 * dy2))


class LensPlane(eqx.Module):
    """The traced pixels (rows, cols) of the high-resolution lens-plane `grid`, the β of
    their centres, and the rays: β at Gauss–Legendre sub-pixel offsets (weights [R]) of the
    pixels (ray_rows, ray_cols) that need them (all traced pixels, or those reaching a
    ray-traced clump), which lie in the window rows r0:r1, cols c0:c1 of the grid.
    rebin_ops: per band, the sparse operators from the grid to its sub-grid."""

    grid: Grid = eqx.field(static=True)
    rows: jnp.ndarray
    cols: jnp.ndarray
    beta1_center: jnp.ndarray
    beta2_center: jnp.ndarray
    beta1: jnp.ndarray
    beta2: jnp.ndarray
    ray_weights: jnp.ndarray
    ray_rows: jnp.ndarray
    ray_cols: jnp.ndarray
    ray_window: tuple = eqx.field(static=True)
    rebin_ops: tuple
    ray_cov: Optional[tuple] = None     # (s11, s12, s22) [M, R]: second moment of each ray's
                                        # source-plane cell (arcsec²), where asked for

    @classmethod
    def build(cls, corner_b1, corner_b2, grid: Grid, rows, cols, ray_pixels, layouts,
              lens_subsampling: int, dtype, ray_cov: bool = False):
        """From the traced corners: rays in the pixels `ray_pixels` (indices into rows, cols).
        ray_cov: also each ray's cell second moment (`ray_cell_covariance`).
        Returns (the plane, (β1, β2) of its rays in numpy float64 for other builders)."""
        sel = ray_pixels
        window = ((int(rows[sel].min()), int(rows[sel].max()) + 1,
                   int(cols[sel].min()), int(cols[sel].max()) + 1) if sel.size else (0, 0, 0, 0))
        # with cell moments the rays are the centres of equal cells that tile the pixel (the
        # Gauss–Legendre points' cells would overlap and leave gaps)
        offs, wts = (((np.arange(lens_subsampling) + 0.5) / lens_subsampling - 0.5,
                      np.full(lens_subsampling, 1.0 / lens_subsampling)) if ray_cov
                     else gauss_legendre_offsets(lens_subsampling))
        ox, oy = np.meshgrid(offs, offs)
        wxy = np.outer(wts, wts).ravel()
        b1, b2 = tracing.rays_in_pixels(corner_b1, corner_b2, rows[sel], cols[sel],
                                        (ox.ravel(), oy.ravel()))
        c1, c2 = tracing.rays_in_pixels(corner_b1, corner_b2, rows, cols,
                                        (np.zeros(1), np.zeros(1)))
        # once per sub-grid: bands on one sub-grid share its operators (the paper scene's
        # nine bands have three sub-grids)
        per_subgrid = {}
        for lay in layouts:
            if lay.sub_grid not in per_subgrid:
                per_subgrid[lay.sub_grid] = tuple(
                    (jnp.asarray(t), jnp.asarray(w, dtype),
                     None if m is None else jnp.asarray(m, dtype))
                    for t, w, m in sparse_rebin_operators(grid, lay.sub_grid))
        ops = tuple(per_subgrid[lay.sub_grid] for lay in layouts)
        return cls(grid, jnp.asarray(rows), jnp.asarray(cols), jnp.asarray(c1[:, 0], dtype),
                   jnp.asarray(c2[:, 0], dtype), jnp.asarray(b1, dtype), jnp.asarray(b2, dtype),
                   jnp.asarray(wxy, dtype), jnp.asarray(rows[sel]), jnp.asarray(cols[sel]),
                   window, ops,
                   tuple(jnp.asarray(v, dtype) for v in ray_cell_covariance(
                       corner_b1, corner_b2, rows[sel], cols[sel], (ox.ravel(), oy.ravel()),
                       lens_subsampling)) if ray_cov else None), (b1, b2)

    @property
    def dtype(self):
        return self.beta1_center.dtype

    @property
    def pixel_area(self):
        return self.grid.pixel_arcsec**2

    def scatter(self, values):
        """Values [M, C] of the traced pixels as a lens-plane image [ny, nx, C]."""
        img = jnp.zeros(self.grid.shape + (values.shape[1],), values.dtype)
        return img.at[self.rows, self.cols].set(values)

    def window_image(self, values):
        """Values [C, P] of the pixels with rays as an image [h, w, C] of the ray window."""
        r0, r1, c0, c1 = self.ray_window
        img = jnp.zeros((r1 - r0, c1 - c0, values.shape[0]), values.dtype)
        return img.at[self.ray_rows - r0, self.ray_cols - c0].set(values.T)

    def add_window(self, image, window):
        """A lens-plane image [ny, nx, C] with a ray-window image added."""
        r0, r1, c0, c1 = self.ray_window
        return image.at[r0:r1, c0:c1].add(window)

    def to_subgrid(self, image, k: int, shape):
        """A lens-plane image [ny, nx, C] rebinned onto band k's sub-grid (of this shape)."""
        return rebin_sparse(image, self.rebin_ops[k], shape)

    def window_to_subgrid(self, window, k: int, shape):
        """A ray-window image rebinned onto band k's sub-grid."""
        r0, r1, c0, c1 = self.ray_window
        (ty, wy, my), (tx, wx, mx) = self.rebin_ops[k]
        return rebin_sparse(window, ((ty[:, r0:r1], wy[:, r0:r1], _cols(my, r0, r1)),
                                     (tx[:, c0:c1], wx[:, c0:c1], _cols(mx, c0, c1))), shape)
