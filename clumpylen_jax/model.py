"""The composed forward model of a scene: source → (lens) → pixels → PSF → sky and noise.

`build_model` makes the static decisions once — grids, which lens-plane pixels
to ray-trace, stamp sizes, PSF transforms — and returns a `SceneModel`, an
equinox Module whose methods are pure functions of a `Source`:

- ``band_images(source)``: PSF-convolved source light per band, counts/s/pixel;
- ``noiseless(source)``: the same plus sky;
- ``observe(source, key)``: a photon-noise realisation and its variance map.

Only the stages a scene calls for are in the model: without a lens there is no
ray tracing, a band without PSF has no FFT, and no random numbers are drawn
unless ``observe`` is called. Rays are traced only over the lens-plane pixels
where the source lands, once, at build time (the lens is fixed in a model; the
source is what is differentiated).
"""

from __future__ import annotations

import dataclasses
from typing import Optional

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from . import convolve, noise, profiles, raycache, render, tiles
from . import defaults as D
from .errors import ConfigError, require
from .lensing.linearised import (ClumpImages, FootprintIndex, bilinear_patch,
                                 image_magnifications, lensed_clumps,
                                 light_averaged_flux_scale, linearisation_error,
                                 pixel_footprints, pixels_near, point_images)
from .pixels import Grid, bin_blocks, gauss_legendre_offsets, rebin_sparse, sparse_rebin_operators
from .source import Source


from .accuracy import ACCURACY_PRESETS, SOURCE_MODES, Accuracy  # noqa: F401  (re-exported)


@dataclasses.dataclass(frozen=True)
class Band:
    """One band as the model needs it.

    name: filter name.  pixel_arcsec: detector pixel.  exptime_s, sky_counts_per_s: exposure
    and sky per detector pixel.  psf: PSF image sampled at `psf_pixel_arcsec` (numpy) or None.
    psf_effective: True when the PSF already includes the detector pixel response.
    """

    name: str
    pixel_arcsec: float
    exptime_s: float
    sky_counts_per_s: float = 0.0
    psf: Optional[np.ndarray] = dataclasses.field(default=None, compare=False, hash=False)
    psf_pixel_arcsec: Optional[float] = None
    psf_effective: bool = False

    def validate(self, name=None):
        name = name or f"bands[{self.name}]"
        require(np.isfinite(self.pixel_arcsec) and self.pixel_arcsec > 0,
                f"{name}.pixel_arcsec", self.pixel_arcsec, "a positive pixel scale (arcsec)")
        require(np.isfinite(self.exptime_s) and self.exptime_s > 0, f"{name}.exptime_s",
                self.exptime_s, "a positive exposure time (s)")
        require(np.isfinite(self.sky_counts_per_s) and self.sky_counts_per_s >= 0,
                f"{name}.sky_counts_per_s", self.sky_counts_per_s, "a sky level ≥ 0 counts/s/pixel")
        if self.psf is not None:
            convolve.check_psf_values(self.psf, f"{name}.psf")
            require(self.psf_pixel_arcsec is not None and self.psf_pixel_arcsec > 0,
                    f"{name}.psf_pixel_arcsec", self.psf_pixel_arcsec,
                    "the PSF's pixel scale in arcsec")
        return self


@dataclasses.dataclass(frozen=True)
class _BandLayout:
    """Static per-band layout inside a model."""

    name: str
    grid: Grid             # detector pixels
    oversampling: int      # sub-grid on which the PSF acts (1 without PSF)
    exptime_s: float
    sky_counts_per_s: float
    psf_shape: Optional[tuple]
    psf_effective: bool
    stamp_sides: tuple     # clump stamp (side, strip) groups on the sub-grid (unlensed models)
    host_strips: tuple     # (bulge, disk): exact strip, not core, on the sub-grid (unlensed)


# ------------------------------------------------------------------ static helpers


_radius_enclosing = profiles.sersic_radius_enclosing_np  # numpy, build-time only


def source_extent(source: Source, flux_fraction: float, stamp_flux_fraction: float):
    """(center (2,), radius arcsec) of a disc holding the source's light, from concrete parameters."""
    comps = [c for c in (source.bulge, source.disk.sersic if source.disk is not None else None)
             if c is not None]
    centers = [np.asarray(c.center_arcsec, float) for c in comps]
    if source.clumps is not None and source.clumps.count > 0:
        cc = np.asarray(source.clumps.center_arcsec, float)
        center = centers[0] if centers else cc.mean(axis=0)
    elif centers:
        center = centers[0]
    else:
        raise ConfigError("source", "no components", "at least one of bulge, disk or clumps")
    radius = 0.0
    for c in comps:
        r = float(_radius_enclosing(flux_fraction, c.re_arcsec, c.n))
        radius = max(radius, r + float(np.hypot(*(np.asarray(c.center_arcsec) - center))))
    if source.clumps is not None and source.clumps.count > 0:
        cl = source.clumps
        re = np.asarray(cl.re_arcsec, float)
        n = np.asarray(cl.n, float)
        rcut = _radius_enclosing(stamp_flux_fraction, re, n)
        d = np.hypot(*(np.asarray(cl.center_arcsec, float) - center).T)
        radius = max(radius, float(np.max(d + rcut)))
    return np.asarray(center), radius


def _unlensed_clump_groups(source: Source, pixel_arcsec: float, accuracy):
    """Stamp groups [((side, strip), indices)] of an unlensed source's clumps on a grid of
    this pixel: the exact strip for thin clumps with light beyond the exact core."""
    cl = source.clumps
    if cl is None or cl.count == 0:
        return []
    if not accuracy.thin_strip:
        return [((side, False), idx) for side, idx in render.stamp_groups(
            cl.re_arcsec, cl.n, pixel_arcsec, flux_fraction=accuracy.stamp_flux_fraction)]
    return render.strip_groups(cl.re_arcsec, cl.n, pixel_arcsec, accuracy.exact_core, q=cl.q,
                               flux_fraction=accuracy.stamp_flux_fraction)


def _host_strips(source: Source, pixel_arcsec: float, core: int):
    """(bulge, disk): whether each host component needs the exact strip on a grid of this
    pixel (thin, with light beyond the exact core; the disk only when a plain Sérsic)."""
    def need(s, q):
        return bool(render.strip_needed(np.asarray(s.re_arcsec), np.asarray(s.n), pixel_arcsec,
                                        core, q=np.asarray(q)))
    disk = source.disk
    return (source.bulge is not None and need(source.bulge, source.bulge.q),
            disk is not None and disk.arms is None and disk.texture is None
            and need(disk.sersic, disk.q_projected))


def _cols(a, lo, hi):
    """Columns lo:hi of a [T, n] operator array, or None."""
    return None if a is None else a[:, lo:hi]


def _trace_in_chunks(lens, theta1, theta2, chunk=1 << 20):
    """β of rays θ (numpy, flat), computed with the lens in float64 by chunks."""
    out1 = np.empty_like(theta1)
    out2 = np.empty_like(theta2)
    f = jax.jit(lambda a, b: lens.deflection(a, b))
    for s in range(0, theta1.size, chunk):
        a1, a2 = f(jnp.asarray(theta1[s:s + chunk]), jnp.asarray(theta2[s:s + chunk]))
        out1[s:s + chunk] = theta1[s:s + chunk] - np.asarray(a1)
        out2[s:s + chunk] = theta2[s:s + chunk] - np.asarray(a2)
    bad = ~(np.isfinite(out1) & np.isfinite(out2))
    if np.any(bad):
        k = int(np.argmax(bad))
        raise ConfigError("lens", f"non-finite deflection at θ = ({theta1[k]:.4f}, {theta2[k]:.4f})\" "
                          f"({int(bad.sum())} rays)",
                          "a lens with finite deflections over the traced field (NaN in the "
                          "deflection maps there?)")
    return out1, out2


def trace_corners(lens, hr_grid: Grid):
    """β (two [ny + 1, nx + 1] arrays) at the corners of every lens-plane pixel."""
    xc, yc = np.meshgrid(hr_grid.x_edges(), hr_grid.y_edges())
    b1, b2 = _trace_in_chunks(lens, xc.ravel(), yc.ravel())
    return b1.reshape(xc.shape), b2.reshape(xc.shape)


def traced_pixels(corner_b1, corner_b2, center, radius):
    """Rows and columns of lens-plane pixels whose light can come from the source disc,
    and the `FootprintIndex` of their source-plane footprints.

    A pixel is traced when the disc (center, radius) comes within its
    source-plane footprint: the distance from the mean of its corners' β to the
    centre is below radius + the largest corner distance from that mean, so
    that thin, highly magnified images are not missed.
    """
    m1, m2, reach = pixel_footprints(corner_b1, corner_b2)
    keep = np.hypot(m1 - center[0], m2 - center[1]) < radius + 1.01 * reach
    rows, cols = np.nonzero(keep)
    return rows, cols, FootprintIndex(m1[keep], m2[keep], reach[keep])


def rays_in_pixels(corner_b1, corner_b2, rows, cols, offsets):
    """β of rays at sub-pixel offsets (in (−½, ½) pixel) of the given pixels: [M, R] each.

    Bilinear interpolation of the corners' β: the lens mapping is smooth on the
    scale of a lens-plane pixel, and each pixel needs one deflection per corner
    instead of one per ray.
    """
    ox, oy = offsets
    fx = (ox + 0.5)[None, :]
    fy = (oy + 0.5)[None, :]
    return [bilinear_patch(b, rows[:, None], cols[:, None], fx, fy, derivatives=False)
            for b in (corner_b1, corner_b2)]


# ------------------------------------------------------------------ the model


def _n_bands(source: Source) -> int:
    for comp in (source.bulge, source.disk.sersic if source.disk is not None else None):
        if comp is not None:
            return comp.flux.shape[0]
    return source.clumps.flux.shape[1]



class SceneModel(eqx.Module):
    """A scene's forward model; build it with `build_model`."""

    layouts: tuple = eqx.field(static=True)
    accuracy: Accuracy = eqx.field(static=True)
    lensed: bool = eqx.field(static=True)
    hr_grid: Optional[Grid] = eqx.field(static=True)
    clump_grid: Optional[Grid] = eqx.field(static=True)
    clump_stamp_sides: tuple = eqx.field(static=True)
    clump_stamp_index: tuple
    clump_tiles: Optional[jnp.ndarray]       # slot of each tile of the bordered source grid
    clump_tile_layout: Optional[tiles.TileLayout] = eqx.field(static=True)
    psf_fts: tuple
    rebin_ops: tuple
    traced_rows: Optional[jnp.ndarray]
    traced_cols: Optional[jnp.ndarray]
    beta1: Optional[jnp.ndarray]
    beta2: Optional[jnp.ndarray]
    ray_weights: Optional[jnp.ndarray]
    beta1_center: Optional[jnp.ndarray]
    beta2_center: Optional[jnp.ndarray]
    stamp_index_unlensed: tuple = ()
    # rays exist for the traced pixels (ray_rows, ray_cols) (all of them, or those reaching
    # a ray-traced clump), which lie in the window rows r0:r1, cols c0:c1 of hr_grid;
    # linearised clump images and their stamp groups ((side, strip) and indices) on each
    # band's sub-grid and on hr_grid
    ray_rows: Optional[jnp.ndarray] = None
    ray_cols: Optional[jnp.ndarray] = None
    ray_window: tuple = eqx.field(static=True, default=(0, 0, 0, 0))
    lin_images: Optional[ClumpImages] = None
    lin_stamp_sides: tuple = eqx.field(static=True, default=())
    lin_stamp_index: tuple = ()
    lin_hr_sides: tuple = eqx.field(static=True, default=())
    lin_hr_index: tuple = ()
    # traced pixels near the images of a host component's centre (indices into the traced
    # pixels), their sub-pixels' source-plane footprints' corners [K, S, 4] and 1 / their areas
    host_core_index: Optional[jnp.ndarray] = None
    host_core_b1: Optional[jnp.ndarray] = None
    host_core_b2: Optional[jnp.ndarray] = None
    host_core_inv_area: Optional[jnp.ndarray] = None
    host_core_origin: tuple = eqx.field(static=True, default=(0.0, 0.0))   # corners are from it

    @property
    def band_names(self):
        return tuple(b.name for b in self.layouts)

    # -- lens plane ------------------------------------------------------------

    def _clump_groups(self):
        return tuple(zip(self.clump_stamp_sides, self.clump_stamp_index))

    def _clump_tiles(self, stamps, flux):
        """Clump surface brightness [size, C] of C bands in the source grid's stored tiles.

        The grid has a zero border of one pixel (rays beyond it read zero), hence +1.
        """
        store = None
        for st, i0, j0, idx in stamps:
            store = tiles.scatter_stamps(self.clump_tile_layout, self.clump_tiles, st, i0 + 1,
                                         j0 + 1, flux[idx], store)
        return store / self.clump_grid.pixel_arcsec**2

    def _ray_positions(self):
        """Rays' fractional pixel indices in the bordered source grid: (x, y), [P, R] each."""
        g = self.clump_grid
        return ((self.beta1 - g.x0_arcsec) / g.pixel_arcsec + 1.0,
                (self.beta2 - g.y0_arcsec) / g.pixel_arcsec + 1.0)

    def _band_chunk(self, nb: int) -> int:
        """Bands per source-plane grid: as many as fit in ~0.5 GB."""
        return int(max(1, min(nb, 5.0e8 // (8 * self.clump_tile_layout.size))))

    def _clump_values(self, source: Source, nb: int, stamps=None, block: int = 1 << 17):
        """Clump light [B, M] of every traced pixel, from the source-plane grid.

        Sequential over groups of bands (one grid in memory at a time) and over
        blocks of pixels (bounded temporaries), so memory stays flat however
        many bands and rays a scene has.
        """
        g = self.clump_grid
        w = self.ray_weights
        m = self.beta1.shape[0]
        step = self._band_chunk(nb)
        n_chunks = -(-nb // step)
        flux = jnp.pad(source.clumps.flux, ((0, 0), (0, n_chunks * step - nb)))
        flux = flux.reshape(flux.shape[0], n_chunks, step).transpose(1, 0, 2)
        n_blocks = -(-m // block)
        pad = n_blocks * block - m

        def blocks(x):
            return jnp.pad(x, ((0, pad), (0, 0))).reshape(n_blocks, block, -1)

        xs, ys = (blocks(x) for x in self._ray_positions())

        # the stamps hold unit flux: made once, scattered with each group of bands' fluxes
        if stamps is None:
            stamps = render.grouped_stamps(source.clumps, g, self._clump_groups(),
                                           order=self.accuracy.source_order,
                                           core=self.accuracy.exact_core)

        def one_chunk(f):
            store = self._clump_tiles(stamps, f)

            def one_block(xy):
                vals = tiles.bilinear(self.clump_tile_layout, self.clump_tiles, store, *xy)
                return jnp.einsum("mrc,r->mc", vals, w)

            return jax.lax.map(one_block, (xs, ys)).reshape(n_blocks * block, step)[:m]

        vals = jax.lax.map(one_chunk, flux)                      # [chunks, M, step]
        return vals.transpose(0, 2, 1).reshape(n_chunks * step, m)[:nb]

    def _host_values(self, source: Source):
        """Host light at every traced pixel: (units [M, C] per unit flux, fluxes [C, B]).

        One column per host component: each is achromatic, so every band is a linear
        combination of C ≤ 2 lens-plane images.
        """
        dtype = self.beta1_center.dtype
        # host components vary slowly across a lens-plane pixel's footprint: one ray per
        # pixel (its centre) unless host_subsampling asks for all of them
        if self.accuracy.host_subsampling:
            h1, h2, hw = self.beta1, self.beta2, self.ray_weights
        else:
            h1, h2, hw = self.beta1_center[:, None], self.beta2_center[:, None], jnp.ones(1, dtype)
        units, fluxes = [], []
        if source.bulge is not None:
            s = source.bulge
            kw = render._sersic_kw(s)
            units.append(self._exact_host_core(
                render.sersic_unit_brightness(h1, h2, **kw) @ hw, kw))
            fluxes.append(s.flux)
        if source.disk is not None:
            d = source.disk
            u = render.disk_unit_brightness(d, h1, h2) @ hw
            if d.arms is None and d.texture is None:
                u = self._exact_host_core(u, render._disk_kw(d))
            elif self.host_core_index is not None:
                # arms × texture vary slowly: the sampled modulation times the exact Sérsic
                kw = render._disk_kw(d)
                i = self.host_core_index
                smooth = render.sersic_unit_brightness(h1[i], h2[i], **kw) @ hw
                u = self._exact_host_core(u, kw, modulation=u[i] / jnp.maximum(
                    smooth, jnp.finfo(smooth.dtype).tiny))
            units.append(u)
            fluxes.append(d.sersic.flux)
        if not units:
            return None, None
        area = self.hr_grid.pixel_arcsec**2
        return jnp.stack(units, -1) * area, jnp.stack(fluxes, 0)

    def _exact_host_core(self, brightness, kw, modulation=None):
        """Host brightness [M] at the traced pixels with, near the images of its centre, the
        mean over each pixel instead of a sample: the exact integral of the Sérsic over the
        pixel's source-plane footprint (a quadrilateral) divided by its area (a sample
        misses or invents the light of a cusp: +3 % of an n = 4 host of R_e 4 lens pixels).
        modulation: the disk's arms × texture factor [K] at those pixels, or None."""
        if self.host_core_index is None:
            return brightness
        idx = self.host_core_index
        # corners relative to a point near the host (sub-pixel edges of 1e-4" would lose
        # two digits next to β ~ 10" in float32)
        kw = dict(kw, center1=kw["center1"] - self.host_core_origin[0],
                  center2=kw["center2"] - self.host_core_origin[1])
        exact = _footprint_mean_brightness(self.host_core_b1, self.host_core_b2,
                                           self.host_core_inv_area, kw)
        if modulation is not None:
            exact = exact * modulation
        return brightness.at[idx].set(exact.astype(brightness.dtype))

    def _clump_ray_values(self, source: Source, stamps=None):
        """Ray-traced clump flux [B, P] of the pixels with rays (counts/s), or None.
        stamps: the ray-traced clumps' source-grid stamps, when already made."""
        if source.clumps is None or source.clumps.count == 0:
            return None
        if self.accuracy.source_mode == "analytic":
            vals = render.clumps_brightness(source.clumps, self.beta1, self.beta2) @ self.ray_weights
        elif self.clump_grid is not None:
            vals = self._clump_values(source, _n_bands(source), stamps)
        else:
            return None
        return vals * self.hr_grid.pixel_arcsec**2

    def _clump_window(self, source: Source, stamps=None):
        """Ray-traced clumps on the window of hr_grid holding the rays: [h, w, B], or None."""
        vals = self._clump_ray_values(source, stamps)
        if vals is None:
            return None
        r0, r1, c0, c1 = self.ray_window
        img = jnp.zeros((r1 - r0, c1 - c0, vals.shape[0]), vals.dtype)
        return img.at[self.ray_rows - r0, self.ray_cols - c0].set(vals.T)

    def _clump_stamps(self, source: Source, grids):
        """Linearised clump images on each (grid, sides, index) of `grids` ([ny, nx, B] counts/s
        per pixel each; [] without linearised clumps) and the ray-traced clumps' stamps on the
        source grid (None without them), made in one call: one exact-pixel kernel for all."""
        acc = self.accuracy
        cl = source.clumps
        traced = (self.clump_grid is not None and acc.source_mode != "analytic"
                  and cl is not None and cl.count > 0)
        lin = lensed_clumps(cl, self.lin_images) if self._has_linearised(source) else None
        if lin is None and not traced:
            return [], None
        k = 0 if lin is None else lin.count
        sets = [c for c in (lin, cl if traced else None) if c is not None]
        both = sets[0] if len(sets) == 1 else jax.tree_util.tree_map(
            lambda a, b: jnp.concatenate([a, b]), *sets)
        targets = [] if lin is None else [
            (g, tuple((side, idx, strip) for (side, strip), idx in zip(sides, index)))
            for g, sides, index in grids]
        if traced:   # exact cores, not strips (strip=False below)
            targets.append((self.clump_grid, tuple((side, idx + k) for side, idx
                                                   in self._clump_groups())))
        stamps = render.grouped_stamps_on(both, targets, order=acc.source_order,
                                          core=acc.exact_core)
        images = ([] if lin is None else
                  [render.scatter_grouped(st, lin.flux, g) for st, (g, _)
                   in zip(stamps, targets)])
        return images, ([(st, i0, j0, idx - k) for st, i0, j0, idx in stamps[-1]]
                        if traced else None)

    def _has_linearised(self, source: Source):
        return (self.lin_images is not None and self.lin_images.count > 0
                and source.clumps is not None)

    def source_magnification_map(self):
        """Lens-plane area landing on each stored source-grid pixel / that pixel's area.

        The adjoint of the ray-tracing interpolation applied to ones, in the tiled
        storage ([size]; pixels no ray reads hold 0): Σ over a clump's stamp of this
        map × its light is exactly the magnification the model gives that clump.
        """
        lay, slots = self.clump_tile_layout, self.clump_tiles
        x, y = self._ray_positions()

        def lensed_total(store):
            return jnp.sum(tiles.bilinear(lay, slots, store[:, None], x, y)[..., 0]
                           @ self.ray_weights)

        zeros = jnp.zeros(lay.size, self.beta1.dtype)
        grad = jax.grad(lensed_total)(zeros)
        return grad * (self.hr_grid.pixel_arcsec / self.clump_grid.pixel_arcsec) ** 2

    def clump_magnifications(self, source: Source):
        """Magnification [N] of each clump within the field (light-weighted over its stamp)."""
        cl = source.clumps
        if self.accuracy.source_mode == "analytic" and self.beta1 is not None:
            return self._analytic_magnifications(cl)
        out = jnp.zeros(cl.count, cl.re_arcsec.dtype)
        if self._has_linearised(source):
            # a linearised clump: Σ |μ| over its images (each wholly inside the field)
            out = out.at[self.lin_images.clump_index].add(image_magnifications(self.lin_images,
                                                                               out.dtype))
        if self.clump_grid is None:
            return out
        mu = self.source_magnification_map()
        for stamps, i0, j0, idx in render.grouped_stamps(cl, self.clump_grid, self._clump_groups(),
                                                         order=self.accuracy.source_order,
                                                         core=self.accuracy.exact_core):
            k = jnp.arange(stamps.shape[1])
            rows = j0[:, None, None] + k[None, :, None] + 1      # +1: the grid's border
            cols = i0[:, None, None] + k[None, None, :] + 1
            at = tiles.flat_index(self.clump_tile_layout, self.clump_tiles, rows, cols)
            mags = jnp.sum(stamps * mu[at], axis=(1, 2)) / jnp.sum(stamps, axis=(1, 2))
            out = out.at[idx].set(mags)
        return out

    def _analytic_magnifications(self, cl):
        """Magnification [N] as the analytic path renders each clump: its unit-flux light
        summed over every ray (one clump at a time: the memory of one clump's rays)."""
        b = profiles.sersic_b(cl.n)
        area = self.hr_grid.pixel_arcsec**2

        def one(k):
            val = render.sersic_unit_brightness(
                self.beta1, self.beta2, re_arcsec=cl.re_arcsec[k], n=cl.n[k], q=cl.q[k],
                pa_rad=cl.pa_rad[k], center1=cl.center_arcsec[k, 0],
                center2=cl.center_arcsec[k, 1], b=b[k])
            return jnp.sum(val @ self.ray_weights) * area

        return jax.lax.map(one, jnp.arange(cl.count))

    def lens_plane(self, source: Source):
        """High-resolution lens-plane images [B, ny, nx], counts/s per lens-plane pixel."""
        nb = _n_bands(source)
        dtype = self.beta1_center.dtype
        img = jnp.zeros(self.hr_grid.shape + (nb,), dtype)
        units, fluxes = self._host_values(source)
        if units is not None:
            img = img.at[self.traced_rows, self.traced_cols].set(units @ fluxes)
        lin, traced = self._clump_stamps(
            source, [(self.hr_grid, self.lin_hr_sides, self.lin_hr_index)]
            if self.lin_hr_sides else [])
        win = self._clump_window(source, traced)
        if win is not None:
            r0, r1, c0, c1 = self.ray_window
            img = img.at[r0:r1, c0:c1].add(win)
        if lin:
            img = img + lin[0]
        return jnp.moveaxis(img, -1, 0)

    # -- detector ----------------------------------------------------------------

    def _unlensed_subgrid_image(self, source: Source, k: int, lay: _BandLayout, cache):
        """Pixel-integrated source light on band k's sub-grid (unlensed scenes). `cache` holds
        the images already made per sub-grid: hosts (made here), clumps (by band_images)."""
        g = lay.grid.subdivided(lay.oversampling)
        acc = self.accuracy
        key = ("host", g)
        if key not in cache:
            parts = []
            strip_bulge, strip_disk = lay.host_strips
            if source.bulge is not None:
                parts.append((source.bulge.flux,
                              render.sersic_image(source.bulge, g, order=acc.source_order,
                                                  core=acc.exact_core, strip=strip_bulge)))
            if source.disk is not None:
                parts.append((source.disk.sersic.flux,
                              render.disk_image(source.disk, g, order=acc.source_order,
                                                core=acc.exact_core, strip=strip_disk)))
            cache[key] = parts
        img = jnp.zeros(g.shape, jnp.result_type(*[p[1] for p in cache[key]])
                        if cache[key] else source.clumps.flux.dtype)
        for flux, unit in cache[key]:
            img = img + flux[k] * unit
        if ("clumps", g) in cache:
            img = img + cache[("clumps", g)][..., k]
        return img

    def _first_band_per_subgrid(self):
        """{sub-grid: index of its first band}: bands on the same sub-grid share every
        image made on it."""
        first = {}
        for k, lay in enumerate(self.layouts):
            first.setdefault(lay.grid.subdivided(lay.oversampling), k)
        return first

    def _observe_subgrid(self, sub, k: int, lay: _BandLayout):
        """PSF and detector pixels: sub-grid flux image → detector counts/s (no sky)."""
        s = lay.oversampling
        if lay.psf_shape is None:
            return bin_blocks(sub, s)
        conv = convolve.fft_convolve(sub, self.psf_fts[k], lay.psf_shape)
        if lay.psf_effective:
            # the PSF holds the pixel response: sample it at detector centres (DESIGN.md trap)
            return conv[s // 2::s, s // 2::s] * (s * s)
        return bin_blocks(conv, s)

    def band_images(self, source: Source):
        """PSF-convolved source light per band (tuple of [ny, nx], counts/s per pixel, no sky)."""
        out = []
        if self.lensed:
            units, fluxes = self._host_values(source)
            hosts = None
            if units is not None:
                hosts = jnp.zeros(self.hr_grid.shape + (units.shape[1],), units.dtype)
                hosts = hosts.at[self.traced_rows, self.traced_cols].set(units)
            r0, r1, c0, c1 = self.ray_window
            first = self._first_band_per_subgrid()
            images, traced = self._clump_stamps(
                source, [(g, self.lin_stamp_sides[k], self.lin_stamp_index[k])
                         for g, k in first.items()] if self.lin_stamp_sides else [])
            lin = dict(zip(first, images))
            win = self._clump_window(source, traced)
            cache = {}
            for k, lay in enumerate(self.layouts):
                g = lay.grid.subdivided(lay.oversampling)
                if g not in cache:
                    (ty, wy, my), (tx, wx, mx) = ops = self.rebin_ops[k]
                    parts = {}
                    if hosts is not None:
                        parts["hosts"] = rebin_sparse(hosts, ops, g.shape)
                    if win is not None:
                        parts["clumps"] = rebin_sparse(
                            win, ((ty[:, r0:r1], wy[:, r0:r1], _cols(my, r0, r1)),
                                  (tx[:, c0:c1], wx[:, c0:c1], _cols(mx, c0, c1))), g.shape)
                    if g in lin:
                        parts["linearised"] = lin[g]
                    cache[g] = parts
                parts = cache[g]
                sub = jnp.zeros(g.shape, self.beta1_center.dtype)
                if "hosts" in parts:
                    sub = sub + parts["hosts"] @ fluxes[:, k]
                for name in ("clumps", "linearised"):
                    if name in parts:
                        sub = sub + parts[name][..., k]
                out.append(self._observe_subgrid(sub, k, lay))
        else:
            cache = {}
            cl = source.clumps
            if cl is not None and cl.count > 0:
                # every band and every sub-grid at once: one exact-pixel kernel, and bands
                # on the same grid share the stamps
                first = self._first_band_per_subgrid()
                targets = [(g, tuple((side, idx, strip) for (side, strip), idx
                                     in zip(self.layouts[k].stamp_sides,
                                            self.stamp_index_unlensed[k])))
                           for g, k in first.items()]
                images = render.clumps_images(cl, targets, cl.flux,
                                              order=self.accuracy.source_order,
                                              core=self.accuracy.exact_core)
                cache.update({("clumps", g): img for (g, _), img in zip(targets, images)})
            for k, lay in enumerate(self.layouts):
                sub = self._unlensed_subgrid_image(source, k, lay, cache)
                out.append(self._observe_subgrid(sub, k, lay))
        return tuple(out)

    def noiseless(self, source: Source):
        """Band images with sky added (counts/s per pixel)."""
        return tuple(img + lay.sky_counts_per_s
                     for img, lay in zip(self.band_images(source), self.layouts))

    def variances(self, noiseless_images):
        """Poisson variance maps of noiseless images (with sky), (counts/s)²."""
        return tuple(noise.variance_map(img, lay.exptime_s)
                     for img, lay in zip(noiseless_images, self.layouts))

    def observe(self, source: Source, key):
        """(noisy images, noiseless images, variances), one of each per band."""
        clean = self.noiseless(source)
        # each band's key from its filter name, not its position: a band's noise is the
        # same whichever other bands are simulated with it (--bands)
        noisy = tuple(
            noise.add_photon_noise(jax.random.fold_in(key, noise.band_key(lay.name)), img,
                                   lay.exptime_s, self.accuracy.gaussian_noise_above)
            for img, lay in zip(clean, self.layouts))
        return noisy, clean, self.variances(clean)


# ------------------------------------------------------------------ building


def _psf_kernel_for(band: Band, sub_pixel_arcsec: float):
    """The band's PSF as an odd kernel on the sub-grid: point samples of an effective PSF
    (it already holds the pixel integral), area averages of an optical one."""
    from .psf import PSF, resample_psf, sample_psf
    psf = PSF(array=np.asarray(band.psf, float) / np.sum(band.psf),
              pixel_arcsec=float(band.psf_pixel_arcsec), effective=bool(band.psf_effective),
              source="model")
    to_grid = sample_psf if band.psf_effective else resample_psf
    return convolve.check_kernel(to_grid(psf, sub_pixel_arcsec), f"bands[{band.name}].psf")


def require_float64_mode(dtype):
    """ConfigError unless JAX's 64-bit mode is on when `dtype` is float64 (JAX would
    otherwise compute in float32 without saying so)."""
    if jnp.dtype(dtype) == jnp.float64 and not jax.config.read("jax_enable_x64"):
        raise ConfigError("render.dtype", "float64",
                          'JAX 64-bit mode on: call clumpylen_jax.enable_float64() first (the '
                          'clumpylen command does), or use render.dtype = "float32"')


def build_model(source: Source, bands, *, lens=None, field_arcsec=None,
                lens_pixel_arcsec: float = D.LENS_PIXEL_ARCSEC, source_pixel_arcsec: float = D.SOURCE_PIXEL_ARCSEC,
                accuracy: Accuracy = Accuracy(), dtype=jnp.float64,
                ray_cache=None, grids=None) -> SceneModel:
    """Make the forward model of a scene (static decisions happen here, once).

    source: a Source with concrete parameters (sets the traced region and stamp sizes;
        the model then accepts any source of the same structure).
    bands: sequence of `Band`.  lens: an object with ``deflection(theta1, theta2)`` or None.
    field_arcsec: ((x0, x1), (y0, y1)) lens-plane field (θ, arcsec) for lensed scenes,
        or the image field (β) for unlensed ones; None: found from the source's extent.
    lens_pixel_arcsec: high-resolution lens-plane pixel.  source_pixel_arcsec: pixel of the
        source-plane grid holding the clumps (grid mode).
    ray_cache: folder keeping traced lens-plane corners between runs (`raycache`), or None.
    grids: one `Grid` per band (detector pixels as observed data place them: each band its
        own scale and offset), overriding field_arcsec; its pixel must be the band's.
    """
    accuracy.validate()
    source.validate()
    bands = [b.validate(f"bands[{i}]") for i, b in enumerate(bands)]
    if not bands:
        raise ConfigError("bands", "[]", "at least one band")
    require(lens_pixel_arcsec > 0, "render.lens_pixel_arcsec", lens_pixel_arcsec,
            "a positive pixel scale (arcsec)")
    require(source_pixel_arcsec > 0, "render.source_pixel_arcsec", source_pixel_arcsec,
            "a positive pixel scale (arcsec)")
    dtype = jnp.dtype(dtype)
    require_float64_mode(dtype)
    center, radius = source_extent(source, accuracy.source_flux_fraction,
                                   accuracy.stamp_flux_fraction)
    has_clumps = source.clumps is not None and source.clumps.count > 0

    layouts, psf_fts, unlensed_index = [], [], []
    psf_margin = 0.0
    for band in bands:
        if band.psf is not None:
            psf_margin = max(psf_margin, 0.5 * max(np.shape(band.psf)) * band.psf_pixel_arcsec)
    if grids is not None:
        require(len(grids) == len(bands) and all(
            abs(g.pixel_arcsec - b.pixel_arcsec) <= 1e-9 * b.pixel_arcsec
            for g, b in zip(grids, bands)), "grids", grids, "one Grid per band, of its pixel")
    for k, band in enumerate(bands):
        if grids is not None:
            grid = grids[k]
        elif field_arcsec is not None:
            grid = Grid.covering(field_arcsec[0], field_arcsec[1], band.pixel_arcsec)
        elif lens is None:
            grid = Grid.centered(center, radius + psf_margin, band.pixel_arcsec)
        else:
            raise ConfigError("render.field_arcsec", None,
                              "a lens-plane field for a lensed scene (the scene layer finds one)")
        s = accuracy.psf_oversampling if band.psf is not None else 1
        if band.psf is None and lens is None:
            s = 1
        sub = band.pixel_arcsec / s
        kernel = _psf_kernel_for(band, sub) if band.psf is not None else None
        groups = _unlensed_clump_groups(source, sub, accuracy) if lens is None else []
        unlensed_index.append(tuple(jnp.asarray(i) for _, i in groups))
        layouts.append(_BandLayout(band.name, grid, s, float(band.exptime_s),
                                   float(band.sky_counts_per_s),
                                   None if kernel is None else kernel.shape,
                                   bool(band.psf_effective), tuple(key for key, _ in groups),
                                   _host_strips(source, sub, accuracy.exact_core)
                                   if lens is None and accuracy.thin_strip else (False, False)))
        psf_fts.append(None if kernel is None else
                       convolve.kernel_rfft(kernel, grid.subdivided(s).shape, dtype))

    if lens is None:
        return SceneModel(tuple(layouts), accuracy, False, None, None, (), (), None, None,
                          tuple(psf_fts), (), None, None, None, None, None, None, None,
                          tuple(unlensed_index))

    # lens plane: one high-resolution grid over the union of the band fields
    x_lo = min(l.grid.x_range[0] for l in layouts)
    x_hi = max(l.grid.x_range[1] for l in layouts)
    y_lo = min(l.grid.y_range[0] for l in layouts)
    y_hi = max(l.grid.y_range[1] for l in layouts)
    hr = Grid.covering((x_lo, x_hi), (y_lo, y_hi), lens_pixel_arcsec)
    corner_b1, corner_b2 = raycache.traced_corners(lens, hr, trace_corners, ray_cache)
    rows, cols, footprint_index = traced_pixels(corner_b1, corner_b2, center, radius)
    if rows.size == 0:
        raise ConfigError("render.field_arcsec", field_arcsec,
                          "a lens-plane field where the source lands (no pixel of it maps "
                          f"within {radius:.3g}\" of the source centre {tuple(center)})")
    host_core = _host_core_layout(source, corner_b1, corner_b2, rows, cols, footprint_index,
                                  accuracy, dtype)
    n_clumps = source.clumps.count if has_clumps else 0
    traced_clumps = np.arange(n_clumps)
    lin = dict(lin_images=None)
    if has_clumps and accuracy.source_mode == "hybrid" and accuracy.linearise_tolerance > 0:
        tol = accuracy.linearise_tolerance * min(l.grid.pixel_arcsec for l in layouts)
        lin_mask, images = _linearise_clumps(source.clumps, corner_b1, corner_b2, hr, rows, cols,
                                             footprint_index, accuracy, tol, dtype)
        traced_clumps = np.nonzero(~lin_mask)[0]
        lin = _linearised_layout(source, images, layouts, hr, accuracy)
    # rays: every traced pixel when every ray needs a value; otherwise only the pixels
    # whose footprint reaches a ray-traced clump's stamp
    ray_pixels = np.arange(rows.size)
    if accuracy.source_mode != "analytic" and not accuracy.host_subsampling:
        cl = source.clumps
        r_stamp = (_radius_enclosing(accuracy.stamp_flux_fraction,
                                     np.asarray(cl.re_arcsec, float)[traced_clumps],
                                     np.asarray(cl.n, float)[traced_clumps])
                   if traced_clumps.size else np.zeros(0))
        _, pix = pixels_near(corner_b1, corner_b2, rows, cols,
                             np.asarray(cl.center_arcsec, float)[traced_clumps]
                             if traced_clumps.size else np.zeros((0, 2)), r_stamp,
                             footprint_index)
        ray_pixels = np.unique(pix)
    sel = ray_pixels
    ray_window = ((int(rows[sel].min()), int(rows[sel].max()) + 1,
                   int(cols[sel].min()), int(cols[sel].max()) + 1) if sel.size else (0, 0, 0, 0))
    offs, wts = gauss_legendre_offsets(accuracy.lens_subsampling)
    ox, oy = np.meshgrid(offs, offs)
    wxy = np.outer(wts, wts).ravel()
    b1, b2 = rays_in_pixels(corner_b1, corner_b2, rows[sel], cols[sel], (ox.ravel(), oy.ravel()))
    c1, c2 = rays_in_pixels(corner_b1, corner_b2, rows, cols, (np.zeros(1), np.zeros(1)))
    del corner_b1, corner_b2
    rebin_ops = tuple(tuple((jnp.asarray(t), jnp.asarray(w, dtype),
                             None if m is None else jnp.asarray(m, dtype)) for t, w, m in
                            sparse_rebin_operators(hr, l.grid.subdivided(l.oversampling)))
                      for l in layouts)

    clump_grid, groups = None, []
    if traced_clumps.size and accuracy.source_mode in ("grid", "hybrid"):
        cl = source.clumps
        sub = jax.tree_util.tree_map(lambda a: np.asarray(a)[traced_clumps], cl)
        groups = [(side, traced_clumps[idx])
                  for side, idx in render.stamp_groups(sub.re_arcsec, sub.n, source_pixel_arcsec,
                                                       flux_fraction=accuracy.stamp_flux_fraction)]
        cc = np.asarray(cl.center_arcsec, float)[traced_clumps]
        half = (max(side for side, _ in groups) / 2 + 2) * source_pixel_arcsec
        clump_grid = Grid.covering((cc[:, 0].min() - half, cc[:, 0].max() + half),
                                   (cc[:, 1].min() - half, cc[:, 1].max() + half),
                                   source_pixel_arcsec)
    tile_layout, slot_map = None, None
    if clump_grid is not None:
        # store only the tiles of the bordered grid that some ray reads
        p = clump_grid.pixel_arcsec
        tile_layout, slot_map = tiles.active_tiles((b1 - clump_grid.x0_arcsec) / p + 1.0,
                                                   (b2 - clump_grid.y0_arcsec) / p + 1.0,
                                                   (clump_grid.ny + 2, clump_grid.nx + 2))
        slot_map = jnp.asarray(slot_map)
    return SceneModel(tuple(layouts), accuracy, True, hr, clump_grid,
                      tuple(side for side, _ in groups), tuple(jnp.asarray(i) for _, i in groups),
                      slot_map, tile_layout, tuple(psf_fts),
                      rebin_ops, jnp.asarray(rows), jnp.asarray(cols),
                      jnp.asarray(b1, dtype), jnp.asarray(b2, dtype), jnp.asarray(wxy, dtype),
                      jnp.asarray(c1[:, 0], dtype), jnp.asarray(c2[:, 0], dtype),
                      ray_rows=jnp.asarray(rows[sel]), ray_cols=jnp.asarray(cols[sel]),
                      ray_window=ray_window, **lin, **host_core)


_HOST_CORE_REACHES = 4     # × exact_core: footprint reaches from a host centre integrated exactly
_HOST_CORE_SPLIT = 2       # each such pixel as 2 × 2 sub-pixels, each with its own footprint
_HOST_CORE_DET_CHANGE = 0.01   # largest relative change of |μ| across a sub-pixel integrated exactly


def _host_core_layout(source: Source, corner_b1, corner_b2, rows, cols, footprint_index,
                      accuracy: Accuracy, dtype):
    """The traced pixels whose host light is integrated exactly (`SceneModel._exact_host_core`).

    Those whose source-plane footprint lies within 4·exact_core of its own reaches from a
    host component's centre, where a sample is off by % near a cusp (the residual total
    flux error of an n = 4 host of R_e 4 lens pixels behind a mass sheet: 5e-4 with
    2·exact_core, 2e-4 with 4, 1.5e-4 with 6, +3 % with none), and where the lens map is
    linear enough. Each is split into 2 × 2 sub-pixels whose footprints (corners by
    bilinear interpolation of the pixel's traced corners) are integrated exactly and
    divided by their areas: the mean |dθ/dβ| of a sub-pixel stands for the local one.
    That holds where |μ| changes by < 1 % across each sub-pixel; near a critical curve it
    changes by tens of % across a pixel, and a sample at the pixel's centre is the better
    estimate there (an n = 1 host by an SIS caustic lost 3e-4 of its flux otherwise).
    The 4 × 4 split changed a compact host behind an SIS by 1e-4 and cost 4× more.
    """
    comps = [{k: np.asarray(v, float) for k, v in kw.items()} for kw in
             ([render._sersic_kw(source.bulge)] if source.bulge is not None else [])
             + ([render._disk_kw(source.disk)] if source.disk is not None else [])]
    if not comps or accuracy.exact_core == 0:
        return {}
    m1, m2, reach = footprint_index.m1, footprint_index.m2, footprint_index.reach
    near = np.zeros(m1.shape, bool)
    for kw in comps:
        near |= (np.hypot(m1 - kw["center1"], m2 - kw["center2"])
                 < _HOST_CORE_REACHES * accuracy.exact_core * reach)
    idx = np.nonzero(near)[0]
    if idx.size == 0:
        return {}
    r, k = rows[idx], cols[idx]
    # the pixel's corners (lower left, lower right, upper right, upper left), then the
    # sub-pixels' corners by bilinear interpolation: [K, split², 4]
    ll, lr, ur, ul = ((r, k), (r, k + 1), (r + 1, k + 1), (r + 1, k))
    f = np.arange(_HOST_CORE_SPLIT + 1) / _HOST_CORE_SPLIT
    fy, fx = np.meshgrid(f, f, indexing="ij")

    def sub_corners(cb):
        a, b, c_, d = (cb[p][:, None, None] for p in (ll, lr, ur, ul))
        g = (a * (1 - fx) * (1 - fy) + b * fx * (1 - fy) + c_ * fx * fy + d * (1 - fx) * fy)
        return np.stack([g[:, :-1, :-1], g[:, :-1, 1:], g[:, 1:, 1:], g[:, 1:, :-1]],
                        -1).reshape(idx.size, -1, 4)

    v1, v2 = sub_corners(corner_b1), sub_corners(corner_b2)
    e1, e2 = np.roll(v1, -1, -1) - v1, np.roll(v2, -1, -1) - v2
    turn = e1 * np.roll(e2, -1, -1) - e2 * np.roll(e1, -1, -1)
    convex = np.all(turn > 0, -1) | np.all(turn < 0, -1)
    area = 0.5 * np.abs(np.sum(v1 * np.roll(v2, -1, -1) - np.roll(v1, -1, -1) * v2, -1))
    # |det| changes across a bilinear footprint by |w × e| along each edge e, with w its
    # twist v0 − v1 + v2 − v3: relative to the mean (the area), at most |w| Σ|e| / area
    twist = np.hypot(v1[..., 0] - v1[..., 1] + v1[..., 2] - v1[..., 3],
                     v2[..., 0] - v2[..., 1] + v2[..., 2] - v2[..., 3])
    edges = np.hypot(e1[..., 0], e2[..., 0]) + np.hypot(e1[..., 1], e2[..., 1])
    ok = convex & (area > 0) & (twist * edges < _HOST_CORE_DET_CHANGE * np.maximum(area, 1e-300))
    keep = np.all(ok, -1)
    if not np.any(keep):
        return {}
    origin = (float(comps[0]["center1"]), float(comps[0]["center2"]))
    return dict(host_core_index=jnp.asarray(idx[keep]),
                host_core_b1=jnp.asarray(v1[keep] - origin[0], dtype),
                host_core_b2=jnp.asarray(v2[keep] - origin[1], dtype),
                host_core_inv_area=jnp.asarray(1.0 / area[keep], dtype), host_core_origin=origin)


@jax.jit
def _footprint_mean_brightness(b1, b2, inv_area, kw):
    """Mean brightness of a unit-flux Sérsic over footprints [K, S, 4] split in S parts."""
    return jnp.mean(profiles.sersic_quad_flux_exact(b1, b2, flux=1.0, **kw) * inv_area, -1)


def _linearise_clumps(clumps, corner_b1, corner_b2, hr: Grid, rows, cols, footprint_index,
                      accuracy: Accuracy, tolerance_arcsec: float, dtype):
    """Which clumps the local linear lens map renders well, and their images.

    A clump is linearised when every image of its centre has a linearisation error
    (`linearisation_error` on its 99 %-light circle) below `tolerance_arcsec` and 8 points
    on the rim of its stamp have as many images as the centre (no caustic crosses it).
    Returns (mask [N], ClumpImages of the linearised clumps).
    """
    cc = np.asarray(clumps.center_arcsec, float)
    re = np.asarray(clumps.re_arcsec, float)
    n = np.asarray(clumps.n, float)
    N = re.size
    r99 = _radius_enclosing(0.99, re, n)
    r_stamp = _radius_enclosing(accuracy.stamp_flux_fraction, re, n)
    ang = np.linspace(0.0, 2 * np.pi, 8, endpoint=False)
    rim = cc[:, None, :] + r_stamp[:, None, None] * np.stack([np.cos(ang), np.sin(ang)], -1)
    pidx, theta, A = point_images(corner_b1, corner_b2, hr, rows, cols,
                                  np.concatenate([cc, rim.reshape(-1, 2)]),
                                  index=footprint_index)
    counts = np.bincount(pidx, minlength=9 * N)
    ok = np.all(counts[N:].reshape(N, 8) == counts[:N, None], axis=1)
    centre = pidx < N
    ci, theta, A = pidx[centre], theta[centre], A[centre]
    err = linearisation_error(corner_b1, corner_b2, hr, theta, A, cc[ci], r99[ci])
    bad = np.zeros(N, bool)
    np.logical_or.at(bad, ci, ~(err < tolerance_arcsec))
    ok &= ~bad
    keep = ok[ci]
    ci, theta, A = ci[keep], theta[keep], A[keep]
    samples, weights = _light_samples(cc, re, n, np.asarray(clumps.q, float),
                                      np.asarray(clumps.pa_rad, float), r_stamp)
    scale = light_averaged_flux_scale(corner_b1, corner_b2, hr, theta, A, cc[ci],
                                      samples[ci], weights[ci])
    images = ClumpImages(clump_index=jnp.asarray(ci), theta0=jnp.asarray(theta, dtype),
                         beta0=jnp.asarray(cc[ci], dtype), jacobian=jnp.asarray(A, dtype),
                         flux_scale=jnp.asarray(scale, dtype))
    return ok, images


def _light_samples(center, re, n, q, pa, r_max, radial: int = 10, angular: int = 16):
    """Points β ([N, radial·angular, 2], arcsec) and weights ([N, radial·angular], summing
    to 1) that integrate a smooth function over each clump's light.

    Radially Gauss–Laguerre in x = b (r/R_e)^{1/n}, where the light is x^{2n−1} e^{−x} dx
    (generalised Laguerre weight), points beyond r_max [N] (the stamp's radius) pulled in
    to it; in the elliptical angle (light is uniform in it) equal steps.
    """
    from scipy.special import gammaincinv, roots_genlaguerre
    N = re.size
    r = np.empty((N, radial))
    w = np.empty((N, radial))
    for nv in np.unique(n):
        at = n == nv
        x, wx = roots_genlaguerre(radial, 2 * nv - 1)
        b = gammaincinv(2 * nv, 0.5)
        r[at] = np.minimum(re[at, None] * (x / b) ** nv, r_max[at, None])
        w[at] = wx / wx.sum()
    phi = (np.arange(angular) + 0.5) * (2 * np.pi / angular)
    u = r[:, :, None] * np.cos(phi)
    v = (q[:, None, None] * r[:, :, None]) * np.sin(phi)
    c, s = np.cos(pa)[:, None, None], np.sin(pa)[:, None, None]
    x = center[:, 0, None, None] + c * u - s * v
    y = center[:, 1, None, None] + s * u + c * v
    weights = np.broadcast_to(w[:, :, None] / angular, u.shape).reshape(N, -1)
    return np.stack([x, y], -1).reshape(N, -1, 2), weights


def _linearised_layout(source: Source, images: ClumpImages, layouts, hr: Grid, accuracy):
    """SceneModel fields for linearised clump images: stamp groups per band sub-grid and on hr."""
    if images.count == 0:
        return dict(lin_images=None)
    lensed = jax.jit(lensed_clumps)(jax.tree_util.tree_map(lambda a: jnp.asarray(a, jnp.float64),
                                                  source.clumps),
                           jax.tree_util.tree_map(lambda a: jnp.asarray(a), images))
    re = np.asarray(lensed.re_arcsec)
    n = np.asarray(lensed.n)

    def groups(pixel):
        # (side, strip) groups: the exact strip for images with light beyond the core
        g = render.strip_groups(re, n, pixel, accuracy.exact_core,
                                flux_fraction=accuracy.stamp_flux_fraction)
        return tuple(k for k, _ in g), tuple(jnp.asarray(i) for _, i in g)

    per_pixel = {}
    sides, index = [], []
    for l in layouts:
        pix = l.grid.pixel_arcsec / l.oversampling
        if pix not in per_pixel:
            per_pixel[pix] = groups(pix)
        sides.append(per_pixel[pix][0])
        index.append(per_pixel[pix][1])
    hr_sides, hr_index = groups(hr.pixel_arcsec)
    return dict(lin_images=images, lin_stamp_sides=tuple(sides), lin_stamp_index=tuple(index),
                lin_hr_sides=hr_sides, lin_hr_index=hr_index)
