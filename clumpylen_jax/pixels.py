"""Pixel grids and flux-conserving rebinning between them.

A `Grid` is static (hashable): pixel [j, i] (row j along θ2/β2, column i along
θ1/β1) is the square of side `pixel_arcsec` centred at
(x0_arcsec + i·pixel, y0_arcsec + j·pixel). Images are arrays [ny, nx] of flux
per pixel (counts/s), never surface brightness, so that rebinning is a sum.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np


@dataclasses.dataclass(frozen=True)
class Grid:
    """A regular square-pixel grid. x0/y0: centre of pixel [0, 0], arcsec."""

    x0_arcsec: float
    y0_arcsec: float
    pixel_arcsec: float
    nx: int
    ny: int

    def __post_init__(self):
        # plain Python numbers: numpy scalars would promote float32 computations to float64
        for name in ("x0_arcsec", "y0_arcsec", "pixel_arcsec"):
            object.__setattr__(self, name, float(getattr(self, name)))
        for name in ("nx", "ny"):
            object.__setattr__(self, name, int(getattr(self, name)))

    @classmethod
    def covering(cls, x_range, y_range, pixel_arcsec):
        """The grid whose lower-left corner is (x_range[0], y_range[0]) and which covers the ranges."""
        nx = max(1, int(math.ceil((x_range[1] - x_range[0]) / pixel_arcsec - 1e-9)))
        ny = max(1, int(math.ceil((y_range[1] - y_range[0]) / pixel_arcsec - 1e-9)))
        return cls(float(x_range[0] + pixel_arcsec / 2), float(y_range[0] + pixel_arcsec / 2),
                   float(pixel_arcsec), nx, ny)  # Python floats: numpy scalars would promote float32

    @classmethod
    def centered(cls, center, half_size_arcsec, pixel_arcsec):
        """An odd-sized grid whose central pixel is centred on `center` (arcsec)."""
        half = int(math.ceil(half_size_arcsec / pixel_arcsec - 0.5 - 1e-9))
        n = 2 * max(half, 0) + 1
        return cls(float(center[0] - half * pixel_arcsec), float(center[1] - half * pixel_arcsec),
                   float(pixel_arcsec), n, n)

    @property
    def shape(self):
        return (self.ny, self.nx)

    @property
    def x_range(self):
        return (self.x0_arcsec - self.pixel_arcsec / 2,
                self.x0_arcsec + (self.nx - 0.5) * self.pixel_arcsec)

    @property
    def y_range(self):
        return (self.y0_arcsec - self.pixel_arcsec / 2,
                self.y0_arcsec + (self.ny - 0.5) * self.pixel_arcsec)

    def x_centers(self):
        return self.x0_arcsec + self.pixel_arcsec * np.arange(self.nx)

    def y_centers(self):
        return self.y0_arcsec + self.pixel_arcsec * np.arange(self.ny)

    def x_edges(self):
        return self.x0_arcsec + self.pixel_arcsec * (np.arange(self.nx + 1) - 0.5)

    def y_edges(self):
        return self.y0_arcsec + self.pixel_arcsec * (np.arange(self.ny + 1) - 0.5)

    def subdivided(self, factor: int):
        """The same area with each pixel split into factor × factor sub-pixels."""
        p = self.pixel_arcsec / factor
        return Grid(self.x0_arcsec - self.pixel_arcsec / 2 + p / 2,
                    self.y0_arcsec - self.pixel_arcsec / 2 + p / 2, p,
                    self.nx * factor, self.ny * factor)


def _overlaps(src_edges, dst_edges):
    """(lo, hi [m, n], src_lo, width [1, n]): the overlap [lo, hi] of destination pixel j
    with source pixel i (empty where hi ≤ lo), and the source pixels' lower edges and widths."""
    src_edges = np.asarray(src_edges, float)
    dst_edges = np.asarray(dst_edges, float)
    lo = np.maximum(dst_edges[:-1, None], src_edges[None, :-1])
    hi = np.minimum(dst_edges[1:, None], src_edges[None, 1:])
    return lo, hi, src_edges[None, :-1], np.diff(src_edges)[None, :]


def overlap_matrix(src_edges, dst_edges, src_pixel=None):
    """W[j, i] = fraction of source pixel i that lies in destination pixel j (1-D, numpy).

    W @ flux moves flux from the source bins to the destination bins; flux in
    source bins outside the destination range is dropped. Exact for any ratio
    of pixel sizes (pixels are treated as uniformly filled). src_pixel: the source
    pixels' common width when known (the PSF resampling divides by it; None: each
    pixel's width from its edges).
    """
    lo, hi, _, width = _overlaps(src_edges, dst_edges)
    return np.clip(hi - lo, 0.0, None) / (width if src_pixel is None else src_pixel)


def rebin_operators(src: Grid, dst: Grid):
    """(Wy, Wx) with dst_image = Wy @ src_image @ Wx.T (flux-conserving)."""
    return (overlap_matrix(src.y_edges(), dst.y_edges()),
            overlap_matrix(src.x_edges(), dst.x_edges()))


def rebin(image, wy, wx):
    """Apply separable rebinning operators to an image [..., ny, nx]."""
    wy = jnp.asarray(wy, image.dtype)
    wx = jnp.asarray(wx, image.dtype)
    return jnp.einsum("ji,...ik,lk->...jl", wy, image, wx)


def overlap_moments(src_edges, dst_edges):
    """M[j, i] = ∫ (s − ½) ds over the part of source pixel i in destination pixel j, with
    s ∈ [0, 1] across the source pixel (1-D, numpy): the share of a linear slope's flux
    that the overlap takes. Σ_j M[j, i] = 0 for a pixel inside the destination range."""
    lo, hi, start, width = _overlaps(src_edges, dst_edges)
    s0 = (lo - start) / width
    s1 = (hi - start) / width
    return np.where(hi > lo, 0.5 * (s1 - s0) * (s1 + s0 - 1.0), 0.0)


def sparse_overlap(src_edges, dst_edges):
    """The overlap operator of `overlap_matrix` by source pixel: (targets [T, n], weights
    [T, n], moments [T, n] or None).

    Source pixel i puts weights[t, i] of its flux into destination pixel targets[t, i];
    T is the most destination pixels any source pixel touches (2 when destination
    pixels are the larger). Targets are non-decreasing along i for every t (zero-weight
    padding included), so that sums over them can use sorted segment sums. moments: the
    `overlap_moments` of the same pairs, None when the grids nest (all zero).
    """
    w = overlap_matrix(src_edges, dst_edges)                 # [m, n]
    nz = w > 0
    count = nz.sum(axis=0)
    T = max(int(count.max()), 1)
    first = np.where(count > 0, np.argmax(nz, axis=0), 0)
    targets = np.minimum(first[None, :] + np.arange(T)[:, None], w.shape[0] - 1)
    valid = np.arange(T)[:, None] < count[None, :]
    weights = np.take_along_axis(w, targets, axis=0) * valid
    moments = np.take_along_axis(overlap_moments(src_edges, dst_edges), targets, axis=0) * valid
    targets = np.maximum.accumulate(targets, axis=1)
    return (targets.astype(np.int32), weights,
            moments if np.max(np.abs(moments), initial=0.0) > 1e-9 else None)


def sparse_rebin_operators(src: Grid, dst: Grid):
    """((ty, wy, my), (tx, wx, mx)): `sparse_overlap` along y and x, for `rebin_sparse`."""
    return (sparse_overlap(src.y_edges(), dst.y_edges()),
            sparse_overlap(src.x_edges(), dst.x_edges()))


def limited_slope(image):
    """Minmod slope of a flux image along axis 0 (flux per pixel per pixel): the smaller
    one-sided difference where both have one sign, else 0 (zero beyond the edges). A
    pixel's linear profile v + g (s − ½) then stays ≥ 0 wherever v ≥ 0."""
    zero = jnp.zeros_like(image[:1])
    ahead = jnp.concatenate([image[1:], zero]) - image
    behind = image - jnp.concatenate([zero, image[:-1]])
    return jnp.where(ahead * behind > 0,
                     jnp.sign(ahead) * jnp.minimum(jnp.abs(ahead), jnp.abs(behind)), 0.0)


def _rebin_axis0(image, targets, weights, size, moments=None):
    # with moments, each pixel shares its linear profile, not a flat one (one segment
    # sum per target slot either way: the slope term rides along)
    slope = None if moments is None else limited_slope(image)
    shape = (-1,) + (1,) * (image.ndim - 1)
    out = 0.0
    for t in range(targets.shape[0]):
        part = image * weights[t].reshape(shape).astype(image.dtype)
        if slope is not None:
            part = part + slope * moments[t].reshape(shape).astype(image.dtype)
        out = out + jax.ops.segment_sum(part, targets[t], num_segments=size,
                                        indices_are_sorted=True)
    return out


def rebin_sparse(image, ops, shape):
    """Flux-conserving rebinning of [ny, nx, ...] images (extra axes are carried along) to
    `shape` with `sparse_rebin_operators`: cost ∝ pixels, not pixels × output side.

    Where the grids do not nest, a source pixel split between destination pixels shares
    its flux as a linear (minmod-limited) profile across it, not a flat one: flat
    sharing is first order in the pixel size (1e-3 of the peak of a lensed host on
    0.031" pixels over 2.5 mas ones). Flux is conserved either way."""
    (ty, wy, my), (tx, wx, mx) = ops
    img = _rebin_axis0(image, ty, wy, shape[0], my)                       # [my, nx, ...]
    img = _rebin_axis0(jnp.swapaxes(img, 0, 1), tx, wx, shape[1], mx)     # [mx, my, ...]
    return jnp.swapaxes(img, 0, 1)


def bin_blocks(image, factor: int):
    """Sum factor × factor blocks (the pixel response of an integer oversampling)."""
    if factor == 1:
        return image
    *lead, ny, nx = image.shape
    return image.reshape(*lead, ny // factor, factor, nx // factor, factor).sum(axis=(-3, -1))


def gauss_legendre_offsets(order: int):
    """Sub-pixel sample offsets in (−0.5, 0.5) pixel and weights summing to 1 (1-D)."""
    x, w = np.polynomial.legendre.leggauss(order)
    return x / 2, w / 2
