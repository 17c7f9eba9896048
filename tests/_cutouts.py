"""A cutout file as JWST/HST products lay it out, for the observation tests."""

from __future__ import annotations

import numpy as np
from astropy.io import fits


def write_cutout(path, sci, err=None, *, header=None, bunit="MJy/sr", extra=None, wht=None,
                 psf=None):
    """SCI (and ERR, WHT, PSF where given) image HDUs after an empty primary; `header` (copied),
    BUNIT (None: left out) and the `extra` cards on every data HDU but PSF. Returns the path."""
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
    fits.HDUList(hdus).writeto(path, overwrite=True)
    return str(path)
