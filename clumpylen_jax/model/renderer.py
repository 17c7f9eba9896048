"""The interface every renderer follows, and the light it hands to the detector bands.

A renderer is a final equinox Module that draws some of a source's components (the host,
the clumps) in one way (unlensed, through the traced lens plane, linearised, ...). It does
its build-time precomputation in its own `build` classmethod; `build_model` chooses which
renderers a scene needs (`source_mode`, lens or not) and `SceneModel` only adds up what
they return, band by band, before each `DetectorBand` observes it.
"""

from __future__ import annotations

import abc

import equinox as eqx
import jax.numpy as jnp

from ..source import Source


# the light moments about each sub-pixel's centre that a renderer may hand the PSF, in this
# order (`Light.add_band_moments`, `detector.psf_kernel`): flux-weighted, in sub-pixels
MOMENTS = ("x", "y", "x²", "y²", "xy")


class Light:
    """A renderer's light on one sub-grid, for every band (not a pytree: lives inside a trace).

    has_moments: the light also knows where in each sub-pixel it lies (`add_band_moments`),
    which the PSF then carries (`DetectorBand.observe`)."""

    has_moments = False

    def add_band(self, image, k: int):
        """image + band k's light ([ny, nx] each)."""
        raise NotImplementedError

    def add_band_moments(self, moments, k: int):
        """moments [len(MOMENTS), ny, nx] + band k's light moments (`MOMENTS`)."""
        raise NotImplementedError


class BandStack(Light):
    """Light held per band: images [ny, nx, B], added in turn."""

    def __init__(self, images, dtype=None):
        self.images = images
        self.dtype = images[0].dtype if dtype is None else dtype

    def add_band(self, image, k):
        for img in self.images:
            image = image + img[..., k]
        return image


class HostStack(Light):
    """Achromatic components: units [ny, nx, C] per unit flux, times fluxes [C, B]."""

    def __init__(self, units, fluxes):
        self.units, self.fluxes = units, fluxes
        self.dtype = units.dtype

    def add_band(self, image, k):
        return image + self.units @ self.fluxes[:, k]


class UnitImages(Light):
    """Achromatic components one by one: [(flux [B], unit image [ny, nx])]."""

    def __init__(self, parts):
        self.parts = parts
        self.dtype = jnp.result_type(*[unit for _, unit in parts])

    def add_band(self, image, k):
        for flux, unit in self.parts:
            image = image + flux[k] * unit
        return image


class SeparableLight(Light):
    """Round Gaussian clumps on one sub-grid: per row [3, ny, N] and per column [3, nx, N]
    of each clump, its light fraction and first and second moments about the pixel's
    centre (`render.gaussian_pixel_moments`), and fluxes [N, B]. Band k is rows[0] ·
    diag(flux[:, k]) · cols[0]ᵀ (one matrix product per band, nothing of size clumps ×
    pixels), and its moments are separable the same way (5 more products), so a clump far
    smaller than a sub-pixel still moves its image as its centre moves within one."""

    has_moments = True

    def __init__(self, rows, cols, flux):
        self.rows, self.cols, self.flux = rows, cols, flux
        self.dtype = jnp.result_type(rows, flux)

    def add_band(self, image, k):
        return image + (self.rows[0] * self.flux[:, k]) @ self.cols[0].T

    def add_band_moments(self, moments, k):
        r = self.rows * self.flux[:, k]
        c = self.cols
        # (x, y, x², y², xy): x runs along columns, y along rows
        return moments + jnp.stack([r[0] @ c[1].T, r[1] @ c[0].T, r[0] @ c[2].T,
                                    r[2] @ c[0].T, r[1] @ c[1].T])


class Renderer(eqx.Module):
    """Draws some of a source's components on the model's sub-grids.

    any_count: whether it draws a source with any number of clumps (its build fixes
    nothing per clump), so a fit may render only the clumps it moves (`inference.capacity`).
    """

    any_count = False   # a class constant, not a field

    @abc.abstractmethod
    def subgrid_light(self, source: Source, subgrids: dict) -> dict:
        """{sub-grid: Light} for `subgrids` ({sub-grid: index of its first band}); sub-grids
        where the renderer draws nothing are left out."""


def n_bands(source: Source) -> int:
    for comp in (source.bulge, source.disk.sersic if source.disk is not None else None):
        if comp is not None:
            return comp.flux.shape[0]
    return source.clumps.flux.shape[1]


def first_band_per_subgrid(layouts) -> dict:
    """{sub-grid: index of its first band}: bands on the same sub-grid share every image
    made on it."""
    first = {}
    for k, lay in enumerate(layouts):
        first.setdefault(lay.sub_grid, k)
    return first
