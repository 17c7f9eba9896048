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
import math
from typing import Optional

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from . import convolve, noise, profiles, render
from .errors import ConfigError, require
from .lensing.grid import bilinear_interpolate
from .pixels import Grid, bin_blocks, gauss_legendre_offsets, rebin, rebin_operators
from .source import Source


@dataclasses.dataclass(frozen=True)
class Accuracy:
    """Accuracy knobs. Presets in `ACCURACY_PRESETS`; benchmarks/ measure what each costs.

    lens_subsampling: Gauss–Legendre order per lens-plane pixel (rays per pixel = its square).
    source_order: Gauss–Legendre order per pixel when a profile is integrated on a grid.
    exact_core: side (pixels) of the block around each Sérsic centre integrated exactly.
    psf_oversampling: odd factor of the grid, finer than the detector, on which the PSF acts.
    source_mode: "grid" (clumps on a source-plane grid, bilinear at each ray) or "analytic"
        (every clump evaluated at every ray: the converged reference, cost rays × clumps).
    stamp_flux_fraction: light fraction of the largest clump its stamp must hold.
    source_flux_fraction: light fraction of each host component inside the traced region.
    gaussian_noise_above: expected counts above which noise is drawn as a Gaussian (None: never).
    """

    lens_subsampling: int = 3
    source_order: int = 3
    exact_core: int = 5
    psf_oversampling: int = 3
    source_mode: str = "grid"
    stamp_flux_fraction: float = 0.9999
    source_flux_fraction: float = 0.99
    gaussian_noise_above: Optional[float] = 1.0e4

    def validate(self, name="render.accuracy"):
        for key in ("lens_subsampling", "source_order", "psf_oversampling"):
            v = getattr(self, key)
            require(isinstance(v, (int, np.integer)) and 1 <= v <= 16, f"{name}.{key}", v,
                    "an integer in [1, 16]")
        require(self.psf_oversampling % 2 == 1, f"{name}.psf_oversampling",
                self.psf_oversampling, "an odd integer (detector centres on sub-pixel centres)")
        require(isinstance(self.exact_core, (int, np.integer)) and 0 <= self.exact_core <= 31,
                f"{name}.exact_core", self.exact_core, "an integer in [0, 31]")
        require(self.source_mode in ("grid", "analytic"), f"{name}.source_mode",
                self.source_mode, '"grid" or "analytic"')
        for key in ("stamp_flux_fraction", "source_flux_fraction"):
            v = getattr(self, key)
            require(0.5 <= v < 1, f"{name}.{key}", v, "a fraction in [0.5, 1)")
        return self


ACCURACY_PRESETS = {
    "fast": Accuracy(lens_subsampling=1, source_order=2, exact_core=3, psf_oversampling=1,
                     stamp_flux_fraction=0.999, source_flux_fraction=0.98),
    "default": Accuracy(),
    "high": Accuracy(lens_subsampling=5, source_order=5, exact_core=7, psf_oversampling=5,
                     stamp_flux_fraction=0.99999, source_flux_fraction=0.999),
}


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
    stamp: int             # clump stamp side on the sub-grid (unlensed models)


# ------------------------------------------------------------------ static helpers


def _radius_enclosing(fraction, re_arcsec, n):
    """Major-axis radius holding `fraction` of a Sérsic's light (numpy; build-time only)."""
    from scipy.special import gammaincinv
    n = np.asarray(n, float)
    return np.asarray(re_arcsec, float) * (gammaincinv(2 * n, fraction)
                                           / gammaincinv(2 * n, 0.5)) ** n


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


def _clump_stamp(source: Source, pixel_arcsec: float, fraction: float) -> int:
    cl = source.clumps
    if cl is None or cl.count == 0:
        return 0
    return render.stamp_size(float(np.max(cl.re_arcsec)), float(np.max(cl.n)), pixel_arcsec,
                             flux_fraction=fraction)


def _trace_in_chunks(lens, theta1, theta2, chunk=1 << 20):
    """β of rays θ (numpy, flat), computed with the lens in float64 by chunks."""
    out1 = np.empty_like(theta1)
    out2 = np.empty_like(theta2)
    f = jax.jit(lambda a, b: lens.deflection(a, b))
    for s in range(0, theta1.size, chunk):
        a1, a2 = f(jnp.asarray(theta1[s:s + chunk]), jnp.asarray(theta2[s:s + chunk]))
        out1[s:s + chunk] = theta1[s:s + chunk] - np.asarray(a1)
        out2[s:s + chunk] = theta2[s:s + chunk] - np.asarray(a2)
    if not (np.all(np.isfinite(out1)) and np.all(np.isfinite(out2))):
        raise ConfigError("lens", "non-finite deflection in the traced field",
                          "a lens with finite deflections over the field")
    return out1, out2


def traced_pixels(lens, hr_grid: Grid, center, radius):
    """Rows and columns of lens-plane pixels whose light can come from the source disc.

    A pixel is traced when the disc (center, radius) comes within 1.5 pixel
    footprints of its centre's β; the footprint is the largest β step to a
    neighbouring pixel, so that thin, highly magnified images are not missed.
    """
    xc, yc = np.meshgrid(hr_grid.x_centers(), hr_grid.y_centers())
    b1, b2 = _trace_in_chunks(lens, xc.ravel(), yc.ravel())
    b1 = b1.reshape(hr_grid.shape)
    b2 = b2.reshape(hr_grid.shape)
    step = np.zeros(hr_grid.shape)
    for axis in (0, 1):
        d = np.hypot(np.diff(b1, axis=axis), np.diff(b2, axis=axis))
        pad = [(0, 0), (0, 0)]
        pad[axis] = (0, 1)
        step = np.maximum(step, np.pad(d, pad, mode="edge"))
        pad[axis] = (1, 0)
        step = np.maximum(step, np.pad(d, pad, mode="edge"))
    dist = np.hypot(b1 - center[0], b2 - center[1])
    rows, cols = np.nonzero(dist < radius + 1.5 * step)
    return rows, cols


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
    clump_stamp: int = eqx.field(static=True)
    psf_fts: tuple
    rebin_ops: tuple
    traced_rows: Optional[jnp.ndarray]
    traced_cols: Optional[jnp.ndarray]
    beta1: Optional[jnp.ndarray]
    beta2: Optional[jnp.ndarray]
    ray_weights: Optional[jnp.ndarray]

    @property
    def band_names(self):
        return tuple(b.name for b in self.layouts)

    # -- lens plane ------------------------------------------------------------

    def _clump_source_grids(self, source: Source):
        """Clump surface brightness on the source-plane grid, per band: [B, ny, nx]."""
        cl = source.clumps
        stamps, i0, j0 = render.clump_stamps(cl, self.clump_grid, self.clump_stamp,
                                             order=self.accuracy.source_order,
                                             core=self.accuracy.exact_core)
        flux = render.scatter_stamps(stamps, i0, j0, cl.flux, self.clump_grid)
        return flux / self.clump_grid.pixel_arcsec**2

    def traced_values(self, source: Source):
        """Flux [B, M] of every traced lens-plane pixel (counts/s)."""
        b1, b2 = self.beta1, self.beta2
        w = self.ray_weights
        nb = _n_bands(source)
        dtype = b1.dtype
        total = jnp.zeros((nb, b1.shape[0]), dtype)
        if source.bulge is not None:
            s = source.bulge
            u = render.sersic_unit_brightness(b1, b2, **render._sersic_kw(s)) @ w
            total = total + s.flux[:, None] * u[None, :]
        if source.disk is not None:
            d = source.disk
            u = render.disk_unit_brightness(d, b1, b2) @ w
            total = total + d.sersic.flux[:, None] * u[None, :]
        if source.clumps is not None and source.clumps.count > 0:
            if self.accuracy.source_mode == "analytic":
                total = total + render.clumps_brightness(source.clumps, b1, b2) @ w
            else:
                grids = self._clump_source_grids(source)
                g = self.clump_grid
                x = (b1 - g.x0_arcsec) / g.pixel_arcsec + 1.0  # +1: the zero border
                y = (b2 - g.y0_arcsec) / g.pixel_arcsec + 1.0
                padded = jnp.pad(grids, ((0, 0), (1, 1), (1, 1)))

                def one_band(img):
                    return bilinear_interpolate(img, x, y) @ w

                total = total + jax.lax.map(one_band, padded)
        return total * self.hr_grid.pixel_arcsec**2

    def source_magnification_map(self):
        """Lens-plane area landing on each clump-grid pixel / that pixel's area (grid mode).

        The adjoint of the ray-tracing interpolation applied to ones: Σ over a
        clump's stamp of this map × its light is exactly the magnification the
        model gives that clump within the field.
        """
        g = self.clump_grid
        dtype = self.beta1.dtype
        x = (self.beta1 - g.x0_arcsec) / g.pixel_arcsec + 1.0
        y = (self.beta2 - g.y0_arcsec) / g.pixel_arcsec + 1.0

        def lensed_total(img):
            return jnp.sum(bilinear_interpolate(img, x, y) @ self.ray_weights)

        zeros = jnp.zeros((g.ny + 2, g.nx + 2), dtype)
        grad = jax.grad(lensed_total)(zeros)[1:-1, 1:-1]
        return grad * (self.hr_grid.pixel_arcsec / g.pixel_arcsec) ** 2

    def clump_magnifications(self, source: Source):
        """Magnification [N] of each clump within the field (light-weighted over its stamp)."""
        cl = source.clumps
        mu = self.source_magnification_map()
        stamps, i0, j0 = render.clump_stamps(cl, self.clump_grid, self.clump_stamp,
                                             order=self.accuracy.source_order,
                                             core=self.accuracy.exact_core)
        k = jnp.arange(self.clump_stamp)
        rows = jnp.clip(j0[:, None, None] + k[None, :, None], 0, self.clump_grid.ny - 1)
        cols = jnp.clip(i0[:, None, None] + k[None, None, :], 0, self.clump_grid.nx - 1)
        return jnp.sum(stamps * mu[rows, cols], axis=(1, 2)) / jnp.sum(stamps, axis=(1, 2))

    def lens_plane(self, source: Source):
        """High-resolution lens-plane images [B, ny, nx], counts/s per lens-plane pixel."""
        vals = self.traced_values(source)
        img = jnp.zeros((vals.shape[0],) + self.hr_grid.shape, vals.dtype)
        return img.at[:, self.traced_rows, self.traced_cols].set(vals)

    # -- detector ----------------------------------------------------------------

    def _unlensed_subgrid_image(self, source: Source, k: int, lay: _BandLayout, cache):
        """Pixel-integrated source light on band k's sub-grid (unlensed scenes)."""
        g = lay.grid.subdivided(lay.oversampling)
        acc = self.accuracy
        key = ("host", g)
        if key not in cache:
            parts = []
            if source.bulge is not None:
                parts.append((source.bulge.flux,
                              render.sersic_image(source.bulge, g, order=acc.source_order,
                                                  core=acc.exact_core)))
            if source.disk is not None:
                parts.append((source.disk.sersic.flux,
                              render.disk_image(source.disk, g, order=acc.source_order,
                                                core=acc.exact_core)))
            cache[key] = parts
        img = jnp.zeros(g.shape, jnp.result_type(*[p[1] for p in cache[key]])
                        if cache[key] else source.clumps.flux.dtype)
        for flux, unit in cache[key]:
            img = img + flux[k] * unit
        cl = source.clumps
        if cl is not None and cl.count > 0:
            skey = ("stamps", g, lay.stamp)
            if skey not in cache:
                cache[skey] = render.clump_stamps(cl, g, lay.stamp, order=acc.source_order,
                                                  core=acc.exact_core)
            stamps, i0, j0 = cache[skey]
            img = img + render.scatter_stamps(stamps, i0, j0, cl.flux[:, k:k + 1], g)[0]
        return img

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
            hr = self.lens_plane(source)
            for k, lay in enumerate(self.layouts):
                wy, wx = self.rebin_ops[k]
                out.append(self._observe_subgrid(rebin(hr[k], wy, wx), k, lay))
        else:
            cache = {}
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
        noisy = tuple(
            noise.add_photon_noise(jax.random.fold_in(key, k), img, lay.exptime_s,
                                   self.accuracy.gaussian_noise_above)
            for k, (img, lay) in enumerate(zip(clean, self.layouts)))
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


def build_model(source: Source, bands, *, lens=None, field_arcsec=None,
                lens_pixel_arcsec: float = 0.0025, source_pixel_arcsec: float = 0.00025,
                accuracy: Accuracy = Accuracy(), dtype=jnp.float64) -> SceneModel:
    """Make the forward model of a scene (static decisions happen here, once).

    source: a Source with concrete parameters (sets the traced region and stamp sizes;
        the model then accepts any source of the same structure).
    bands: sequence of `Band`.  lens: an object with ``deflection(theta1, theta2)`` or None.
    field_arcsec: ((x0, x1), (y0, y1)) lens-plane field (θ, arcsec) for lensed scenes,
        or the image field (β) for unlensed ones; None: found from the source's extent.
    lens_pixel_arcsec: high-resolution lens-plane pixel.  source_pixel_arcsec: pixel of the
        source-plane grid holding the clumps (grid mode).
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
    center, radius = source_extent(source, accuracy.source_flux_fraction,
                                   accuracy.stamp_flux_fraction)
    has_clumps = source.clumps is not None and source.clumps.count > 0

    layouts, psf_fts = [], []
    psf_margin = 0.0
    for band in bands:
        if band.psf is not None:
            psf_margin = max(psf_margin, 0.5 * max(np.shape(band.psf)) * band.psf_pixel_arcsec)
    for band in bands:
        if field_arcsec is not None:
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
        stamp = _clump_stamp(source, sub, accuracy.stamp_flux_fraction) if lens is None else 0
        layouts.append(_BandLayout(band.name, grid, s, float(band.exptime_s),
                                   float(band.sky_counts_per_s),
                                   None if kernel is None else kernel.shape,
                                   bool(band.psf_effective), stamp))
        psf_fts.append(None if kernel is None else
                       convolve.kernel_rfft(kernel, grid.subdivided(s).shape, dtype))

    if lens is None:
        return SceneModel(tuple(layouts), accuracy, False, None, None, 0, tuple(psf_fts), (),
                          None, None, None, None, None)

    # lens plane: one high-resolution grid over the union of the band fields
    x_lo = min(l.grid.x_range[0] for l in layouts)
    x_hi = max(l.grid.x_range[1] for l in layouts)
    y_lo = min(l.grid.y_range[0] for l in layouts)
    y_hi = max(l.grid.y_range[1] for l in layouts)
    hr = Grid.covering((x_lo, x_hi), (y_lo, y_hi), lens_pixel_arcsec)
    rows, cols = traced_pixels(lens, hr, center, radius)
    if rows.size == 0:
        raise ConfigError("render.field_arcsec", field_arcsec,
                          "a lens-plane field where the source lands (no pixel of it maps "
                          f"within {radius:.3g}\" of the source centre {tuple(center)})")
    order = accuracy.lens_subsampling
    offs, wts = gauss_legendre_offsets(order)
    ox, oy = np.meshgrid(offs, offs)
    wxy = np.outer(wts, wts).ravel()
    t1 = hr.x_centers()[cols][:, None] + ox.ravel()[None, :] * hr.pixel_arcsec
    t2 = hr.y_centers()[rows][:, None] + oy.ravel()[None, :] * hr.pixel_arcsec
    b1, b2 = _trace_in_chunks(lens, t1.ravel(), t2.ravel())
    rebin_ops = tuple(tuple(jnp.asarray(w, dtype) for w in
                            rebin_operators(hr, l.grid.subdivided(l.oversampling)))
                      for l in layouts)

    clump_grid, stamp = None, 0
    if has_clumps and accuracy.source_mode == "grid":
        stamp = _clump_stamp(source, source_pixel_arcsec, accuracy.stamp_flux_fraction)
        cc = np.asarray(source.clumps.center_arcsec, float)
        half = (stamp / 2 + 2) * source_pixel_arcsec
        clump_grid = Grid.covering((cc[:, 0].min() - half, cc[:, 0].max() + half),
                                   (cc[:, 1].min() - half, cc[:, 1].max() + half),
                                   source_pixel_arcsec)
    return SceneModel(tuple(layouts), accuracy, True, hr, clump_grid, stamp, tuple(psf_fts),
                      rebin_ops, jnp.asarray(rows), jnp.asarray(cols),
                      jnp.asarray(b1.reshape(t1.shape), dtype),
                      jnp.asarray(b2.reshape(t2.shape), dtype), jnp.asarray(wxy, dtype))
