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

from . import convolve, noise, render
from .errors import ConfigError, require
from .lensing.grid import bilinear_interpolate, bilinear_interpolate_channels
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
    host_subsampling: evaluate host components at every ray (True) or at each lens-plane
        pixel's centre only (False: they vary little across a pixel's source-plane footprint).
    """

    lens_subsampling: int = 4
    source_order: int = 3
    exact_core: int = 5
    psf_oversampling: int = 5
    source_mode: str = "grid"
    stamp_flux_fraction: float = 0.9999
    source_flux_fraction: float = 0.99
    gaussian_noise_above: Optional[float] = 1.0e4
    host_subsampling: bool = False

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


# Chosen from benchmarks/results/accuracy.md (error against time, measured in one run):
# the lens-plane ray density dominates the clump flux error (per-clump error with 2.5 mas
# lens pixels: 2–9 % at 3 rays per axis, 0.3–3 % at 4, 0.01–1 % at 6); the exact core
# is what makes sub-pixel Sérsics converge; PSF oversampling 3/5/7 gives 10/3/1.6 σ.
ACCURACY_PRESETS = {
    "fast": Accuracy(lens_subsampling=2, source_order=2, exact_core=5, psf_oversampling=3,
                     stamp_flux_fraction=0.999, source_flux_fraction=0.98),
    "default": Accuracy(lens_subsampling=4, source_order=3, exact_core=5, psf_oversampling=5),
    "high": Accuracy(lens_subsampling=8, source_order=4, exact_core=7, psf_oversampling=7,
                     source_mode="analytic", stamp_flux_fraction=0.99999,
                     source_flux_fraction=0.999, host_subsampling=True),
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
    stamp_sides: tuple     # clump stamp sides on the sub-grid (unlensed models)


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


def _clump_groups_for(source: Source, pixel_arcsec: float, fraction: float):
    """Stamp groups [(side, indices)] of the source's clumps on a grid of this pixel."""
    cl = source.clumps
    if cl is None or cl.count == 0:
        return []
    return render.stamp_groups(cl.re_arcsec, cl.n, pixel_arcsec, flux_fraction=fraction)


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
    """Rows and columns of lens-plane pixels whose light can come from the source disc.

    A pixel is traced when the disc (center, radius) comes within its
    source-plane footprint: the distance from the mean of its corners' β to the
    centre is below radius + the largest corner distance from that mean, so
    that thin, highly magnified images are not missed.
    """
    quads = [(slice(0, -1), slice(0, -1)), (slice(0, -1), slice(1, None)),
             (slice(1, None), slice(0, -1)), (slice(1, None), slice(1, None))]
    m1 = sum(corner_b1[q] for q in quads) / 4
    m2 = sum(corner_b2[q] for q in quads) / 4
    reach = np.max([np.hypot(corner_b1[q] - m1, corner_b2[q] - m2) for q in quads], axis=0)
    dist = np.hypot(m1 - center[0], m2 - center[1])
    rows, cols = np.nonzero(dist < radius + 1.01 * reach)
    return rows, cols


def rays_in_pixels(corner_b1, corner_b2, rows, cols, offsets):
    """β of rays at sub-pixel offsets (in (−½, ½) pixel) of the given pixels: [M, R] each.

    Bilinear interpolation of the corners' β: the lens mapping is smooth on the
    scale of a lens-plane pixel, and each pixel needs one deflection per corner
    instead of one per ray.
    """
    ox, oy = offsets
    fx = (ox + 0.5)[None, :]
    fy = (oy + 0.5)[None, :]
    out = []
    for b in (corner_b1, corner_b2):
        v00 = b[rows, cols][:, None]
        v01 = b[rows, cols + 1][:, None]
        v10 = b[rows + 1, cols][:, None]
        v11 = b[rows + 1, cols + 1][:, None]
        out.append(v00 * (1 - fx) * (1 - fy) + v01 * fx * (1 - fy) + v10 * (1 - fx) * fy
                   + v11 * fx * fy)
    return out


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

    @property
    def band_names(self):
        return tuple(b.name for b in self.layouts)

    # -- lens plane ------------------------------------------------------------

    def _clump_groups(self):
        return tuple(zip(self.clump_stamp_sides, self.clump_stamp_index))

    def _clump_source_grid(self, source: Source, flux):
        """Clump surface brightness [ny, nx, C] of C bands on the source-plane grid, zero border."""
        img = render.clumps_image(source.clumps, self.clump_grid, self._clump_groups(), flux,
                                  order=self.accuracy.source_order, core=self.accuracy.exact_core)
        return jnp.pad(img / self.clump_grid.pixel_arcsec**2, ((1, 1), (1, 1), (0, 0)))

    def _band_chunk(self, nb: int) -> int:
        """Bands per source-plane grid: as many as fit in ~0.5 GB."""
        npix = (self.clump_grid.nx + 2) * (self.clump_grid.ny + 2)
        return int(max(1, min(nb, 5.0e8 // (8 * npix))))

    def _clump_values(self, source: Source, nb: int, block: int = 1 << 17):
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

        def blocks(b, origin):
            x = (b - origin) / g.pixel_arcsec + 1.0  # +1: the zero border
            return jnp.pad(x, ((0, pad), (0, 0))).reshape(n_blocks, block, -1)

        xs = blocks(self.beta1, g.x0_arcsec)
        ys = blocks(self.beta2, g.y0_arcsec)

        def one_chunk(f):
            grid = self._clump_source_grid(source, f)

            def one_block(xy):
                return jnp.einsum("mrc,r->mc", bilinear_interpolate_channels(grid, *xy), w)

            return jax.lax.map(one_block, (xs, ys)).reshape(n_blocks * block, step)[:m]

        vals = jax.lax.map(one_chunk, flux)                      # [chunks, M, step]
        return vals.transpose(0, 2, 1).reshape(n_chunks * step, m)[:nb]

    def traced_values(self, source: Source):
        """Flux [B, M] of every traced lens-plane pixel (counts/s)."""
        b1, b2 = self.beta1, self.beta2
        w = self.ray_weights
        nb = _n_bands(source)
        dtype = b1.dtype
        total = jnp.zeros((nb, b1.shape[0]), dtype)
        # host components vary slowly across a lens-plane pixel's footprint: one ray per
        # pixel (its centre) unless host_subsampling asks for all of them
        if self.accuracy.host_subsampling:
            h1, h2, hw = b1, b2, w
        else:
            h1, h2, hw = self.beta1_center[:, None], self.beta2_center[:, None], jnp.ones(1, dtype)
        if source.bulge is not None:
            s = source.bulge
            u = render.sersic_unit_brightness(h1, h2, **render._sersic_kw(s)) @ hw
            total = total + s.flux[:, None] * u[None, :]
        if source.disk is not None:
            d = source.disk
            u = render.disk_unit_brightness(d, h1, h2) @ hw
            total = total + d.sersic.flux[:, None] * u[None, :]
        if source.clumps is not None and source.clumps.count > 0:
            if self.accuracy.source_mode == "analytic":
                total = total + render.clumps_brightness(source.clumps, b1, b2) @ w
            else:
                total = total + self._clump_values(source, nb)
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
        out = jnp.zeros(cl.count, mu.dtype)
        for side, idx in self._clump_groups():
            sub = jax.tree_util.tree_map(lambda a: a[idx], cl)
            stamps, i0, j0 = render.clump_stamps(sub, self.clump_grid, side,
                                                 order=self.accuracy.source_order,
                                                 core=self.accuracy.exact_core)
            k = jnp.arange(side)
            rows = jnp.clip(j0[:, None, None] + k[None, :, None], 0, self.clump_grid.ny - 1)
            cols = jnp.clip(i0[:, None, None] + k[None, None, :], 0, self.clump_grid.nx - 1)
            mags = jnp.sum(stamps * mu[rows, cols], axis=(1, 2)) / jnp.sum(stamps, axis=(1, 2))
            out = out.at[idx].set(mags)
        return out

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
            ckey = ("clumps", g)
            if ckey not in cache:
                # every band at once: bands on the same grid share the stamps
                groups = tuple(zip(lay.stamp_sides, self.stamp_index_unlensed[k]))
                cache[ckey] = render.clumps_image(cl, g, groups, cl.flux,
                                                  order=acc.source_order, core=acc.exact_core)
            img = img + cache[ckey][..., k]
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

    layouts, psf_fts, unlensed_index = [], [], []
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
        groups = (_clump_groups_for(source, sub, accuracy.stamp_flux_fraction)
                  if lens is None else [])
        unlensed_index.append(tuple(jnp.asarray(i) for _, i in groups))
        layouts.append(_BandLayout(band.name, grid, s, float(band.exptime_s),
                                   float(band.sky_counts_per_s),
                                   None if kernel is None else kernel.shape,
                                   bool(band.psf_effective), tuple(side for side, _ in groups)))
        psf_fts.append(None if kernel is None else
                       convolve.kernel_rfft(kernel, grid.subdivided(s).shape, dtype))

    if lens is None:
        return SceneModel(tuple(layouts), accuracy, False, None, None, (), (), tuple(psf_fts), (),
                          None, None, None, None, None, None, None, tuple(unlensed_index))

    # lens plane: one high-resolution grid over the union of the band fields
    x_lo = min(l.grid.x_range[0] for l in layouts)
    x_hi = max(l.grid.x_range[1] for l in layouts)
    y_lo = min(l.grid.y_range[0] for l in layouts)
    y_hi = max(l.grid.y_range[1] for l in layouts)
    hr = Grid.covering((x_lo, x_hi), (y_lo, y_hi), lens_pixel_arcsec)
    corner_b1, corner_b2 = trace_corners(lens, hr)
    rows, cols = traced_pixels(corner_b1, corner_b2, center, radius)
    if rows.size == 0:
        raise ConfigError("render.field_arcsec", field_arcsec,
                          "a lens-plane field where the source lands (no pixel of it maps "
                          f"within {radius:.3g}\" of the source centre {tuple(center)})")
    offs, wts = gauss_legendre_offsets(accuracy.lens_subsampling)
    ox, oy = np.meshgrid(offs, offs)
    wxy = np.outer(wts, wts).ravel()
    b1, b2 = rays_in_pixels(corner_b1, corner_b2, rows, cols, (ox.ravel(), oy.ravel()))
    c1, c2 = rays_in_pixels(corner_b1, corner_b2, rows, cols, (np.zeros(1), np.zeros(1)))
    del corner_b1, corner_b2
    rebin_ops = tuple(tuple(jnp.asarray(w, dtype) for w in
                            rebin_operators(hr, l.grid.subdivided(l.oversampling)))
                      for l in layouts)

    clump_grid, groups = None, []
    if has_clumps and accuracy.source_mode == "grid":
        groups = _clump_groups_for(source, source_pixel_arcsec, accuracy.stamp_flux_fraction)
        cc = np.asarray(source.clumps.center_arcsec, float)
        half = (max(side for side, _ in groups) / 2 + 2) * source_pixel_arcsec
        clump_grid = Grid.covering((cc[:, 0].min() - half, cc[:, 0].max() + half),
                                   (cc[:, 1].min() - half, cc[:, 1].max() + half),
                                   source_pixel_arcsec)
    return SceneModel(tuple(layouts), accuracy, True, hr, clump_grid,
                      tuple(side for side, _ in groups), tuple(jnp.asarray(i) for _, i in groups),
                      tuple(psf_fts),
                      rebin_ops, jnp.asarray(rows), jnp.asarray(cols),
                      jnp.asarray(b1, dtype), jnp.asarray(b2, dtype), jnp.asarray(wxy, dtype),
                      jnp.asarray(c1[:, 0], dtype), jnp.asarray(c2[:, 0], dtype))
