"""The composed forward model of a scene: source → (lens) → pixels → PSF → sky and noise.

`build_model` makes the static decisions once — grids, which lens-plane pixels to
ray-trace, stamp sizes, PSF transforms — and assembles a `SceneModel` from the renderers
the scene needs: a host renderer, a clump renderer (which ones: lens or not, and
`accuracy.source_mode`) and a `DetectorBand` per band. Its methods are pure functions of a
`Source`:

- ``band_images(source)``: PSF-convolved source light per band, counts/s/pixel;
- ``noiseless(source)``: the same plus sky;
- ``observe(source, key)``: a photon-noise realisation and its variance map.

Only the stages a scene calls for are in the model: without a lens there is no ray
tracing, a band without PSF has no FFT, and no random numbers are drawn unless
``observe`` is called. Rays are traced only over the lens-plane pixels where the source
lands, once, at build time (the lens is fixed in a model; the source is what is
differentiated).
"""

from __future__ import annotations

import dataclasses
from typing import Optional

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .. import defaults as D
from .. import noise, profiles, raycache
from ..accuracy import Accuracy
from ..errors import ConfigError, require
from ..lensing import tracing
from ..lensing.linearised import linearise_clumps
from ..pixels import Grid
from ..source import Source
from .clumps import (AnalyticClumps, LensedClumps, LinearisedClumps, RoundGaussianClumps,
                     SourceGridClumps, UnlensedClumps)
from .detector import DetectorBand
from .hosts import HeldHosts, HostCore, LensPlaneHosts, UnlensedHosts
from .lensplane import LensPlane
from .renderer import MOMENTS, Renderer, first_band_per_subgrid, n_bands

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


class SceneModel(eqx.Module):
    """A scene's forward model: renderers for the host and the clumps, a detector per band,
    and (lensed scenes) the traced lens plane they share; build it with `build_model`."""

    layouts: tuple                   # one DetectorBand per band
    hosts: Renderer
    clumps: Renderer
    plane: Optional[LensPlane]
    accuracy: Accuracy = eqx.field(static=True)

    @property
    def band_names(self):
        return tuple(b.name for b in self.layouts)

    @property
    def lensed(self) -> bool:
        return self.plane is not None

    def _zeros(self, shape, source: Source, parts):
        # lensed: the model's dtype; unlensed: the source's (its first light's, or its clumps')
        dtype = (self.plane.dtype if self.plane is not None else
                 parts[0].dtype if parts else source.clumps.flux.dtype)
        return jnp.zeros(shape, dtype)

    def band_images(self, source: Source):
        """PSF-convolved source light per band (tuple of [ny, nx], counts/s per pixel, no sky)."""
        subgrids = first_band_per_subgrid(self.layouts)
        return self._observed([r.subgrid_light(source, subgrids)
                               for r in (self.hosts, self.clumps)], source)

    def band_images_and_clumps_on(self, source: Source, grid: Grid, groups, flux):
        """(`band_images(source)`, the clumps' light [ny, nx, C] on one more `grid`: stamp
        `groups` as `render.grouped_stamps_on` takes them, fluxes `flux` [N, C]), the clumps'
        stamps made by one call (`UnlensedClumps.subgrid_light_and_grid`): unlensed models
        with Sérsic clump stamps only."""
        subgrids = first_band_per_subgrid(self.layouts)
        clump_light, on_grid = self.clumps.subgrid_light_and_grid(source, subgrids, grid,
                                                                  groups, flux)
        return self._observed([self.hosts.subgrid_light(source, subgrids), clump_light],
                              source), on_grid

    def _observed(self, lights, source: Source):
        """Band images from the renderers' sub-grid light (`subgrid_light`'s dicts)."""
        out = []
        for k, det in enumerate(self.layouts):
            g = det.sub_grid
            parts = [light[g] for light in lights if g in light]
            sub = self._zeros(g.shape, source, parts)
            for part in parts:
                sub = part.add_band(sub, k)
            moments = None
            if det.moment_ft is not None and any(p.has_moments for p in parts):
                moments = self._zeros((len(MOMENTS),) + g.shape, source, parts)
                for part in parts:
                    if part.has_moments:
                        moments = part.add_band_moments(moments, k)
            out.append(det.observe(sub, moments))
        return tuple(out)

    def noiseless(self, source: Source):
        """Band images with sky added (counts/s per pixel)."""
        return tuple(det.with_sky(img) for img, det in zip(self.band_images(source), self.layouts))

    def variances(self, noiseless_images):
        """Poisson variance maps of noiseless images (with sky), (counts/s)²."""
        return tuple(det.variance(img) for img, det in zip(noiseless_images, self.layouts))

    def observe(self, source: Source, key):
        """(noisy images, noiseless images, variances), one of each per band."""
        clean = self.noiseless(source)
        noisy = noise.add_photon_noise_bands(key, clean, [det.name for det in self.layouts],
                                             [det.exptime_s for det in self.layouts],
                                             self.accuracy.gaussian_noise_above)
        return noisy, clean, self.variances(clean)

    def noiseless_lens_plane_magnifications(self, source: Source, plane_source=None,
                                            magnify: bool = False):
        """(`noiseless(source)`, `lens_plane(plane_source)` or None without plane_source,
        `clump_magnifications(source)` or None without `magnify`) in one computation:
        in a lensed scene with ray-traced or linearised clumps, one stamp call and one
        ray-traced pass serve all three (`LensedClumps.light_lens_plane_and_magnifications`);
        otherwise each is computed as alone (XLA merges what they share)."""
        if not isinstance(self.clumps, LensedClumps):
            clean = self.noiseless(source)
            plane = None if plane_source is None else self.lens_plane(plane_source)
            mags = self.clump_magnifications(source, beside_band_images=True) if magnify \
                else None
            return clean, plane, mags
        subgrids = first_band_per_subgrid(self.layouts)
        plane = None
        if plane_source is not None:
            plane = jnp.zeros(self.plane.grid.shape + (n_bands(plane_source),),
                              self.plane.dtype)
            plane = self.hosts.add_lens_plane(plane_source, plane)
        clump_light, plane, mags = self.clumps.light_lens_plane_and_magnifications(
            source, subgrids, plane_source, plane, magnify)
        images = self._observed([self.hosts.subgrid_light(source, subgrids), clump_light],
                                source)
        clean = tuple(det.with_sky(img) for img, det in zip(images, self.layouts))
        return clean, None if plane is None else jnp.moveaxis(plane, -1, 0), mags

    def lens_plane(self, source: Source):
        """High-resolution lens-plane images [B, ny, nx], counts/s per lens-plane pixel."""
        img = jnp.zeros(self.plane.grid.shape + (n_bands(source),), self.plane.dtype)
        img = self.clumps.add_lens_plane(source, self.hosts.add_lens_plane(source, img))
        return jnp.moveaxis(img, -1, 0)

    def with_host_light(self, units) -> "SceneModel":
        """This model with the host's light per unit flux held: `units` is
        `hosts.unit_light(source, first_band_per_subgrid(layouts))` of the source's host,
        computed before. Its images are this model's for any host fluxes, and not
        differentiable in the host's geometry."""
        return dataclasses.replace(self, hosts=HeldHosts(self.hosts, units))

    def clump_magnifications(self, source: Source, beside_band_images: bool = False):
        """Magnification [N] of each clump within the field (light-weighted over its stamp).

        beside_band_images: for a program that computes `band_images` too: the ray-traced
        clumps' stamps are made as it makes them, so that XLA computes them once for both
        (one program instead of a second one with its own exact-pixel kernel)."""
        if beside_band_images and isinstance(self.clumps, LensedClumps):
            return self.clumps.magnifications(source, first_band_per_subgrid(self.layouts))
        return self.clumps.magnifications(source)

    def source_magnification_map(self):
        """Lens-plane area per stored source-grid pixel / its area (ray-traced clumps only)."""
        return self.clumps.source_magnification_map()

    # -- what summaries, diagnostics and benchmarks read about the build --------------

    @property
    def hr_grid(self):
        return None if self.plane is None else self.plane.grid

    @property
    def traced_rows(self):
        return None if self.plane is None else self.plane.rows

    @property
    def traced_cols(self):
        return None if self.plane is None else self.plane.cols

    @property
    def beta1(self):
        return None if self.plane is None else self.plane.beta1

    @property
    def clump_grid(self):
        traced = getattr(self.clumps, "traced", None)
        return None if traced is None else traced.grid

    @property
    def clump_stamp_index(self):
        traced = getattr(self.clumps, "traced", None)
        return () if traced is None else traced.index

    @property
    def lin_images(self):
        lin = getattr(self.clumps, "linearised", None)
        return None if lin is None else lin.images

    @property
    def host_core_index(self):
        core = getattr(self.hosts, "core", None)
        return None if core is None else core.index


# ------------------------------------------------------------------ building


def require_float64_mode(dtype):
    """ConfigError unless JAX's 64-bit mode is on when `dtype` is float64 (JAX would
    otherwise compute in float32 without saying so)."""
    if jnp.dtype(dtype) == jnp.float64 and not jax.config.read("jax_enable_x64"):
        raise ConfigError("render.dtype", "float64",
                          'JAX 64-bit mode on: call clumpylen_jax.enable_float64() first (the '
                          'clumpylen command does), or use render.dtype = "float32"')


def _band_grids(bands, grids, field_arcsec, lens, center, radius):
    """The detector grid of each band: given, covering the field, or around the source."""
    psf_margin = 0.0
    for band in bands:
        if band.psf is not None:
            psf_margin = max(psf_margin, 0.5 * max(np.shape(band.psf)) * band.psf_pixel_arcsec)
    if grids is not None:
        require(len(grids) == len(bands) and all(
            abs(g.pixel_arcsec - b.pixel_arcsec) <= 1e-9 * b.pixel_arcsec
            for g, b in zip(grids, bands)), "grids", grids,
            "one Grid (or RotatedGrid) per band, of its pixel")
        return list(grids)
    if field_arcsec is not None:
        return [Grid.covering(field_arcsec[0], field_arcsec[1], b.pixel_arcsec) for b in bands]
    if lens is None:
        return [Grid.centered(center, radius + psf_margin, b.pixel_arcsec) for b in bands]
    raise ConfigError("render.field_arcsec", None,
                      "a lens-plane field for a lensed scene (the scene layer finds one)")


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
        own scale and offset), or a `RotatedGrid` where the band's pixel axes are turned
        against the frame (`DetectorBand`), overriding field_arcsec; its pixel must be the
        band's.
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
    # the Gaussian-mixture clumps (no stamps, so no layouts needed) hand the PSF their
    # light's moments in each sub-pixel (`SeparableLight`): the bands make kernels for them
    mixture = (RoundGaussianClumps.build(source, accuracy.clump_pixels)
               if lens is None and accuracy.clump_pixels != "sersic" else None)
    layouts = tuple(DetectorBand.build(b, g, accuracy.psf_oversampling, dtype,
                                       moments=mixture is not None)
                    for b, g in zip(bands, _band_grids(bands, grids, field_arcsec, lens, center,
                                                       radius)))
    if lens is None:
        clumps = mixture if mixture is not None else \
            UnlensedClumps.build(source, layouts, accuracy)
        return SceneModel(layouts, UnlensedHosts.build(source, layouts, accuracy), clumps, None,
                          accuracy)
    require(accuracy.clump_pixels == "sersic", "render.accuracy.clump_pixels",
            accuracy.clump_pixels, '"sersic" for a lensed scene (clumps are evaluated at rays '
            'through the lens; the Gaussian mixtures draw unlensed sub-grids only)')
    return _lensed_model(source, layouts, lens, field_arcsec, center, radius, lens_pixel_arcsec,
                         source_pixel_arcsec, accuracy, dtype, ray_cache)


def _lensed_model(source, layouts, lens, field_arcsec, center, radius, lens_pixel_arcsec,
                  source_pixel_arcsec, accuracy, dtype, ray_cache):
    """The renderers of a lensed scene, on one high-resolution lens-plane grid over the union
    of the band fields; `source_mode` chooses the clump renderer."""
    hr = Grid.covering((min(l.grid.x_range[0] for l in layouts),
                        max(l.grid.x_range[1] for l in layouts)),
                       (min(l.grid.y_range[0] for l in layouts),
                        max(l.grid.y_range[1] for l in layouts)), lens_pixel_arcsec)
    corner_b1, corner_b2 = raycache.traced_corners(lens, hr, tracing.trace_corners, ray_cache)
    rows, cols, footprints = tracing.traced_pixels(corner_b1, corner_b2, center, radius)
    if rows.size == 0:
        raise ConfigError("render.field_arcsec", field_arcsec,
                          "a lens-plane field where the source lands (no pixel of it maps "
                          f"within {radius:.3g}\" of the source centre {tuple(center)})")
    core = HostCore.build(source, corner_b1, corner_b2, rows, cols, footprints,
                          accuracy.exact_core, dtype)
    has_clumps = source.clumps is not None and source.clumps.count > 0
    traced = np.arange(source.clumps.count if has_clumps else 0)
    linearised = None
    if has_clumps and accuracy.source_mode == "hybrid" and accuracy.linearise_tolerance > 0:
        tol = accuracy.linearise_tolerance * min(l.grid.pixel_arcsec for l in layouts)
        lin_mask, images = linearise_clumps(source.clumps, corner_b1, corner_b2, hr, rows, cols,
                                            footprints, accuracy.stamp_flux_fraction, tol, dtype)
        traced = np.nonzero(~lin_mask)[0]
        linearised = LinearisedClumps.build(source, images, layouts, hr, accuracy)
    ray_pixels = _ray_pixels(source, traced, corner_b1, corner_b2, rows, cols, footprints,
                             accuracy)
    footprint = accuracy.ray_footprint and accuracy.source_mode == "analytic"
    if footprint and has_clumps:
        bad = np.asarray(source.clumps.n, float)
        bad = bad[bad != 0.5]
        require(not bad.size, "render.accuracy.ray_footprint", True,
                f"clumps that are all Gaussian (Sérsic n = 0.5; n = {bad[:1]} here)")
    plane, (b1, b2) = LensPlane.build(corner_b1, corner_b2, hr, rows, cols, ray_pixels, layouts,
                                      accuracy.lens_subsampling, dtype, ray_cov=footprint)
    del corner_b1, corner_b2
    hosts = LensPlaneHosts(plane, core, accuracy.host_subsampling)
    if accuracy.source_mode == "analytic":
        clumps = AnalyticClumps(plane)
    else:
        clumps = LensedClumps(plane, SourceGridClumps.build(source.clumps, traced, b1, b2,
                                                            source_pixel_arcsec, accuracy),
                              linearised, accuracy.source_order, accuracy.exact_core)
    return SceneModel(layouts, hosts, clumps, plane, accuracy)


def _ray_pixels(source, traced, corner_b1, corner_b2, rows, cols, footprints, accuracy):
    """Indices of the traced pixels that get rays: every one when every ray needs a value
    (analytic clumps, host_subsampling); otherwise only the pixels whose footprint reaches
    a ray-traced clump's stamp."""
    if accuracy.source_mode == "analytic" or accuracy.host_subsampling:
        return np.arange(rows.size)
    cl = source.clumps
    r_stamp = (_radius_enclosing(accuracy.stamp_flux_fraction,
                                 np.asarray(cl.re_arcsec, float)[traced],
                                 np.asarray(cl.n, float)[traced])
               if traced.size else np.zeros(0))
    _, pix = tracing.pixels_near(corner_b1, corner_b2, rows, cols,
                                 np.asarray(cl.center_arcsec, float)[traced]
                                 if traced.size else np.zeros((0, 2)), r_stamp, footprints)
    return np.unique(pix)
