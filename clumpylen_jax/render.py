"""Rendering kernels: source components to pixel fluxes on a grid, and to surface brightness at rays.

Pure functions of the source pytrees (`source.py`) and static grids
(`pixels.Grid`). Pixel values are integrals of surface brightness over the
pixel: Gauss–Legendre sub-pixel sampling of order `order` everywhere, and, for
Sérsic profiles, the exact fan integral (`profiles.sersic_pixel_flux_exact`) on a
`core` × `core` block of pixels around the centre, where the profile is least
smooth. Clumps are rendered on stamps of static size around their centres, so
their cost grows with the area they cover, not with clumps × grid.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from . import incgamma, profiles
from .pixels import Grid, gauss_legendre_offsets
from .source import Clumps, Disk, Sersic

# ------------------------------------------------------------------ unit-flux brightness


def sersic_unit_brightness(x1, x2, *, re_arcsec, n, q, pa_rad, center1, center2, b=None):
    """Surface brightness (per arcsec²) of a unit-flux Sérsic at (x1, x2)."""
    return profiles.sersic_brightness(x1, x2, flux=1.0, re_arcsec=re_arcsec, n=n, q=q,
                                      pa_rad=pa_rad, center1=center1, center2=center2, b=b)


def sersic_component_brightness(s: Sersic, x1, x2):
    """Surface brightness (per arcsec²) of the Sérsic `s` scaled to unit flux, at (x1, x2)."""
    return sersic_unit_brightness(x1, x2, **_sersic_kw(s))


def _sersic_kw(s: Sersic):
    return dict(re_arcsec=s.re_arcsec, n=s.n, q=s.q, pa_rad=s.pa_rad,
                center1=s.center_arcsec[0], center2=s.center_arcsec[1])


def _disk_kw(d: Disk):
    s = d.sersic
    return dict(re_arcsec=s.re_arcsec, n=s.n, q=d.q_projected, pa_rad=s.pa_rad,
                center1=s.center_arcsec[0], center2=s.center_arcsec[1])


def disk_modulation(disk: Disk, x1, x2):
    """Arms × texture factor of a disk at (x1, x2), before flux renormalisation."""
    kw = _disk_kw(disk)
    m = 1.0
    if disk.arms is not None:
        a = disk.arms
        m = m * profiles.spiral_modulation(
            x1, x2, center1=kw["center1"], center2=kw["center2"], q=kw["q"], pa_rad=kw["pa_rad"],
            count=a.count, amplitude=a.amplitude, winding=a.winding, phase_rad=a.phase_rad,
            scale_arcsec=a.scale_arcsec, orientation_rad=a.orientation_rad)
    if disk.texture is not None:
        t = disk.texture
        m = m * profiles.texture_modulation(
            x1, x2, center1=kw["center1"], center2=kw["center2"], amplitude=t.amplitude,
            scale_arcsec=t.scale_arcsec, octaves=t.octaves, seed=t.seed)
    return m


def disk_modulation_mean(disk: Disk, radial_nodes: int = 48, angular_nodes: int = 96):
    """Light-weighted mean of the disk's modulation, so that the modulated disk keeps its flux.

    Quadrature in the disk's circularised frame: radii at Gauss–Legendre nodes
    of the enclosed-light fraction (r = R_e (P⁻¹(2n, u)/b)^n, exact weights for
    the radial light distribution), uniform angles. The arms alone average to
    exactly 1 (∮ cos = 0); the texture does not, hence this normaliser.
    """
    if disk.texture is None:
        return 1.0
    kw = _disk_kw(disk)
    n = kw["n"]
    b = profiles.sersic_b(n)
    x, w = np.polynomial.legendre.leggauss(radial_nodes)
    dtype = jnp.result_type(kw["re_arcsec"])
    u = jnp.asarray((x + 1) / 2, dtype) * (1 - 1e-9)
    wr = jnp.asarray(w / 2, dtype)
    r = kw["re_arcsec"] * (profiles.gammainc_inverse(2 * n, u) / b) ** n
    phi = jnp.asarray(2 * np.pi * (np.arange(angular_nodes) + 0.5) / angular_nodes, dtype)
    major = r[:, None] * jnp.cos(phi)[None, :]
    minor = r[:, None] * jnp.sin(phi)[None, :] * kw["q"]
    c, s = jnp.cos(kw["pa_rad"]), jnp.sin(kw["pa_rad"])
    x1 = kw["center1"] + major * c - minor * s
    x2 = kw["center2"] + major * s + minor * c
    m = disk_modulation(disk, x1, x2)
    return jnp.sum(wr[:, None] * m) / angular_nodes


def disk_unit_brightness(disk: Disk, x1, x2, modulation_mean=None):
    """Surface brightness of a unit-flux disk (inclined Sérsic × arms × texture)."""
    if modulation_mean is None:
        modulation_mean = disk_modulation_mean(disk)
    smooth = sersic_unit_brightness(x1, x2, **_disk_kw(disk))
    if disk.arms is None and disk.texture is None:
        return smooth
    return smooth * disk_modulation(disk, x1, x2) / modulation_mean


def clumps_brightness(clumps: Clumps, x1, x2):
    """Surface brightness [B, ...] of all clumps at (x1, x2), evaluated analytically.

    Cost is rays × clumps: the reference path. Scans over clumps so memory
    stays that of one clump's evaluation.
    """
    bvals = profiles.sersic_b(clumps.n)
    nb = clumps.flux.shape[1]

    def body(acc, k):
        val = sersic_unit_brightness(
            x1, x2, re_arcsec=clumps.re_arcsec[k], n=clumps.n[k], q=clumps.q[k],
            pa_rad=clumps.pa_rad[k], center1=clumps.center_arcsec[k, 0],
            center2=clumps.center_arcsec[k, 1], b=bvals[k])
        return acc + clumps.flux[k][(...,) + (None,) * val.ndim] * val[None], None

    acc0 = jnp.zeros((nb,) + jnp.shape(x1), jnp.result_type(x1, clumps.flux))
    out, _ = jax.lax.scan(body, acc0, jnp.arange(clumps.count))
    return out


def gaussian_clumps_cell_brightness(clumps: Clumps, x1, x2, cov):
    """Mean surface brightness [B, ...] (per arcsec², unit-flux profiles × flux) of Gaussian
    clumps (Sérsic n = 0.5; their n is not read) over each ray's source-plane cell: the
    clump's covariance plus the cell's second moment cov = (s11, s12, s22) [...] (arcsec²),
    the Gaussian approximation of averaging over the cell.

    Point sampling (`clumps_brightness`) aliases a clump narrower than the ray spacing: through
    an SIS at 2 rays per 0.01" lens pixel a q = 0.27, R_e = 7.5 mas clump (minor σ 1.7 mas
    across the arc, rays ~5 mas apart) drew an image Δχ² = 75 from the converged one, and the
    fits ran to such shapes (issue 18). With cov → 0 this is the point value."""
    from .gaussian_mixtures import round_mixture
    (sigma_per_re,) = round_mixture("round_gaussian")[2]    # σ / R_e, as the round renderer's
    s11, s12, s22 = cov
    nb = clumps.flux.shape[1]

    def body(acc, k):
        a2 = (clumps.re_arcsec[k] * sigma_per_re) ** 2
        b2 = a2 * clumps.q[k] ** 2
        c, s = jnp.cos(clumps.pa_rad[k]), jnp.sin(clumps.pa_rad[k])
        c11 = a2 * c * c + b2 * s * s + s11
        c22 = a2 * s * s + b2 * c * c + s22
        c12 = (a2 - b2) * c * s + s12
        det = c11 * c22 - c12 * c12
        d1 = x1 - clumps.center_arcsec[k, 0]
        d2 = x2 - clumps.center_arcsec[k, 1]
        quad = (c22 * d1 * d1 - 2.0 * c12 * d1 * d2 + c11 * d2 * d2) / det
        val = jnp.exp(-0.5 * quad) / (2.0 * jnp.pi * jnp.sqrt(det))
        return acc + clumps.flux[k][(...,) + (None,) * val.ndim] * val[None], None

    acc0 = jnp.zeros((nb,) + jnp.shape(x1), jnp.result_type(x1, clumps.flux))
    out, _ = jax.lax.scan(body, acc0, jnp.arange(clumps.count))
    return out


# ------------------------------------------------------------------ pixel-integrated images


def gaussian_pixel_fractions(edges_arcsec, center_arcsec, sigma_arcsec):
    """Light fraction [N, M] of N 1-D Gaussians (centre, σ: [N], arcsec) in each of the M
    pixels between M + 1 increasing `edges_arcsec` (numpy, static): Φ differences, exact.

    A pixel right of the centre takes ½[erfc(a) − erfc(b)] of its standardised edges a < b
    (a/√2 form), one left of it ½[erfc(−b) − erfc(−a)]: both terms are tails there, so a pixel
    100 σ out keeps its tiny fraction instead of cancelling 1 − 1 to zero (and with it its
    gradient). Both branches have finite gradients everywhere, so `where` keeps them finite
    for σ → 0 and for centres far outside the edges. Neighbours share the edge values, so the
    fractions telescope: their sum is the light between the first and the last edge.
    """
    dtype = jnp.result_type(center_arcsec, sigma_arcsec)
    edges = jnp.asarray(edges_arcsec, dtype)
    t = (edges[None, :] - center_arcsec[:, None]) / (jnp.sqrt(jnp.asarray(2.0, dtype))
                                                      * sigma_arcsec[:, None])
    right = jax.scipy.special.erfc(t)            # 2 × light beyond each edge
    left = jax.scipy.special.erfc(-t)            # 2 × light before it
    lo, hi = slice(None, -1), slice(1, None)
    far_side = t[:, lo] >= 0                     # the whole pixel right of the centre
    return 0.5 * jnp.where(far_side, right[:, lo] - right[:, hi], left[:, hi] - left[:, lo])


# above this σ (pixels) `gaussian_pixel_moments` takes the series: its truncation is then
# below 1e-5 of M2, and the exact form's cancellation grows as σ²
SERIES_SIGMA_PIXELS = 6.0


def gaussian_pixel_moments(edges_arcsec, center_arcsec, sigma_arcsec):
    """(F, M1, M2) [N, M] of N 1-D Gaussians in the M pixels between M + 1 evenly spaced
    `edges_arcsec`: the light fraction F (`gaussian_pixel_fractions`) and its first and
    second moments about each pixel's centre c, in pixels: M1 = ∫(x − c) g dx / p and
    M2 = ∫(x − c)² g dx / p² over the pixel (p its width), exact.

    With t = (x − μ)/σ and φ the standard normal density, ∫(x − μ) g = σ[φ(t_a) − φ(t_b)]
    and ∫(x − μ)² g = σ²[F + t_a φ(t_a) − t_b φ(t_b)]; the moments about c follow by
    x − c = (x − μ) + (μ − c). No term has a 1/σ prefactor, so σ → 0 stays finite (φ
    underflows to 0 far out, and its gradient with it). That shift cancels for σ of many
    pixels (σ² F against the true F/12: in float32, 3e-5 of a clump's peak at R_e 50
    pixels), so for σ > SERIES_SIGMA_PIXELS the moments are the Taylor series of g about c
    instead: M1 = g′/12 + g‴/480, M2 = g/12 + g″/160 (truncation below 1e-5 of M2 there)."""
    edges_np = np.asarray(edges_arcsec, float)
    pixel = float(edges_np[1] - edges_np[0])
    assert np.allclose(np.diff(edges_np), pixel, rtol=1e-9, atol=0), "evenly spaced edges"
    dtype = jnp.result_type(center_arcsec, sigma_arcsec)
    frac = gaussian_pixel_fractions(edges_arcsec, center_arcsec, sigma_arcsec)
    edges = jnp.asarray(edges_np / pixel, dtype)                 # in pixels from here on
    mu = center_arcsec[:, None] / pixel
    sig = sigma_arcsec[:, None] / pixel
    t = (edges[None, :] - mu) / sig
    phi = jnp.exp(-0.5 * t * t) * jnp.asarray(1.0 / np.sqrt(2.0 * np.pi), dtype)
    sig_phi = sig * phi                                          # σ φ(t) at each edge
    first = sig_phi[:, :-1] - sig_phi[:, 1:]                     # ∫ (x − μ) g
    second = sig * (sig * frac + (edges[None, :-1] - mu) * phi[:, :-1]
                    - (edges[None, 1:] - mu) * phi[:, 1:])       # ∫ (x − μ)² g: σ t φ = (x − μ) φ
    off = mu - 0.5 * (edges[None, :-1] + edges[None, 1:])        # μ − c
    m1, m2 = first + off * frac, second + 2.0 * off * first + off * off * frac
    wide = sig > SERIES_SIGMA_PIXELS
    s_w = jnp.where(wide, sig, SERIES_SIGMA_PIXELS)              # double where: 1/σ finite
    tc = -off / s_w                                              # (c − μ)/σ at each centre
    g = jnp.exp(-0.5 * tc * tc) * jnp.asarray(1.0 / np.sqrt(2.0 * np.pi), dtype) / s_w
    d1, d2 = -tc * g / s_w, (tc * tc - 1.0) * g / (s_w * s_w)    # g′, g″ (per pixel)
    d3 = -(tc * tc - 3.0) * tc * g / s_w ** 3
    return (frac, jnp.where(wide, d1 / 12.0 + d3 / 480.0, m1),
            jnp.where(wide, g / 12.0 + d2 / 160.0, m2))



def _sampled_image(brightness, grid: Grid, order: int, dtype):
    """∫ brightness over each pixel of `grid` by order × order Gauss–Legendre sampling."""
    return _sample_sum(brightness, grid, order, dtype) * _pixel_area(grid)


def _pixel_area(grid: Grid) -> float:
    p = grid.pixel_arcsec
    return p * p


def _sample_sum(brightness, grid: Grid, order: int, dtype):
    """`_sampled_image` / the pixel area: the weighted sum of each pixel's samples.

    A loop over the samples, not an unrolled sum: a brightness of hundreds of operations (the
    textured disk) is then compiled once per grid instead of order² times. Offsets and
    weights are products of Python floats rounded once to dtype, the constants the unrolled
    sum used, and the samples are added in the same order (y outer, x inner); XLA still rounds
    some pixels differently from the unrolled sum (in the last bit or two). The body closes over
    `brightness`, so an eager (unjitted) call compiles the loop anew: call it under jit.
    """
    offs, wts = (v.tolist() for v in gauss_legendre_offsets(order))
    p = grid.pixel_arcsec
    dx = jnp.asarray([ox * p for _ in offs for ox in offs], dtype)
    dy = jnp.asarray([oy * p for oy in offs for _ in offs], dtype)
    w = jnp.asarray([wy * wx for wy in wts for wx in wts], dtype)
    xc = jnp.asarray(grid.x_centers(), dtype)[None, :]
    yc = jnp.asarray(grid.y_centers(), dtype)[:, None]

    def add_sample(k, acc):
        return acc + w[k] * brightness(xc + dx[k], yc + dy[k])

    return jax.lax.fori_loop(0, order * order, add_sample, jnp.zeros(grid.shape, dtype))


def _sample_sums(brightness, grids, order: int, dtype):
    """`_sample_sum` on each grid of `grids`, in one loop whose body evaluates `brightness`
    once per sample on the pixels of every grid at once: the profile (a textured disk:
    thousands of operations) is compiled once, not once per grid. Each pixel's samples are
    the values `_sample_sum` adds, in the same order.

    The grids' pixels are one flat range, each pixel's sample coordinates computed from its
    index (grid, row, column: the same centre + offset sums as `_sample_sum`), and one flat
    sum is kept: no coordinate arrays are concatenated, nor values split, per sample (the
    paper scene's unlensed sub-grids and 2047² source plane: the same bits, 10.3 → 4.6–6.0
    s of CPU per run)."""
    if len(grids) == 1:
        return [_sample_sum(brightness, grids[0], order, dtype)]
    offs, wts = (v.tolist() for v in gauss_legendre_offsets(order))
    w = jnp.asarray([wy * wx for wy in wts for wx in wts], dtype)
    dx = jnp.asarray([[ox * g.pixel_arcsec for _ in offs for ox in offs] for g in grids], dtype)
    dy = jnp.asarray([[oy * g.pixel_arcsec for oy in offs for _ in offs] for g in grids], dtype)
    # every grid's column and row centres, one table each (rounded to dtype as there)
    xc = jnp.asarray(np.concatenate([np.asarray(g.x_centers(), np.dtype(dtype)) for g in grids]))
    yc = jnp.asarray(np.concatenate([np.asarray(g.y_centers(), np.dtype(dtype)) for g in grids]))
    starts = np.cumsum([0] + [g.ny * g.nx for g in grids]).tolist()
    first_col = jnp.asarray(np.cumsum([0] + [g.nx for g in grids[:-1]]), jnp.int32)
    first_row = jnp.asarray(np.cumsum([0] + [g.ny for g in grids[:-1]]), jnp.int32)
    nx = jnp.asarray([g.nx for g in grids], jnp.int32)
    first = jnp.asarray(starts[:-1], jnp.int32)

    def add_sample(k, acc):
        pixel = jax.lax.iota(jnp.int32, starts[-1])
        g = sum((pixel >= s).astype(jnp.int32) for s in starts[1:-1])
        row = jax.lax.div(pixel - first[g], nx[g])          # indices ≥ 0: truncation is floor
        col = pixel - first[g] - row * nx[g]
        return acc + w[k] * brightness(xc[first_col[g] + col] + dx[g, k],
                                       yc[first_row[g] + row] + dy[g, k])

    acc = jax.lax.fori_loop(0, order * order, add_sample, jnp.zeros(starts[-1], dtype))
    return [acc[a:b].reshape(g.shape) for a, b, g in zip(starts[:-1], starts[1:], grids)]


def _pixel_edges(index, origin, pixel, dtype):
    """(low, high) edges (arcsec) of the pixels with integer `index` on an axis whose pixel 0
    is centred at `origin`. Neighbours share an edge bit for bit (k + 0.5 and (k + 1) − 0.5
    are the same float), so exact pixel integrals tile the plane: computed as low + pixel,
    float32 edges leave gaps and overlaps of ~1e-8" that, on a cusp at a pixel corner, gain
    0.5 % of the light.
    """
    k = index.astype(dtype)
    return origin + (k - 0.5) * pixel, origin + (k + 0.5) * pixel


def _pixel_index(coord, origin, pixel):
    """Index of the pixel holding `coord`, clipped to ±2²⁰ so that far-away points stay integers."""
    t = jnp.clip(jax.lax.stop_gradient((coord - origin) / pixel) + 0.5, -2.0**20, 2.0**20)
    return jnp.floor(t).astype(jnp.int32)


def _exact_core(image, grid: Grid, core: int, kw, b):
    """Replace the core × core pixels around the Sérsic centre by exact pixel integrals."""
    if core <= 0:
        return image
    (i0, j0), (x_lo, x_hi, y_lo, y_hi) = _core_block(grid, core, kw, image.dtype)
    block = profiles.sersic_pixel_flux_exact(x_lo[:1], x_hi[:1], y_lo[:, :1], y_hi[:, :1],
                                             flux=1.0, b=b, **kw)
    return _set_core_block(image, grid, core, i0, j0, block)


def _axis_distance(x, y, center1, center2, pa_rad):
    """|distance| (arcsec) of points (x, y) from the major axis line through the centre."""
    return jnp.abs((x - center1) * jnp.sin(pa_rad) - (y - center2) * jnp.cos(pa_rad))


def _exact_strip(image, grid: Grid, core: int, kw, b):
    """Replace by exact integrals the 3·max(nx, ny) + core² pixels whose centres lie nearest
    the major axis (≥ ~1 pixel on each side of it across the whole grid)."""
    flat, edges = _strip_pixels(image, grid, core, kw)
    vals = profiles.sersic_pixel_flux_exact(*edges, flux=1.0, b=b, **kw)
    return image.ravel().at[flat].set(vals.astype(image.dtype)).reshape(image.shape)


def _core_block(grid: Grid, core: int, kw, dtype):
    """(i0, j0) of the core × core block around the Sérsic centre and its pixels' edges
    (x_lo, x_hi, y_lo, y_hi), [core, core] each."""
    p = grid.pixel_arcsec
    i0 = _pixel_index(kw["center1"], grid.x0_arcsec, p) - core // 2
    j0 = _pixel_index(kw["center2"], grid.y0_arcsec, p) - core // 2
    k = jnp.arange(core)
    x_lo, x_hi = (e[None, :] for e in _pixel_edges(i0 + k, grid.x0_arcsec, p, dtype))
    y_lo, y_hi = (e[:, None] for e in _pixel_edges(j0 + k, grid.y0_arcsec, p, dtype))
    return (i0, j0), [jnp.broadcast_to(e, (core, core)) for e in (x_lo, x_hi, y_lo, y_hi)]


def _set_core_block(image, grid: Grid, core: int, i0, j0, block):
    """`_exact_core`'s placing of the exact block (i0, j0: its pixel [0, 0])."""
    padded = jnp.pad(image, core)
    start_j = jnp.clip(j0 + core, 0, grid.ny + core)
    start_i = jnp.clip(i0 + core, 0, grid.nx + core)
    # where the clamp moved the block, it lies wholly in the padding and is cropped away
    moved = (start_j != j0 + core) | (start_i != i0 + core)
    current = jax.lax.dynamic_slice(padded, (start_j, start_i), (core, core))
    block = jnp.where(moved, current, block.astype(image.dtype))
    padded = jax.lax.dynamic_update_slice(padded, block, (start_j, start_i))
    return padded[core:core + grid.ny, core:core + grid.nx]


def _strip_pixels(image, grid: Grid, core: int, kw):
    """`_exact_strip`'s pixels: their flat indices and edges (x_lo, x_hi, y_lo, y_hi)."""
    ny, nx = grid.shape
    count = min(nx * ny, 3 * max(nx, ny) + core * core)
    p = grid.pixel_arcsec
    dtype = image.dtype
    xc = jnp.asarray(grid.x_centers(), dtype)
    yc = jnp.asarray(grid.y_centers(), dtype)
    dist = _axis_distance(xc[None, :], yc[:, None], kw["center1"], kw["center2"], kw["pa_rad"])
    _, flat = jax.lax.top_k(-jax.lax.stop_gradient(dist).ravel(), count)
    return flat, [*_pixel_edges(flat % nx, grid.x0_arcsec, p, dtype),
                  *_pixel_edges(flat // nx, grid.y0_arcsec, p, dtype)]


def _exact_on(images, grids, core: int, strips, kw, b):
    """`_exact_strip` (strips[t]) or `_exact_core` of one Sérsic on each image of `images`
    (on `grids`), its exact pixel integrals of every grid made by one kernel call."""
    if core <= 0:
        return list(images)
    if len(images) == 1:    # as one grid always was
        f = _exact_strip if strips[0] else _exact_core
        return [f(images[0], grids[0], core, kw, b)]
    where, edges = [], []
    for img, g, strip in zip(images, grids, strips):
        at, e = (_strip_pixels(img, g, core, kw) if strip else
                 _core_block(g, core, kw, img.dtype))
        where.append(at)
        edges.append([v.ravel() for v in e])
    sizes = [e[0].size for e in edges]
    vals = profiles.sersic_pixel_flux_exact(*(jnp.concatenate(v) for v in zip(*edges)),
                                            flux=1.0, b=b, **kw)
    vals = jnp.split(vals, np.cumsum(sizes)[:-1].tolist())
    out = []
    for img, g, strip, at, v in zip(images, grids, strips, where, vals):
        if strip:
            out.append(img.ravel().at[at].set(v.astype(img.dtype)).reshape(img.shape))
        else:
            out.append(_set_core_block(img, g, core, *at, v.reshape(core, core)))
    return out


def _plain_sersic_images(kw, grids, order: int, core: int, strips, dtype):
    """`_plain_sersic_image` on each grid of `grids` (strips: per grid): one compiled
    profile and one exact-pixel kernel for all of them."""
    b = profiles.sersic_b(kw["n"])
    sums = _sample_sums(lambda x, y: sersic_unit_brightness(x, y, b=b, **kw), grids, order,
                        dtype)
    images = [s * _pixel_area(g) for s, g in zip(sums, grids)]
    return _exact_on(images, grids, core, strips, kw, b)


def _plain_sersic_image(kw, grid: Grid, order: int, core: int, strip: bool, dtype):
    b = profiles.sersic_b(kw["n"])
    img = _sampled_image(lambda x, y: sersic_unit_brightness(x, y, b=b, **kw), grid, order, dtype)
    if strip and core > 0:      # core = 0: no exact pixels at all (as for clump stamps)
        return _exact_strip(img, grid, core, kw, b)
    return _exact_core(img, grid, core, kw, b)


def sersic_image(s: Sersic, grid: Grid, *, order: int = 4, core: int = 5, strip: bool = False,
                 dtype=None):
    """Unit-flux pixel integrals [ny, nx] of a Sérsic component on `grid`: Gauss–Legendre
    sampled (order²) but for the core² pixels around the centre, integrated exactly, or with
    strip (a thin profile whose light reaches beyond the core: see `strip_needed`) the pixels
    along its major axis, where sampling would miss or overweight the line of light."""
    dtype = dtype or jnp.result_type(s.re_arcsec)
    return _plain_sersic_image(_sersic_kw(s), grid, order, core, strip, dtype)


def disk_image(d: Disk, grid: Grid, *, order: int = 4, core: int = 5, strip: bool = False,
               dtype=None, modulation_mean=None):
    """Unit-flux pixel integrals of a disk; exact core (or strip) only when it is a plain Sérsic.
    modulation_mean: `disk_modulation_mean(d)` computed before, or None (computed here)."""
    values = disk_image_values(d, grid, order=order, core=core, strip=strip, dtype=dtype,
                               modulation_mean=modulation_mean)
    scale = disk_image_scale(d, grid)
    return values if scale == 1.0 else values * scale


def disk_image_values(d: Disk, grid: Grid, *, order: int = 4, core: int = 5,
                      strip: bool = False, dtype=None, modulation_mean=None):
    """`disk_image` / `disk_image_scale`. Kept apart for a program that takes the values as
    data (`model.hosts.UnlensedHosts`): XLA evaluates flux × (values × scale) as
    values × (flux × scale), so a held image multiplied by a flux would differ from
    flux × disk_image in the last bit; held values times the scale times the flux do not."""
    dtype = dtype or jnp.result_type(d.sersic.re_arcsec)
    if d.arms is None and d.texture is None:
        return _plain_sersic_image(_disk_kw(d), grid, order, core, strip, dtype)
    mean = disk_modulation_mean(d) if modulation_mean is None else modulation_mean
    return _sample_sum(lambda x, y: disk_unit_brightness(d, x, y, mean), grid, order, dtype)


def disk_image_scale(d: Disk, grid: Grid) -> float:
    """disk_image = disk_image_values × this: the pixel area for a sampled (armed or
    textured) disk, else 1."""
    return 1.0 if d.arms is None and d.texture is None else _pixel_area(grid)


def sersic_images(s: Sersic, grids, *, order: int = 4, core: int = 5, strips=None,
                  dtype=None):
    """`sersic_image` on each grid of `grids` (strips: per grid, default none), computed
    together: one compiled profile and one exact-pixel kernel however many grids."""
    dtype = dtype or jnp.result_type(s.re_arcsec)
    grids = list(grids)
    if not grids:
        return []
    strips = strips or [False] * len(grids)
    return _plain_sersic_images(_sersic_kw(s), grids, order, core, strips, dtype)


def disk_images_values(d: Disk, grids, *, order: int = 4, core: int = 5, strips=None,
                       dtype=None, modulation_mean=None):
    """`disk_image_values` on each grid of `grids` (strips: per grid, default none), computed
    together: one compiled profile (and modulation mean) however many grids."""
    dtype = dtype or jnp.result_type(d.sersic.re_arcsec)
    grids = list(grids)
    if not grids:
        return []
    strips = strips or [False] * len(grids)
    if d.arms is None and d.texture is None:
        return _plain_sersic_images(_disk_kw(d), grids, order, core, strips, dtype)
    mean = disk_modulation_mean(d) if modulation_mean is None else modulation_mean
    return _sample_sums(lambda x, y: disk_unit_brightness(d, x, y, mean), grids, order, dtype)


def clump_stamp_origin(clumps: Clumps, grid: Grid, stamp: int):
    """Integer (i0, j0) of each clump stamp's pixel [0, 0] in `grid` (not differentiable)."""
    p = grid.pixel_arcsec
    ic = _pixel_index(clumps.center_arcsec[:, 0], grid.x0_arcsec, p)
    jc = _pixel_index(clumps.center_arcsec[:, 1], grid.y0_arcsec, p)
    return ic - stamp // 2, jc - stamp // 2


def _core_pixels(stamp: int, core: int):
    """Flat stamp indices [core²] (NumPy) of the core × core block around the centre of a
    stamp (which sits at stamp index stamp // 2)."""
    lo = stamp // 2 - core // 2
    k = np.arange(lo, lo + core)
    return (k[:, None] * stamp + k[None, :]).ravel()


def _strip_pixels_flat(center1, center2, pa_rad, xc, yc, stamp: int, core: int, n: int):
    """Flat stamp indices [n, count] of the 3·stamp + core² pixels whose centres lie nearest
    the major axis, for n clumps (centres, position angles [n]; the pixel centres xc, yc
    [n, stamp] of their stamps)."""
    count = min(stamp * stamp, 3 * stamp + core * core)
    dist = _axis_distance(xc[:, None, :], yc[:, :, None], center1[:, None, None],
                          center2[:, None, None], pa_rad[:, None, None])
    _, flat = jax.lax.top_k(-jax.lax.stop_gradient(dist).reshape(n, -1), count)
    return flat


_EXACT_CHUNK = 1 << 17


def _exact_fluxes(clumps: Clumps, b, which, x_lo, x_hi, y_lo, y_hi):
    """Exact unit-flux integrals over pixels [x_lo, x_hi] × [y_lo, y_hi] of
    clump `which` (all 1-D, arcsec): one incomplete-gamma kernel however many stamp sizes
    and grids ask for them.

    Beyond 131 072 pixels, in near-equal chunks, each recomputed in the backward pass
    (`jax.checkpoint`): a gradient holds one chunk's fan intermediates (~64 incomplete
    gammas per pixel, ≤ 4 GB), not every pixel's (29 GB for 1e5 clumps). Below, no
    checkpoint: its barriers cost the forward pass ~20 % (paper scene).
    """
    # one table of Q(2n, ·) per clump, read by all its pixels' fan nodes
    table = incgamma.q_table(2 * clumps.n)

    def one(xl, xh, yl, yh, c1, c2, re, n, q, pa, b, w):
        return profiles.sersic_pixel_flux_exact(xl, xh, yl, yh, flux=1.0, re_arcsec=re,
                                                n=n, q=q, pa_rad=pa, center1=c1, center2=c2, b=b,
                                                q_table=table, q_index=w)

    args = (x_lo, x_hi, y_lo, y_hi, clumps.center_arcsec[which, 0], clumps.center_arcsec[which, 1],
            clumps.re_arcsec[which], clumps.n[which], clumps.q[which], clumps.pa_rad[which],
            b[which], which)
    total = x_lo.shape[0]
    chunks = -(-total // _EXACT_CHUNK)
    if chunks <= 1:
        return jax.vmap(one)(*args)
    size = -(-total // chunks)
    # padding repeats the last pixel (a valid one), so padded lanes stay finite
    args = [jnp.concatenate([a, jnp.broadcast_to(a[-1:], (chunks * size - total,))])
            .reshape(chunks, size) for a in args]
    # prevent_cse=False: the loop already keeps XLA from merging recomputation and forward
    out = jax.lax.map(jax.checkpoint(lambda xs: jax.vmap(one)(*xs), prevent_cse=False), args)
    return out.reshape(-1)[:total]


def _tile_side(sides) -> int:
    """Side of the square tiles the stamps of these sides are cut into: their greatest common
    divisor (every side of the ladder is a multiple of 4; one side alone: the stamp itself)."""
    return math.gcd(*(int(s) for s in sides))


def _sampled_tiles(clumps: Clumps, b, which, i0, j0, grids, starts, tile: int, order: int):
    """Gauss–Legendre (order²) pixel integrals [T, tile, tile] of unit-flux clumps `which`
    [T] on tiles of `tile` × `tile` pixels with pixel [0, 0] at (i0, j0) [T] of grids[g]
    for the tiles from starts[g] on (static, increasing): one broadcast evaluation over [tile, y offset, row,
    x offset, column] for every tile of every stamp size and grid, so that the profile is
    compiled once however many stamp sizes and grids there are."""
    dtype = jnp.result_type(clumps.re_arcsec)
    offs, wts = gauss_legendre_offsets(order)
    # each tile's grid, from the static ranges (not a [T] constant in the program)
    target = jnp.sum(jnp.arange(which.shape[0])[:, None] >= jnp.asarray(starts[1:] or [
        which.shape[0]], jnp.int32)[None, :], axis=1)
    x0 = jnp.asarray([g.x0_arcsec for g in grids], dtype)[target]
    y0 = jnp.asarray([g.y0_arcsec for g in grids], dtype)[target]
    p = jnp.asarray([g.pixel_arcsec for g in grids], dtype)[target]
    o = jnp.asarray(offs, dtype)[None, :] * p[:, None]                  # [T, order]
    w = jnp.asarray(wts, dtype)
    k = jnp.arange(tile)
    xc = x0[:, None] + (i0[:, None] + k).astype(dtype) * p[:, None]    # [T, tile]
    yc = y0[:, None] + (j0[:, None] + k).astype(dtype) * p[:, None]
    x = xc[:, None, None, None, :] + o[:, None, None, :, None]
    y = yc[:, None, :, None, None] + o[:, :, None, None, None]

    def per_tile(a):
        return a[which][:, None, None, None, None]

    val = sersic_unit_brightness(
        x, y, re_arcsec=per_tile(clumps.re_arcsec), n=per_tile(clumps.n),
        q=per_tile(clumps.q), pa_rad=per_tile(clumps.pa_rad),
        center1=per_tile(clumps.center_arcsec[:, 0]),
        center2=per_tile(clumps.center_arcsec[:, 1]), b=per_tile(b))
    wy = w[None, :, None, None, None]
    wx = w[None, None, None, :, None]
    return jnp.sum(val * wy * wx, axis=(1, 3)) * (p * p)[:, None, None]


def _div(a, k: int):
    """a // k for integers a ≥ 0 (truncating: no sign correction)."""
    return jax.lax.div(a, jnp.asarray(k, a.dtype))


def _rem(a, k: int):
    """a % k for integers a ≥ 0."""
    return jax.lax.rem(a, jnp.asarray(k, a.dtype))


def grouped_stamps_on(clumps: Clumps, targets, *, order: int = 3, core: int = 5,
                      strip: bool = False):
    """Unit-flux stamps of clumps on several grids: for each (grid, groups) of `targets`, a
    list [(tiles [T, t, t], i0 [T], j0 [T], clump index [T])] (empty without groups) of the
    square tiles its stamp groups are cut into. A group is (side, indices into `clumps`) or
    (side, indices, strip), which overrides `strip`; a clump of a group of side s has a stamp
    of s × s pixels around its centre, cut into (s / t)² tiles of t × t (t: the greatest
    common divisor of the sides, `_tile_side`), each with its own origin (i0, j0) in the grid.

    Pixels are Gauss–Legendre sampled (order²) except a block of core² pixels around the
    centre, integrated exactly. strip=True integrates exactly instead the 3·stamp + core²
    pixels nearest the major axis: a thin profile (minor axis below a pixel, such as a
    lensed clump) puts its light on that line, where sampling misses or overweights it.
    b(n), the sampled tiles and the exact integrals of every group on every grid are one
    computation each (`_sampled_tiles`, `_exact_fluxes`), so the profile and the incomplete
    gamma function compile once however many stamp sizes and grids there are (issue 20: one
    copy per stamp group was a fifth of the band render's program).
    """
    out = [[] for _ in targets]
    sides = [side for _, groups in targets for side, *_ in groups]
    if not sides:
        return out
    tile = _tile_side(sides)
    dtype = jnp.result_type(clumps.re_arcsec)
    b = profiles.sersic_b(clumps.n)
    # What depends only on the stamp sides (each tile's and exact pixel's offset from its
    # clump's centre pixel, where each exact value goes, and its place among the groups'
    # clumps) is NumPy, made here; the program gathers the clumps (their indices may be a
    # model's arrays) and their centre pixels once per grid, not per stamp group, and what
    # the thin groups' strips need once for all of them (the paper scene's band render:
    # its clump stamps 5729 → 4763 operations, the same bits).
    which, ti0, tj0, ranges = _Pieces(), [], [], []
    exact = _Pieces()
    start = 0
    for grid, groups in targets:
        p = grid.pixel_arcsec
        first = start
        # the pixel of every clump's centre, once per grid (`clump_stamp_origin`)
        ic = _pixel_index(clumps.center_arcsec[:, 0], grid.x0_arcsec, p)
        jc = _pixel_index(clumps.center_arcsec[:, 1], grid.y0_arcsec, p)
        # the groups' clump indices, one array: tiles and exact pixels are gathered from it
        indices = [idx if isinstance(idx, jax.Array) else np.asarray(idx)
                   for _, idx, *_ in groups]
        thin_of = [(group_strip[0] if group_strip else strip) and min(core, side) > 0
                   for side, _, *group_strip in groups]
        # what the thin groups' strips need of their clumps, gathered once for all of them
        thin = _thin_clumps(clumps, [idx for idx, t in zip(indices, thin_of) if t], ic, jc)
        sizes = [idx.shape[0] for idx in indices]
        indices = _joined(indices)
        tiles, pieces, offset, thin_offset = _Pieces(), _Pieces(), 0, 0
        for (side, *_), n, is_thin in zip(groups, sizes, thin_of):
            m, half = side // tile, side // 2
            # the tiles of each stamp, row-major: tile (r, c) has its pixel [0, 0] at
            # stamp pixel (r t, c t)
            tr, tc = np.divmod(np.arange(m * m), m)
            tiles.add(*(v.astype(np.int32) for v in (
                offset + np.repeat(np.arange(n), m * m), np.tile(tc * tile - half, n),
                np.tile(tr * tile - half, n))))
            c = min(core, side)
            if c > 0:
                if is_thin:
                    row, col = _strip_pixels_of([v[thin_offset:thin_offset + n] for v in thin],
                                                grid, side, c, dtype)
                    thin_offset += n
                    at_tile = (start + np.arange(n)[:, None] * (m * m)
                               + _div(row, tile) * m + _div(col, tile))
                    at_pixel = _rem(row, tile) * tile + _rem(col, tile)
                else:       # the core block: the same pixels of every stamp
                    row, col = np.divmod(_core_pixels(side, c)[None, :], side)
                    at_tile = (start + np.arange(n)[:, None] * (m * m)
                               + (row // tile) * m + col // tile)
                    row, col, at_pixel = (np.broadcast_to(v, at_tile.shape) for v in
                                          (row, col, (row % tile) * tile + col % tile))
                count = row.shape[1]
                pieces.add(*(v.astype(np.int32) for v in (
                    offset + np.repeat(np.arange(n), count), col - half, row - half, at_tile,
                    at_pixel)))
            start += n * m * m
            offset += n
        t_which, dc, dr = tiles.joined()
        t_which = indices[t_which]
        which.add(t_which)
        ti0.append(ic[t_which] + dc)
        tj0.append(jc[t_which] + dr)
        if pieces:      # the exact pixels' edges, once per grid
            ew, dcol, drow, at_tile, at_pixel = pieces.joined()
            ew = indices[ew]
            exact.add(ew, at_tile, at_pixel,
                      *_pixel_edges(ic[ew] + dcol, grid.x0_arcsec, p, dtype),
                      *_pixel_edges(jc[ew] + drow, grid.y0_arcsec, p, dtype))
        ranges.append((first, start))
    which = jnp.asarray(which.joined()[0])
    ti0, tj0 = jnp.concatenate(ti0), jnp.concatenate(tj0)
    stamps = _sampled_tiles(clumps, b, which, ti0, tj0,
                            [grid for grid, _ in targets], [lo for lo, _ in ranges], tile, order)
    if exact:
        ew, at_tile, at_pixel, *edges = exact.joined()
        values = _exact_fluxes(clumps, b, jnp.asarray(ew), *edges)
        stamps = (stamps.reshape(start, tile * tile).at[at_tile, at_pixel]
                  .set(values.astype(dtype)).reshape(start, tile, tile))
    for t, (lo, hi) in enumerate(ranges):
        if hi > lo:
            out[t].append((stamps[lo:hi], ti0[lo:hi], tj0[lo:hi], which[lo:hi]))
    return out


class _Pieces:
    """Columns of flat index arrays added piece by piece, NumPy or traced, joined in order:
    consecutive NumPy pieces are joined by NumPy (one constant in the program)."""

    def __init__(self):
        self.columns = None

    def __bool__(self):
        return self.columns is not None

    def add(self, *pieces):
        if self.columns is None:
            self.columns = [[] for _ in pieces]
        for col, piece in zip(self.columns, pieces):
            if isinstance(piece, np.ndarray):
                piece = piece.ravel()
                if col and isinstance(col[-1], np.ndarray):
                    col[-1] = np.concatenate([col[-1], piece])
                    continue
            else:
                piece = piece.ravel()
            col.append(piece)

    def joined(self):
        """Each column as one array (NumPy when it has no traced piece)."""
        return [_joined(col) for col in self.columns]


def _joined(arrays):
    """1-D arrays, NumPy or traced, as one: NumPy when all are (a constant of the program)."""
    if len(arrays) == 1:
        return arrays[0]
    if any(isinstance(a, jax.Array) for a in arrays):
        return jnp.concatenate(arrays)
    return np.concatenate(arrays)


def _thin_clumps(clumps: Clumps, indices, ic, jc):
    """[centre pixel column, row, centre x, y (arcsec), position angle] of the clumps of the
    index arrays `indices` (NumPy or traced) one after the other; None without any."""
    if not indices:
        return None
    idx = _joined(indices)
    return [ic[idx], jc[idx], clumps.center_arcsec[idx, 0], clumps.center_arcsec[idx, 1],
            clumps.pa_rad[idx]]


def _strip_pixels_of(thin, grid: Grid, side: int, core: int, dtype):
    """(row, col) [n, count] in their stamps of the pixels of n thin clumps to integrate
    exactly (`_strip_pixels_flat`), their stamps of `side` pixels of `grid` around their
    centre pixels; thin: `_thin_clumps`' arrays of those n."""
    p = grid.pixel_arcsec
    k = jnp.arange(side)
    ic, jc, c1, c2, pa = thin
    i0, j0 = ic - side // 2, jc - side // 2
    xc = grid.x0_arcsec + (i0[:, None] + k).astype(dtype) * p
    yc = grid.y0_arcsec + (j0[:, None] + k).astype(dtype) * p
    flat = _strip_pixels_flat(c1, c2, pa, xc, yc, side, core, i0.shape[0])
    # indices ≥ 0: truncating division (lax.div, lax.rem) is floor division here, without
    # jnp's sign corrections
    return _div(flat, side), _rem(flat, side)


def scatter_stamps(stamps, i0, j0, weights, grid: Grid, out=None):
    """Σ_k weights[k, c] × stamps[k] placed at (i0, j0): images [ny, nx, C] (channels last),
    added to `out` (default zeros).

    Channels last, so that one lookup of a pixel reads every band at once.
    Parts of stamps that fall outside the grid are dropped (scattered past its end, where
    `mode="drop"` discards them: no padded copy of the grid is made, ~100 MB a stamp size
    on a high-resolution lens plane).
    """
    n, s, _ = stamps.shape
    k = jnp.arange(s)
    rows = jnp.broadcast_to(j0[:, None, None] + k[None, :, None], (n, s, s))
    cols = jnp.broadcast_to(i0[:, None, None] + k[None, None, :], (n, s, s))
    inside = (rows >= 0) & (rows < grid.ny) & (cols >= 0) & (cols < grid.nx)
    rows = jnp.where(inside, rows, grid.ny)     # past the end (a negative index would wrap)
    vals = stamps[..., None] * weights[:, None, None, :]  # [N, s, s, C]
    if out is None:
        out = jnp.zeros((grid.ny, grid.nx, weights.shape[1]), stamps.dtype)
    return out.at[rows, cols].add(vals, mode="drop")


_STAMP_SIDES = (8, 12, 16, 24, 32, 48, 64, 96, 128, 192, 256, 384, 512)


def stamp_groups(re_arcsec, n, pixel_arcsec: float, *, flux_fraction: float = 0.9999,
                 margin: float = 1.25):
    """Clumps grouped by the stamp side they need: [(side, indices)], sides from a short ladder.

    Each clump's stamp holds `flux_fraction` of its light with R_e enlarged by
    `margin` (room for fits that grow it). Grouping keeps the cost at Σ side²
    over clumps instead of N × the largest side², with few compiled shapes.
    """
    re = np.atleast_1d(np.asarray(re_arcsec, float))
    n = np.atleast_1d(np.asarray(n, float))
    need = np.array([stamp_size(r * margin, k, pixel_arcsec, flux_fraction=flux_fraction)
                     for r, k in zip(re, n)])
    sides = np.array([next((s for s in _STAMP_SIDES if s >= k), int(k + k % 2)) for k in need])
    return [(int(side), np.nonzero(sides == side)[0]) for side in np.unique(sides)]


def strip_needed(re_arcsec, n, pixel_arcsec: float, core: int, *, q=None,
                 thin_pixels: float = 1.0, margin: float = 1.25, beyond: float = 1e-4):
    """Which profiles (numpy [N] of R_e, arcsec, and n) need the exact strip along their
    major axis: those with more than `beyond` of their light outside the exact core block
    (radius (core // 2) pixels from the centre; R_e enlarged by `margin` for fits that grow
    it). Given q, only the light where the profile is thin counts: at major-axis radii
    r beyond `thin_pixels` pixels with q·r < `thin_pixels` pixels — most of the profile
    when q·R_e is below a pixel, the inner ridge of a cuspy (n > 1) elongated one however
    large its R_e; never a round one. Elsewhere order ≥ 3 sampling keeps pixel sums within
    2e-3 of the light (tests/test_hard_cases.py)."""
    from scipy.special import gammaincc, gammaincinv
    re = np.asarray(re_arcsec, float) * margin
    n = np.asarray(n, float)
    b = gammaincinv(2 * n, 0.5)

    def outside(r):
        return gammaincc(2 * n, b * (r / re) ** (1 / n))

    r_core = (core // 2) * pixel_arcsec
    if q is None:
        return outside(r_core) > beyond
    # thin: beyond a pixel from the centre (within it, the profile is small, not thin)
    r_lo = max(r_core, thin_pixels * pixel_arcsec)
    r_thin = thin_pixels * pixel_arcsec / np.asarray(q, float)
    return outside(r_lo) - outside(np.maximum(r_thin, r_lo)) > beyond


def strip_groups(re_arcsec, n, pixel_arcsec: float, core: int, *, q=None,
                 flux_fraction: float = 0.9999):
    """`stamp_groups` split by whether the exact strip is needed (`strip_needed`, thin ones
    only when q is given): [((side, strip), indices)], empty groups left out."""
    need = strip_needed(re_arcsec, n, pixel_arcsec, core, q=q)
    groups = [((side, bool(flag)), idx[need[idx] == flag])
              for side, idx in stamp_groups(re_arcsec, n, pixel_arcsec,
                                            flux_fraction=flux_fraction)
              for flag in (True, False)]
    return [(key, idx) for key, idx in groups if idx.size]


def grouped_stamps(clumps: Clumps, grid: Grid, groups, *, order: int = 3, core: int = 5,
                   strip: bool = False):
    """Unit-flux stamps of every clump on one grid by stamp group: [(stamps, i0, j0, indices)]."""
    return grouped_stamps_on(clumps, [(grid, groups)], order=order, core=core, strip=strip)[0]


def scatter_grouped(stamps, weights, grid: Grid):
    """Σ over the `grouped_stamps` of weights[k, c] × stamp k: images [ny, nx, C] (one
    image that every group is added to)."""
    out = None
    for st, i0, j0, idx in stamps:
        out = scatter_stamps(st, i0, j0, weights[idx], grid, out)
    return 0.0 if out is None else out


def clumps_image(clumps: Clumps, grid: Grid, groups, weights, *, order: int = 3, core: int = 5,
                 strip: bool = False):
    """Σ over clumps of weights[k, c] × their pixel-integrated light on `grid`: [ny, nx, C]."""
    return clumps_images(clumps, [(grid, groups)], weights, order=order, core=core,
                         strip=strip)[0]


def clumps_images(clumps: Clumps, targets, weights, *, order: int = 3, core: int = 5,
                  strip: bool = False):
    """`clumps_image` on each (grid, groups) of `targets`, sharing one exact-pixel kernel."""
    stamps = grouped_stamps_on(clumps, targets, order=order, core=core, strip=strip)
    return [scatter_grouped(st, weights, grid) for st, (grid, _) in zip(stamps, targets)]


def stamp_size(re_arcsec_max: float, n_max: float, pixel_arcsec: float, *,
               flux_fraction: float = 0.9999, minimum: int = 8) -> int:
    """Static stamp side (pixels, even) that holds `flux_fraction` of the largest clump."""
    from scipy.special import gammaincinv
    r = re_arcsec_max * (gammaincinv(2 * n_max, flux_fraction)
                         / gammaincinv(2 * n_max, 0.5)) ** n_max
    side = int(np.ceil(2 * r / pixel_arcsec)) + 2
    side = max(side, minimum)
    return side + (side % 2)
