"""A band as the caller gives it (`Band`) and inside a model (`DetectorBand`).

Change the PSF handling here: how a band's PSF image becomes a kernel on the sub-grid
(`psf_kernel`: point samples of an effective PSF, area averages of an optical one) and how
the convolved light becomes detector pixels (`DetectorBand.observe`). Reading, making and
resampling PSF images is `psf.py`; the FFT convolution is `convolve.py`.
"""

from __future__ import annotations

import dataclasses
from typing import Optional

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from .. import convolve, noise
from ..errors import require
from ..pixels import (Grid, RotatedGrid, apply_overlap, apply_sparse_map, bin_blocks,
                      rotated_overlap, rotated_samples)


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


def psf_kernel(band: Band, sub_pixel_arcsec: float, angle_rad: float = 0.0, *,
               moments: bool = False):
    """The band's PSF as an odd kernel on the sub-grid: point samples of an effective PSF
    (it already holds the pixel integral), area averages of an optical one. angle_rad: the
    band's pixel axes against the sub-grid's (the PSF image lies along the band's pixels).

    moments: also return the kernels [5, k, k] that carry each sub-pixel's light moments
    (`renderer.MOMENTS`, in that order; `SeparableLight`) through the PSF:
    the second-order Taylor expansion of the kernel in the light's offset d,
    K(u − d) ≈ K − d·∇K + ½ dᵀ∇∇K d, its derivatives as central differences of the
    kernel made half a sub-pixel off its nodes (each of unit sum, so the moments move
    light and never add any)."""
    from ..psf import PSF, resample_psf, rotate_psf, sample_psf
    psf = PSF(array=np.asarray(band.psf, float) / np.sum(band.psf),
              pixel_arcsec=float(band.psf_pixel_arcsec), effective=bool(band.psf_effective),
              source="model")
    if angle_rad:
        psf = rotate_psf(psf, angle_rad)
    to_grid = sample_psf if band.psf_effective else resample_psf
    kernel = convolve.check_kernel(to_grid(psf, sub_pixel_arcsec), f"bands[{band.name}].psf")
    if not moments:
        return kernel
    h = 0.5 * sub_pixel_arcsec

    def at(sx, sy):
        return to_grid(psf, sub_pixel_arcsec, size=kernel.shape[0], shift_arcsec=(sx * h, sy * h))

    # with steps of h = ½ sub-pixel: ∂x ≈ K(+h) − K(−h), ½∂x² ≈ 2[K(+h) − 2K + K(−h)],
    # ∂x∂y ≈ K(+h,+h) − K(+h,−h) − K(−h,+h) + K(−h,−h)
    slopes = np.stack([
        -(at(1, 0) - at(-1, 0)), -(at(0, 1) - at(0, -1)),
        2.0 * (at(1, 0) - 2.0 * kernel + at(-1, 0)), 2.0 * (at(0, 1) - 2.0 * kernel + at(0, -1)),
        at(1, 1) - at(1, -1) - at(-1, 1) + at(-1, -1)])
    return kernel, slopes


# sub-pixels per pixel of a turned band without a PSF: its light is not smooth on the pixel
# scale, and the overlaps' linear profiles then err by 18 % of a sharp clump's peak at 1,
# 1.2 % at 5 (R_e half a pixel; with a PSF the psf_oversampling chosen applies)
TURNED_MIN_OVERSAMPLING = 5


class DetectorBand(eqx.Module):
    """One band's detector: pixel grid, PSF on a sub-grid `oversampling` times finer, sky
    and exposure. Takes the rendered light on its sub-grid and observes it.

    `grid` is the detector's pixels: a `Grid`, or a `RotatedGrid` for data whose pixel
    axes are turned against the frame. The light is rendered on the frame-aligned
    `render_grid` (the grid itself, or one covering the turned pixels), convolved there
    with the PSF turned into the frame, and carried onto the turned pixels by their exact
    area overlaps (an optical PSF) or sampled at their centres (an effective PSF, which
    holds the pixel response already)."""

    name: str = eqx.field(static=True)
    grid: object = eqx.field(static=True)           # detector pixels: Grid or RotatedGrid
    render_grid: Grid = eqx.field(static=True)      # frame-aligned pixels the light is drawn on
    # sub-grid factor: where the PSF acts (1 without a PSF, TURNED_MIN_OVERSAMPLING if turned)
    oversampling: int = eqx.field(static=True)
    sub_pixel_arcsec: float = eqx.field(static=True)  # the band's pixel / oversampling
    exptime_s: float = eqx.field(static=True)
    sky_counts_per_s: float = eqx.field(static=True)
    psf_shape: Optional[tuple] = eqx.field(static=True)
    psf_effective: bool = eqx.field(static=True)
    psf_ft: Optional[jnp.ndarray]                   # rFFT of the kernel padded to the sub-grid
    # sub-grid → turned pixels: (index, weight) samples or (index, weight, moment) overlaps
    to_pixels: Optional[tuple] = None
    # rFFTs [6, ...] of the kernel and the 5 that carry light moments through the PSF
    # (`psf_kernel`), stacked once here rather than in every `observe`
    moment_ft: Optional[jnp.ndarray] = None

    @classmethod
    def build(cls, band: Band, grid, psf_oversampling: int, dtype, moments: bool = False):
        """The band on `grid` (Grid or RotatedGrid); its PSF (if any) as a kernel on the
        sub-grid. moments: a renderer hands light moments (`SeparableLight`): make the
        kernels that carry them through the PSF."""
        turned = isinstance(grid, RotatedGrid)
        s = (psf_oversampling if band.psf is not None else
             max(psf_oversampling, TURNED_MIN_OVERSAMPLING) if turned else 1)
        render = grid.covering() if turned else grid
        sub = render.subdivided(s)
        angle = grid.angle_rad if turned else 0.0
        kernel = slopes = None
        if band.psf is not None:
            kernel = psf_kernel(band, band.pixel_arcsec / s, angle, moments=moments)
            if moments:
                kernel, slopes = kernel
        to_pixels = None
        if turned:
            if band.psf is not None and band.psf_effective:
                index, weight = rotated_samples(sub, grid)
                to_pixels = (jnp.asarray(index),   # a sample of flux per sub-pixel → per pixel
                             jnp.asarray(weight * (s * s), dtype))
            else:
                index, weight, moment = rotated_overlap(sub, grid)
                to_pixels = (jnp.asarray(index), jnp.asarray(weight, dtype),
                             jnp.asarray(moment, dtype))
        return cls(band.name, grid, render, s, band.pixel_arcsec / s, float(band.exptime_s),
                   float(band.sky_counts_per_s),
                   None if kernel is None else kernel.shape, bool(band.psf_effective),
                   None if kernel is None else
                   convolve.kernel_rfft(kernel, sub.shape, dtype), to_pixels,
                   None if slopes is None else convolve.kernel_rfft(
                       np.concatenate([kernel[None], slopes]), sub.shape, dtype, check=False))

    @property
    def sub_grid(self) -> Grid:
        return self.render_grid.subdivided(self.oversampling)

    def observe(self, sub, moments=None):
        """PSF and detector pixels: sub-grid flux image → detector counts/s (no sky).
        moments: the light's moments about each sub-pixel's centre [5, ny, nx]
        (`renderer.MOMENTS`; `SeparableLight`), or None; read only where a PSF acts. Without
        a PSF, binning keeps a sub-pixel's light whatever its place in it; a turned band's
        overlaps (no PSF) take their slopes from neighbouring sub-pixels instead."""
        s = self.oversampling
        if self.psf_shape is None:
            conv = sub
        elif moments is None or self.moment_ft is None:
            conv = convolve.fft_convolve(sub, self.psf_ft, self.psf_shape)
        else:
            conv = convolve.fft_convolve_sum(jnp.concatenate([sub[None], moments]),
                                             self.moment_ft, self.psf_shape)
        if self.to_pixels is not None:
            apply = apply_sparse_map if len(self.to_pixels) == 2 else apply_overlap
            return apply(conv, *self.to_pixels, self.grid.shape)
        if self.psf_shape is not None and self.psf_effective:
            # the PSF holds the pixel response: sample it at detector centres (DESIGN.md trap)
            return conv[s // 2::s, s // 2::s] * (s * s)
        return bin_blocks(conv, s)

    def with_sky(self, image):
        """Counts/s per pixel with the sky added."""
        return image + self.sky_counts_per_s

    def variance(self, noiseless_image):
        """Poisson variance map of a noiseless image (with sky), (counts/s)²."""
        return noise.variance_map(noiseless_image, self.exptime_s)
