"""Files on disk: atomic writes, FITS images with a TAN WCS in the θ frame,
ECSV catalogues and JSON summaries (colour PNGs: `rgbimage`).

Every writer goes through `atomic_write`, so an interrupted run never leaves a
half-written file under the final name.

The θ frame (DESIGN.md): θ1 = −(RA − RA0)·cos(Dec0)·3600 (arcsec, positive to
the West = +x in a north-up, east-left image), θ2 = (Dec − Dec0)·3600. The
WCS written here is a gnomonic (TAN) projection about (RA0, Dec0), so θ are
its standard coordinates: equal to the linear formula above to second order
(a few mas at 40″ from the reference).
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import math
import os
import tempfile
from pathlib import Path
from typing import Any, Iterator

import numpy as np

__all__ = [
    "atomic_write",
    "make_wcs",
    "theta_to_radec",
    "radec_to_theta",
    "write_band_fits",
    "write_catalog",
    "write_fits_image",
    "write_json",
    "write_residual_fits",
]


@contextlib.contextmanager
def atomic_write(path: str | os.PathLike, mode: str | None = None) -> Iterator[Any]:
    """Write `path` all at once: into a temporary file beside it, then os.replace.

    mode None: yields the temporary file's path (str), for writers that take a
    path (astropy, matplotlib); the temporary name keeps `path`'s suffix so
    format sniffing still works. mode "w"/"wb": yields an open file object.
    If the body raises, the temporary file is removed and `path` is untouched.
    Parent directories are created.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp" + path.suffix)
    os.close(fd)
    try:
        if mode is None:
            yield tmp
        else:
            encoding = None if "b" in mode else "utf-8"
            with open(tmp, mode, encoding=encoding) as fh:
                yield fh
        # mkstemp makes the file private (0600); give it the usual permissions.
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.remove(tmp)
        raise


# ----------------------------------------------------------------------------
# WCS in the θ frame
# ----------------------------------------------------------------------------


def make_wcs(center_radec_deg, pixel_arcsec: float, shape, theta_of_pixel0_arcsec):
    """A celestial TAN WCS for an image whose pixel (0, 0) centre lies at θ = theta_of_pixel0.

    center_radec_deg: (RA0, Dec0), the θ origin (the lens centre, or the
    source centre for an unlensed scene); it is CRVAL. shape: (ny, nx) of the
    image (numpy order). Pixel x grows with θ1 (West), y with θ2 (North):
    CDELT1 = −pixel/3600, CDELT2 = +pixel/3600.
    """
    from astropy.wcs import WCS

    ny, nx = (int(s) for s in shape)
    t1, t2 = (float(t) for t in theta_of_pixel0_arcsec)
    w = WCS(naxis=2)
    w.wcs.ctype = ["RA---TAN", "DEC--TAN"]
    w.wcs.cunit = ["deg", "deg"]
    w.wcs.crval = [float(center_radec_deg[0]), float(center_radec_deg[1])]
    # FITS pixels are 1-based: pixel 0 is 1, and θ = t + (p − 1)·pixel is 0 at CRPIX.
    w.wcs.crpix = [1.0 - t1 / pixel_arcsec, 1.0 - t2 / pixel_arcsec]
    w.wcs.cdelt = [-pixel_arcsec / 3600.0, pixel_arcsec / 3600.0]
    w.wcs.radesys = "ICRS"
    w.pixel_shape = (nx, ny)
    w.wcs.set()
    return w


def theta_to_radec(theta1_arcsec, theta2_arcsec, center_radec_deg):
    """(RA, Dec) in degrees of θ (arcsec) under the gnomonic projection about the centre."""
    from astropy.wcs import WCS

    w = WCS(naxis=2)
    w.wcs.ctype = ["RA---TAN", "DEC--TAN"]
    w.wcs.crval = [float(center_radec_deg[0]), float(center_radec_deg[1])]
    w.wcs.crpix = [1.0, 1.0]  # 0-based pixel 0 (origin=0 below) is the centre
    w.wcs.cdelt = [-1.0 / 3600.0, 1.0 / 3600.0]  # one "pixel" = 1″, x towards the West
    ra, dec = w.wcs_pix2world(np.asarray(theta1_arcsec, float), np.asarray(theta2_arcsec, float), 0)
    return ra, dec


def radec_to_theta(ra_deg, dec_deg, center_radec_deg):
    """θ (arcsec) of (RA, Dec) in degrees: the inverse of theta_to_radec."""
    from astropy.wcs import WCS

    w = WCS(naxis=2)
    w.wcs.ctype = ["RA---TAN", "DEC--TAN"]
    w.wcs.crval = [float(center_radec_deg[0]), float(center_radec_deg[1])]
    w.wcs.crpix = [1.0, 1.0]  # 0-based pixel 0 (origin=0 below) is the centre
    w.wcs.cdelt = [-1.0 / 3600.0, 1.0 / 3600.0]
    t1, t2 = w.wcs_world2pix(np.asarray(ra_deg, float), np.asarray(dec_deg, float), 0)
    return t1, t2


# ----------------------------------------------------------------------------
# FITS
# ----------------------------------------------------------------------------


def _image_hdu(cls, data, wcs, header: dict | None, name: str | None):

    arr = np.asarray(data, dtype=np.float32)
    hdu = cls(data=arr) if name is None else cls(data=arr, name=name)
    if wcs is not None:
        hdu.header.update(wcs.to_header())
    for key, value in (header or {}).items():
        hdu.header[key] = _fits_value(value)
    return hdu


def _fits_value(value):
    """FITS cards take str, int, float, bool (or (value, comment)); unwrap numpy/JAX scalars."""
    if isinstance(value, tuple):
        return (_fits_value(value[0]),) + tuple(value[1:])
    if value is None:
        return "none"
    if hasattr(value, "item") and np.ndim(value) == 0:
        return value.item()
    return value


def write_fits_image(path, data, wcs=None, header: dict | None = None) -> None:
    """A single-HDU float32 FITS image, with an optional WCS and extra header cards."""
    from astropy.io import fits

    hdu = _image_hdu(fits.PrimaryHDU, data, wcs, header, None)
    with atomic_write(path) as tmp:
        fits.HDUList([hdu]).writeto(tmp, overwrite=True)


def write_band_fits(path, image, *, noiseless, variance, unlensed=None, header: dict, wcs,
                    unlensed_wcs=None) -> None:
    """One band's FITS file (SCENE.md): primary = image (counts/s per pixel),
    extensions NOISELESS, VARIANCE and, when given, UNLENSED (with its own WCS).

    header: cards for every HDU, e.g. TELESCOP, INSTRUME, FILTER, EXPTIME,
    ZP_AB, PIXSCALE, SKYLEVEL, SEED (values or (value, comment) tuples);
    BUNIT = 'counts/s' is set unless given.
    """
    from astropy.io import fits

    cards = {"BUNIT": "counts/s", **header}
    hdus = [
        _image_hdu(fits.PrimaryHDU, image, wcs, cards, None),
        _image_hdu(fits.ImageHDU, noiseless, wcs, cards, "NOISELESS"),
        _image_hdu(fits.ImageHDU, variance, wcs, {**cards, "BUNIT": "(counts/s)**2"}, "VARIANCE"),
    ]
    if unlensed is not None:
        hdus.append(_image_hdu(fits.ImageHDU, unlensed, unlensed_wcs, cards, "UNLENSED"))
    with atomic_write(path) as tmp:
        fits.HDUList(hdus).writeto(tmp, overwrite=True)


def write_residual_fits(path, data, model, chi, *, header, chi_bunit: str,
                        primary_header=None) -> None:
    """A fit's residuals file: an empty primary HDU, then DATA, MODEL, RESIDUAL (= DATA − MODEL)
    and CHI as float32 extensions, each with the cards of `header` (a dict or a FITS
    header, e.g. BUNIT and FILTER, or a WCS); CHI's BUNIT is `chi_bunit`."""
    from astropy.io import fits

    data, model = np.asarray(data), np.asarray(model)
    hdus = [fits.PrimaryHDU(header=primary_header)]
    for ext, arr in (("DATA", data), ("MODEL", model), ("RESIDUAL", data - model), ("CHI", chi)):
        h = fits.ImageHDU(np.asarray(arr).astype(np.float32), name=ext)
        h.header.update(header)
        if ext == "CHI":
            h.header["BUNIT"] = chi_bunit
        hdus.append(h)
    with atomic_write(path) as tmp:
        fits.HDUList(hdus).writeto(tmp, overwrite=True)


# ----------------------------------------------------------------------------
# Tables and JSON
# ----------------------------------------------------------------------------


def write_catalog(path, table) -> None:
    """Write a table (astropy Table, or a mapping of column name -> array) as ECSV."""
    from astropy.table import Table

    t = table if isinstance(table, Table) else Table({k: np.asarray(v) for k, v in dict(table).items()})
    with atomic_write(path) as tmp:
        t.write(tmp, format="ascii.ecsv", overwrite=True)


def _jsonable(obj):
    """numpy/JAX arrays and scalars, paths, dataclasses, sets -> JSON types; NaN/inf -> None."""
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: _jsonable(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple, set, frozenset)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, (bool, np.bool_)):
        return bool(obj)
    if isinstance(obj, (int, np.integer)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        f = float(obj)
        return f if math.isfinite(f) else None  # strict JSON has no NaN
    if isinstance(obj, (str, type(None))):
        return obj
    if isinstance(obj, os.PathLike):
        return os.fspath(obj)
    if hasattr(obj, "__array__"):  # numpy and JAX arrays
        return _jsonable(np.asarray(obj).tolist())
    if hasattr(obj, "item"):
        return _jsonable(obj.item())
    raise TypeError(f"cannot write {type(obj).__name__} to JSON")


def write_json(path, obj) -> None:
    """Write `obj` as indented JSON (numpy-safe; non-finite numbers become null)."""
    text = json.dumps(_jsonable(obj), indent=2, allow_nan=False)
    with atomic_write(path, "w") as fh:
        fh.write(text + "\n")
