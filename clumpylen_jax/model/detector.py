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
from ..pixels import Grid, bin_blocks


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


def psf_kernel(band: Band, sub_pixel_arcsec: float):
    """The band's PSF as an odd kernel on the sub-grid: point samples of an effective PSF
    (it already holds the pixel integral), area averages of an optical one."""
    from ..psf import PSF, resample_psf, sample_psf
    psf = PSF(array=np.asarray(band.psf, float) / np.sum(band.psf),
              pixel_arcsec=float(band.psf_pixel_arcsec), effective=bool(band.psf_effective),
              source="model")
    to_grid = sample_psf if band.psf_effective else resample_psf
    return convolve.check_kernel(to_grid(psf, sub_pixel_arcsec), f"bands[{band.name}].psf")


class DetectorBand(eqx.Module):
    """One band's detector: pixel grid, PSF on a sub-grid `oversampling` times finer, sky
    and exposure. Takes the rendered light on its sub-grid and observes it."""

    name: str = eqx.field(static=True)
    grid: Grid = eqx.field(static=True)             # detector pixels
    oversampling: int = eqx.field(static=True)      # sub-grid on which the PSF acts (1 without PSF)
    sub_pixel_arcsec: float = eqx.field(static=True)  # the band's pixel / oversampling
    exptime_s: float = eqx.field(static=True)
    sky_counts_per_s: float = eqx.field(static=True)
    psf_shape: Optional[tuple] = eqx.field(static=True)
    psf_effective: bool = eqx.field(static=True)
    psf_ft: Optional[jnp.ndarray]                   # rFFT of the kernel padded to the sub-grid

    @classmethod
    def build(cls, band: Band, grid: Grid, psf_oversampling: int, dtype):
        """The band on `grid`; its PSF (if any) as a kernel on the sub-grid."""
        s = psf_oversampling if band.psf is not None else 1
        kernel = psf_kernel(band, band.pixel_arcsec / s) if band.psf is not None else None
        return cls(band.name, grid, s, band.pixel_arcsec / s, float(band.exptime_s), float(band.sky_counts_per_s),
                   None if kernel is None else kernel.shape, bool(band.psf_effective),
                   None if kernel is None else
                   convolve.kernel_rfft(kernel, grid.subdivided(s).shape, dtype))

    @property
    def sub_grid(self) -> Grid:
        return self.grid.subdivided(self.oversampling)

    def observe(self, sub):
        """PSF and detector pixels: sub-grid flux image → detector counts/s (no sky)."""
        s = self.oversampling
        if self.psf_shape is None:
            return bin_blocks(sub, s)
        conv = convolve.fft_convolve(sub, self.psf_ft, self.psf_shape)
        if self.psf_effective:
            # the PSF holds the pixel response: sample it at detector centres (DESIGN.md trap)
            return conv[s // 2::s, s // 2::s] * (s * s)
        return bin_blocks(conv, s)

    def with_sky(self, image):
        """Counts/s per pixel with the sky added."""
        return image + self.sky_counts_per_s

    def variance(self, noiseless_image):
        """Poisson variance map of a noiseless image (with sky), (counts/s)²."""
        return noise.variance_map(noiseless_image, self.exptime_s)
