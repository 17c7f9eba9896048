"""Pixel grids and flux-conserving rebinning between them.

A `Grid` is static (hashable): pixel [j, i] (row j along θ2/β2, column i along
θ1/β1) is the square of side `pixel_arcsec` centred at
(x0_arcsec + i·pixel, y0_arcsec + j·pixel). Images are arrays [ny, nx] of flux
per pixel (counts/s), never surface brightness, so that rebinning is a sum.
"""

from __future__ import annotations

import dataclasses
import functools
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

    def centers(self):
        """(x, y) [ny, nx]: every pixel's centre, arcsec."""
        return np.meshgrid(self.x_centers(), self.y_centers())

    def pixel_of(self, xy):
        """0-based (x, y) pixel coordinates of points xy [..., 2] (arcsec)."""
        xy = np.asarray(xy, float)
        return np.stack([(xy[..., 0] - self.x0_arcsec) / self.pixel_arcsec,
                         (xy[..., 1] - self.y0_arcsec) / self.pixel_arcsec], -1)

    def position_of(self, pix):
        """Points (arcsec) [..., 2] of 0-based (x, y) pixel coordinates `pix` [..., 2]."""
        pix = np.asarray(pix, float)
        return np.stack([self.x0_arcsec + pix[..., 0] * self.pixel_arcsec,
                         self.y0_arcsec + pix[..., 1] * self.pixel_arcsec], -1)


def rotation_matrix(angle_rad: float) -> np.ndarray:
    """R [2, 2] turning vectors counter-clockwise by angle_rad."""
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    return np.array([[c, -s], [s, c]])


# a pixel's corners, counter-clockwise, in pixels from its centre
_UNIT_SQUARE = np.array([[-0.5, -0.5], [0.5, -0.5], [0.5, 0.5], [-0.5, 0.5]])


@dataclasses.dataclass(frozen=True)
class RotatedGrid:
    """Square pixels whose axes are turned by `angle_rad` (counter-clockwise) from the
    frame's: pixel [j, i] is centred at (x0, y0) + pixel_arcsec · R(angle) (i, j).

    A band's data pixels when its orientation differs from the fit frame's
    (observations/frame.py). The model renders such a band on the aligned `covering()`
    grid and carries the light onto these pixels by their exact area overlaps
    (`rotated_overlap`, model/detector.py)."""

    x0_arcsec: float
    y0_arcsec: float
    pixel_arcsec: float
    nx: int
    ny: int
    angle_rad: float

    def __post_init__(self):
        for name in ("x0_arcsec", "y0_arcsec", "pixel_arcsec", "angle_rad"):
            object.__setattr__(self, name, float(getattr(self, name)))
        for name in ("nx", "ny"):
            object.__setattr__(self, name, int(getattr(self, name)))

    @property
    def shape(self):
        return (self.ny, self.nx)

    def position_of(self, pix):
        """Points (arcsec) [..., 2] of 0-based (x, y) pixel coordinates `pix` [..., 2]."""
        pix = np.asarray(pix, float)
        return np.array([self.x0_arcsec, self.y0_arcsec]) + \
            self.pixel_arcsec * pix @ rotation_matrix(self.angle_rad).T

    def pixel_of(self, xy):
        """0-based (x, y) pixel coordinates of points xy [..., 2] (arcsec)."""
        d = np.asarray(xy, float) - np.array([self.x0_arcsec, self.y0_arcsec])
        return d @ rotation_matrix(self.angle_rad) / self.pixel_arcsec       # R is orthogonal: R⁻¹ = Rᵀ

    def centers(self):
        """(x, y) [ny, nx]: every pixel's centre, arcsec."""
        i, j = np.meshgrid(np.arange(self.nx, dtype=float), np.arange(self.ny, dtype=float))
        xy = self.position_of(np.stack([i, j], -1))
        return xy[..., 0], xy[..., 1]

    def _corners(self):
        c = np.array([[-0.5, -0.5], [self.nx - 0.5, -0.5], [self.nx - 0.5, self.ny - 0.5],
                      [-0.5, self.ny - 0.5]])
        return self.position_of(c)

    @property
    def x_range(self):
        """Extent (arcsec) of the pixels along the frame's x (their bounding box)."""
        x = self._corners()[:, 0]
        return (float(x.min()), float(x.max()))

    @property
    def y_range(self):
        y = self._corners()[:, 1]
        return (float(y.min()), float(y.max()))

    def covering(self) -> Grid:
        """The frame-aligned grid of the same pixel side over these pixels' bounding box."""
        return Grid.covering(self.x_range, self.y_range, self.pixel_arcsec)


def _clip_polygons(poly, count, normal, offset):
    """Convex polygons [N, V, 2] (the first `count` [N] vertices valid, counter-clockwise)
    clipped to the half-plane normal · v ≤ offset (normal [2], offset [N]); vectorised
    Sutherland–Hodgman. Returns (polygons [N, V + 1, 2], counts [N])."""
    n, v = poly.shape[:2]
    idx = np.arange(v)
    nxt = np.where(idx[None, :] + 1 < count[:, None], idx[None, :] + 1, 0)
    a = poly
    b = np.take_along_axis(poly, nxt[..., None], axis=1)
    fa = a @ normal - offset[:, None]
    fb = b @ normal - offset[:, None]
    valid = idx[None, :] < count[:, None]
    keep = valid & (fa <= 0)
    cross = valid & ((fa <= 0) != (fb <= 0))
    t = np.where(cross, fa / np.where(cross, fa - fb, 1.0), 0.0)
    hit = a + t[..., None] * (b - a)
    # each edge a → b emits [a if inside][crossing point if it crosses], in this order
    emit = np.stack([keep, cross], -1).reshape(n, 2 * v)
    pts = np.stack([a, hit], 2).reshape(n, 2 * v, 2)
    pos = np.cumsum(emit, axis=1) - 1
    out = np.zeros((n, v + 1, 2))
    rows = np.broadcast_to(np.arange(n)[:, None], emit.shape)
    out[rows[emit], pos[emit]] = pts[emit]
    return out, emit.sum(axis=1)


def _polygon_moments(poly, count):
    """(area [N], centroid [N, 2]) of polygons [N, V, 2] whose first `count` vertices are
    valid (shoelace; counter-clockwise vertices give positive areas)."""
    idx = np.arange(poly.shape[1])
    nxt = np.where(idx[None, :] + 1 < count[:, None], idx[None, :] + 1, 0)
    b = np.take_along_axis(poly, nxt[..., None], axis=1)
    cross = np.where(idx[None, :] < count[:, None],
                     poly[..., 0] * b[..., 1] - poly[..., 1] * b[..., 0], 0.0)
    area = 0.5 * cross.sum(axis=1)
    safe = np.where(np.abs(area) > 0, area, 1.0)
    centroid = np.sum((poly + b) * cross[..., None], axis=1) / (6.0 * safe[:, None])
    return area, centroid


OVERLAP_BLOCK = 2048    # destination pixels clipped at once (~40 MB of work arrays)


def _clipped_squares(src: Grid, corners, cx, cy, ii, jj):
    """(area fraction [p, C], centroid offset [p, C, 2] in source pixels) of source pixels
    (ii, jj) [p, C] inside the destination pixels centred at (cx, cy) [p] with `corners`
    [4, 2] (counter-clockwise, around the centre)."""
    ps = src.pixel_arcsec
    p, C = ii.shape
    x = src.x0_arcsec + ii.ravel() * ps
    y = src.y0_arcsec + jj.ravel() * ps
    square = np.stack([x, y], -1)[:, None, :] + _UNIT_SQUARE[None] * ps    # [n, 4, 2]
    centre = np.stack([np.repeat(cx, C), np.repeat(cy, C)], -1)
    edges = [(corners[e], corners[(e + 1) % 4]) for e in range(4)]
    normals = [np.array([b[1] - a[1], a[0] - b[0]]) for a, b in edges]   # outward: CCW corners
    offsets = [centre @ n + a @ n for (a, _), n in zip(edges, normals)]
    # a square wholly inside every edge is covered (fraction 1, centroid at its centre); one
    # wholly outside an edge is not touched: only the squares that straddle an edge are clipped
    side = np.stack([square @ n - o[:, None] for n, o in zip(normals, offsets)])   # [4, n, 4]
    covered = np.all(side <= 0, axis=(0, 2))
    missed = np.any(np.all(side > 0, axis=2), axis=0)
    cut = np.nonzero(~covered & ~missed)[0]
    frac = covered.astype(float)
    shift = np.zeros((p * C, 2))
    poly = np.concatenate([square[cut], np.zeros((cut.size, 4, 2))], 1)
    count = np.full(cut.size, 4)
    for n, o in zip(normals, offsets):
        poly, count = _clip_polygons(poly, count, n, o[cut])
        poly = poly[:, :8]
    area, centroid = _polygon_moments(poly, count)
    frac[cut] = area / ps**2
    shift[cut] = (centroid - np.stack([x, y], -1)[cut]) / ps
    return frac.reshape(p, C), shift.reshape(p, C, 2)


@functools.lru_cache(maxsize=8)     # a fit builds its model several times (seconds each)
def rotated_overlap(src: Grid, dst: RotatedGrid):
    """The map from an aligned grid's flux image onto rotated pixels, as (index [P, K]
    int32, weight [P, K], moment [P, K, 2]): destination pixel p (row-major) receives

        Σ_k weight[p, k] · F[i] + moment[p, k] · ∇F[i],   i = index[p, k],

    F the image raveled, ∇F its central differences along x and y (flux per pixel per
    pixel; `apply_overlap`). weight = area(source pixel ∩ destination pixel) / area(source
    pixel), exact (polygon clipping); moment = weight × the overlap's centroid offset from
    the source pixel's centre, in source pixels. Each source pixel's light is thus taken as
    linear across it, not flat: flat sharing errs by ~1 % of a clump's peak at 3 sub-pixels
    per pixel, linear by ~1e-3 (tests/test_rotated_bands.py). The moments of a source pixel
    sum to 0 over destination pixels that cover it: flux is conserved. Source pixels
    outside `src` contribute nothing; zero-weight padding points at pixel 0."""
    ps = src.pixel_arcsec
    corners = dst.position_of(_UNIT_SQUARE)
    corners = corners - np.array([dst.x0_arcsec, dst.y0_arcsec])       # [4, 2] around a centre
    cx, cy = (c.ravel() for c in dst.centers())
    # the source pixels that can touch a destination pixel: its bounding box, in source pixels
    half = np.abs(corners).max(axis=0)
    lo_i = np.floor((cx - half[0] - src.x0_arcsec) / ps + 0.5).astype(int)
    lo_j = np.floor((cy - half[1] - src.y0_arcsec) / ps + 0.5).astype(int)
    span_i = int(np.ceil(2 * half[0] / ps)) + 1
    span_j = int(np.ceil(2 * half[1] / ps)) + 1
    di, dj = np.meshgrid(np.arange(span_i), np.arange(span_j))
    ii = (lo_i[:, None] + di.ravel()[None, :])
    jj = (lo_j[:, None] + dj.ravel()[None, :])
    P, C = ii.shape
    w, offset = np.zeros((P, C)), np.zeros((P, C, 2))
    for start in range(0, P, OVERLAP_BLOCK):     # blocks of pixels: bounded memory
        rows = slice(start, min(start + OVERLAP_BLOCK, P))
        w[rows], offset[rows] = _clipped_squares(src, corners, cx[rows], cy[rows], ii[rows],
                                                 jj[rows])
    inside = (ii >= 0) & (ii < src.nx) & (jj >= 0) & (jj < src.ny)
    w = np.where(inside & (w > 1e-12), w, 0.0)
    K = max(int((w > 0).sum(axis=1).max(initial=0)), 1)
    order = np.argsort(-w, axis=1, kind="stable")[:, :K]
    weight = np.take_along_axis(w, order, axis=1)
    moment = np.take_along_axis(offset, order[..., None], axis=1) * weight[..., None]
    index = np.take_along_axis(np.where(inside, jj * src.nx + ii, 0), order, axis=1)
    index = np.where(weight > 0, index, 0).astype(np.int32)
    for a in (index, weight, moment):
        a.setflags(write=False)     # cached: shared by every caller
    return index, weight, moment


def _keys_cubic(t):
    """Keys' (1981) cubic convolution weights (a = −1/2) of the 4 nodes at offsets −1, 0, 1,
    2 from a point a fraction t ∈ [0, 1) past node 0: [..., 4], summing to 1; third order."""
    t = np.asarray(t, float)[..., None]
    d = np.abs(np.arange(-1, 3) - t)
    near = 1.5 * d**3 - 2.5 * d**2 + 1.0
    far = -0.5 * d**3 + 2.5 * d**2 - 4.0 * d + 2.0
    return np.where(d <= 1, near, np.where(d < 2, far, 0.0))


def rotated_samples(src: Grid, dst: RotatedGrid):
    """Cubic-convolution interpolation (Keys 1981) of an aligned grid's image at the rotated
    pixels' centres, as (index [P, 16] int32, weight [P, 16]) in `rotated_overlap`'s form;
    nodes outside `src` read zero. Bilinear interpolation errs by ~1.5 % of a clump's peak
    at 3 sub-pixels per pixel, this by ~0.4 % (tests/test_rotated_bands.py)."""
    cx, cy = dst.centers()
    fx = (cx.ravel() - src.x0_arcsec) / src.pixel_arcsec
    fy = (cy.ravel() - src.y0_arcsec) / src.pixel_arcsec
    i0, j0 = np.floor(fx).astype(int), np.floor(fy).astype(int)
    wx, wy = _keys_cubic(fx - i0), _keys_cubic(fy - j0)                 # [P, 4] each
    i = i0[:, None, None] + np.arange(-1, 3)[None, None, :]
    j = j0[:, None, None] + np.arange(-1, 3)[None, :, None]
    ok = (i >= 0) & (i < src.nx) & (j >= 0) & (j < src.ny)
    index = np.where(ok, j * src.nx + i, 0).reshape(len(fx), 16)
    weight = np.where(ok, wy[:, :, None] * wx[:, None, :], 0.0).reshape(len(fx), 16)
    return index.astype(np.int32), weight


def apply_sparse_map(image, index, weight, shape):
    """Destination image `shape` from a source image [ny, nx] and a (index, weight) map."""
    flat = image.reshape(-1)
    return jnp.sum(flat[index] * weight.astype(image.dtype), axis=-1).reshape(shape)


def apply_overlap(image, index, weight, moment, shape):
    """Destination image `shape` from a source flux image [ny, nx] and a `rotated_overlap`
    map: the overlap of each source pixel's linear profile (central differences, one-sided
    at the edges)."""
    gx = jnp.gradient(image, axis=1) if image.shape[1] > 1 else jnp.zeros_like(image)
    gy = jnp.gradient(image, axis=0) if image.shape[0] > 1 else jnp.zeros_like(image)
    m = moment.astype(image.dtype)
    return (apply_sparse_map(image, index, weight, shape)
            + apply_sparse_map(gx, index, m[..., 0], shape)
            + apply_sparse_map(gy, index, m[..., 1], shape))


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
