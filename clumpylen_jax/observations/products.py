"""A cutout written as JWST/HST products lay it out: mock data in the formats `read` takes.

JWST i2d: SCI and ERR in MJy/sr (with PIXAR_SR); HST drz: SCI in e⁻/s with a WHT (1/σ²)
map, EXPTIME, PHOTFLAM and PHOTPLAM. The units are the caller's cards (`extra`), so any
format `read.read_observation` understands can be written.
"""

from __future__ import annotations

import numpy as np
from astropy.io import fits

from ..io import atomic_write


def write_cutout(path, sci, err=None, *, header=None, bunit="MJy/sr", extra=None, wht=None,
                 psf=None):
    """Write an empty primary HDU, then SCI (and ERR, WHT, PSF where given) image HDUs.

    sci, err (σ, sci's units), wht (1/σ², sci's units⁻²), psf: 2-D arrays, stored as float32.
    header (copied; a celestial WCS or PIXSCALE), BUNIT (None: left out) and the `extra`
    cards go on every data HDU but PSF. Written atomically. Returns the path as a str.
    """
    hdr = fits.Header() if header is None else header.copy()
    if bunit is not None:
        hdr["BUNIT"] = bunit
    for k, v in (extra or {}).items():
        hdr[k] = v
    hdus = [fits.PrimaryHDU(), fits.ImageHDU(np.asarray(sci, np.float32), hdr, name="SCI")]
    for name, data in (("ERR", err), ("WHT", wht)):
        if data is not None:
            hdus.append(fits.ImageHDU(np.asarray(data, np.float32), hdr, name=name))
    if psf is not None:
        hdus.append(fits.ImageHDU(np.asarray(psf, np.float32), name="PSF"))
    with atomic_write(path) as tmp:
        fits.HDUList(hdus).writeto(tmp, overwrite=True)
    return str(path)
