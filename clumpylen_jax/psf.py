"""Point-spread functions: FITS loading, built-in diffraction PSFs, resampling.

A PSF here is a 2-D array of the fraction of a point source's flux that falls
in each pixel of a regular grid (normalised to unit sum over the array), with
its pixel scale and a flag saying whether the detector pixel response is
already included ("effective" PSF: HST STDPSFs, WebbPSF DET_SAMP images). The
PSF centre is the array centre, ((n−1)/2, (n−1)/2) in 0-based pixel indices:
a pixel centre for odd sizes, a pixel corner for even sizes (the WebbPSF and
STDPSF conventions).

Rendering rule (DESIGN.md, "Known traps"): an effective PSF already contains
the detector pixel; convolve the image integrated over detector pixels with it
(or sample it at detector pixel centres), do not integrate over the pixel again.
An optical PSF (``effective=False``) is convolved with the oversampled image
before binning to detector pixels.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import hashlib
import json
import logging
import math
import os
import re
import tempfile
from pathlib import Path

import numpy as np
from astropy.io import fits

from .constants import ARCSEC_PER_RAD
from .errors import ConfigError, require

__all__ = [
    "PSF",
    "load_psf_fits",
    "diffraction_psf",
    "resample_psf",
    "sample_psf",
    "fwhm_arcsec",
    "recenter_half_pixel",
    "psf_for_band",
    "default_cache_dir",
    "TELESCOPE_DIAMETER_M",
]

# ----------------------------------------------------------------------------
# The record
# ----------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True, eq=False)
class PSF:
    """A pixelised PSF.

    Attributes:
        array: 2-D float64, unit sum; centre at ((n0−1)/2, (n1−1)/2).
        pixel_arcsec: pixel scale of ``array``.
        effective: True when the detector pixel response is already included.
        source: where it came from (file and HDU, or the diffraction model).
        detector_pixel_arcsec: the detector pixel the PSF was made for, when
            known (e.g. 4 x pixel_arcsec for a 4x oversampled file), else None.
    """

    array: np.ndarray
    pixel_arcsec: float
    effective: bool
    source: str = ""
    detector_pixel_arcsec: float | None = None
    scale_key: str = ""             # where pixel_arcsec came from (a header keyword), if known

    def __post_init__(self):
        arr = np.array(self.array, dtype=np.float64)  # a private copy
        setting = "psf"
        require(arr.ndim == 2, setting, f"array of shape {arr.shape}", "a 2-D PSF image")
        require(arr.size > 0, setting, "empty array", "a non-empty 2-D PSF image")
        require(np.all(np.isfinite(arr)), setting, f"{self.source or 'array'} with NaN or inf", "finite PSF values")
        total = float(arr.sum())
        require(total > 0, setting, f"{self.source or 'array'} with sum {total}", "a PSF with positive total flux")
        require(
            isinstance(self.pixel_arcsec, (int, float, np.floating)) and math.isfinite(self.pixel_arcsec) and self.pixel_arcsec > 0,
            "psf_pixel_arcsec",
            self.pixel_arcsec,
            "a positive pixel scale in arcsec",
        )
        arr /= total
        arr.setflags(write=False)
        object.__setattr__(self, "array", arr)
        object.__setattr__(self, "pixel_arcsec", float(self.pixel_arcsec))
        object.__setattr__(self, "effective", bool(self.effective))

    @property
    def center(self) -> tuple[float, float]:
        """The PSF centre in 0-based pixel indices (axis 0, axis 1): the array centre."""
        n0, n1 = self.array.shape
        return ((n0 - 1) / 2.0, (n1 - 1) / 2.0)

    @property
    def shape(self) -> tuple[int, int]:
        return self.array.shape


# ----------------------------------------------------------------------------
# FITS files
# ----------------------------------------------------------------------------

# Detector pixel scales [arcsec] for STDPSF files, whose headers carry none;
# recognised from the file name (Anderson's naming, e.g. PSFSTD_ACSWFC_F606W).
# ACS/WFC 0.05" and WFC3/UVIS 0.0395" (instrument handbooks); WFC3/IR pixels are
# 0.135" x 0.121", geometric mean 0.128".
_STDPSF_DETECTOR_PIXEL_ARCSEC = {
    "ACSWFC": 0.05,
    "ACSHRC": 0.025,
    "WFC3UV": 0.0395,
    "WFC3IR": 0.128,
    "WFPC2": 0.1,
}
_STDPSF_OVERSAMPLING = 4  # Anderson's standard PSFs: 101 x 101 at 4x (25 detector pixels)

_PIXEL_SCALE_KEYS = ("PIXELSCL", "PIXSCALE", "PIXSCAL", "PIXELSCALE", "PIXSIZE", "PSCALE", "SCALE")


def _header_pixel_arcsec(header) -> float | None:
    """Pixel scale in arcsec from the usual keywords, or None."""
    found = _header_pixel_scale(header)
    return None if found is None else found[0]


def _header_pixel_scale(header) -> tuple[float, str] | None:
    """(pixel scale in arcsec, the keyword it came from), or None."""
    for key in _PIXEL_SCALE_KEYS:
        if key in header:
            try:
                value = float(header[key])
            except (TypeError, ValueError):
                continue
            if math.isfinite(value) and value > 0:
                return value, key
    # WCS: CDELT or CD in degrees (the FITS default unit for celestial axes).
    for key in ("CDELT1", "CD1_1"):
        if key in header:
            try:
                value = abs(float(header[key]))
            except (TypeError, ValueError):
                continue
            unit = str(header.get("CUNIT1", "deg")).strip().lower()
            factor = {"deg": 3600.0, "arcmin": 60.0, "arcsec": 1.0, "mas": 1e-3}.get(unit)
            if factor and value > 0:
                return value * factor, key
    return None


def _first_image_hdu(hdul) -> int:
    for i, hdu in enumerate(hdul):
        if hdu.data is not None and getattr(hdu.data, "ndim", 0) >= 2:
            return i
    raise ConfigError("psf", hdul.filename(), "a FITS file with a 2-D PSF image (or an STDPSF cube)")


def _is_stdpsf(header, data) -> bool:
    return data.ndim == 3 and "NXPSFS" in header and "NYPSFS" in header


def _stdpsf_select(header, cube, detector_xy) -> tuple[np.ndarray, tuple[float, float]]:
    """The PSF of an STDPSF cube nearest to detector_xy (default: the detector centre).

    The cube holds NXPSFS x NYPSFS PSFs at detector positions IPSFXnn (x) and
    JPSFYnn (y); PSF number k = i + NXPSFS·j (x varies fastest).
    """
    nx, ny = int(header["NXPSFS"]), int(header["NYPSFS"])
    xs = np.array([float(header[f"IPSFX{i + 1:02d}"]) for i in range(nx)])
    ys = np.array([float(header[f"JPSFY{j + 1:02d}"]) for j in range(ny)])
    require(cube.shape[0] == nx * ny, "psf", f"cube with {cube.shape[0]} planes", f"NXPSFS x NYPSFS = {nx * ny} planes")
    if detector_xy is None:
        # The detector spans the grid of PSF positions (first to last fiducial point).
        detector_xy = (0.5 * (xs.min() + xs.max()), 0.5 * (ys.min() + ys.max()))
    gx, gy = np.meshgrid(xs, ys, indexing="xy")  # shape (ny, nx): k = i + nx j
    dist2 = (gx - detector_xy[0]) ** 2 + (gy - detector_xy[1]) ** 2
    k = int(np.argmin(dist2.ravel()))  # ties: the first (lowest k)
    return cube[k], (float(gx.ravel()[k]), float(gy.ravel()[k]))


def load_psf_fits(
    path,
    *,
    pixel_arcsec: float | None = None,
    effective: bool | None = None,
    hdu: int | str | None = None,
    detector_pixel_arcsec: float | None = None,
    detector_xy: tuple[float, float] | None = None,
    recenter: bool = False,
) -> PSF:
    """Read a PSF from a FITS file.

    Supported layouts (decided from the headers):

    * HST STDPSF (Anderson): a cube of NXPSFS x NYPSFS effective PSFs, each
      101 x 101 at 4x oversampling (header without END card). The PSF nearest
      to ``detector_xy`` (detector pixels; default the detector centre) is
      taken; pixel scale = detector pixel / 4 with the detector pixel from
      ``detector_pixel_arcsec`` or recognised from the file name (ACSWFC 0.05",
      WFC3IR 0.128", WFC3UV 0.0395"); effective = True.
    * WebbPSF output: PIXELSCL in the header; OVERSAMP > 1 marks an oversampled
      optical PSF (effective = False: no detector pixel in it), OVERSAMP = 1 or
      EXTNAME DET_SAMP a detector-sampled PSF (binned from the oversampled one,
      i.e. integrated over detector pixels: effective = True). The detector
      pixel is PIXELSCL x OVERSAMP.
    * Any other 2-D image: pixel scale from PIXELSCL / PIXSCALE / CDELT1 / CD1_1
      or ``pixel_arcsec``; effective from ``effective`` (default False).

    ``hdu`` picks the HDU (index or EXTNAME); default the first with image data
    (for the two-HDU WebbPSF files, HDU 0: the 4x oversampled optical PSF).
    Explicit ``pixel_arcsec`` and ``effective`` arguments override the headers.
    ``recenter=True`` trims rows/columns so that the array centre lands on the
    PSF core to the nearest half pixel (see ``recenter_half_pixel``); use it for
    files whose PSF is not centred on the array centre (e.g. the pre-flight
    ``WebbPSF_F{115,150,200}W_trunc.fits``, peaked on pixel (40, 40) of 80 x 80).
    The array is normalised to unit sum (STDPSFs sum to ≈ 16 at 4x).

    Raises ConfigError (setting ``psf``) for a missing/unreadable file, a PSF
    that is not 2-D, has NaN/inf or a non-positive sum, and (setting
    ``psf_pixel_arcsec``) when no pixel scale is known.
    """
    path = Path(path)
    require(path.is_file(), "psf", str(path), "an existing FITS file")
    with _quiet_fits():
        try:
            hdul_ctx = fits.open(path, ignore_missing_end=True, memmap=False)
        except Exception as exc:  # astropy raises OSError and others for non-FITS
            raise ConfigError("psf", str(path), f"a readable FITS file ({exc})") from exc
        try:
            image_hdu = _read_image_hdu(hdul_ctx, hdu, path)
        except ConfigError:
            raise
        except Exception as exc:  # truncated or corrupt data: astropy raises OSError, ValueError...
            raise ConfigError("psf", str(path), f"a complete, readable FITS file ({exc})") from exc
    index, header, data, primary = image_hdu
    return _finish_load(path, index, header, data, primary, pixel_arcsec, effective,
                        detector_pixel_arcsec, detector_xy, recenter)


def _read_image_hdu(hdul_ctx, hdu, path: Path):
    """(index, header, data as float64, primary header) of the PSF's HDU."""
    with hdul_ctx as hdul:
        if hdu is None:
            index = _first_image_hdu(hdul)
        else:
            try:
                index = hdul.index_of(hdu)
                hdul[index]
            except (KeyError, IndexError) as exc:
                raise ConfigError("psf_hdu", hdu, f"an HDU of {path.name} (it has {len(hdul)})") from exc
        header = hdul[index].header
        data = hdul[index].data
        require(data is not None, "psf", f"{path.name}[{index}] without data", "an image HDU")
        return index, header, np.asarray(data, dtype=np.float64), hdul[0].header


def _finish_load(path, index, header, data, primary, pixel_arcsec, effective, detector_pixel_arcsec,
                 detector_xy, recenter) -> PSF:
    """The PSF record of an HDU's data: layout, pixel scale and its origin (see load_psf_fits)."""
    source = f"{path.name}[{index}]"
    scale_key = "" if pixel_arcsec is None else "psf_pixel_arcsec"
    if _is_stdpsf(header, data):
        image, (x, y) = _stdpsf_select(header, data, detector_xy)
        source += f" STDPSF at detector (x, y) = ({x:.0f}, {y:.0f})"
        if detector_pixel_arcsec is None:
            detector_pixel_arcsec = _stdpsf_detector_pixel(path.name)
        if pixel_arcsec is None and detector_pixel_arcsec is not None:
            pixel_arcsec = detector_pixel_arcsec / _STDPSF_OVERSAMPLING
            scale_key = "the STDPSF detector pixel / 4"
        if effective is None:
            effective = True
    else:
        require(data.ndim == 2, "psf", f"{source} with shape {data.shape}", "a 2-D PSF image")
        image = data
        found = _header_pixel_scale(header) or (_header_pixel_scale(primary) if index else None)
        header_scale = None if found is None else found[0]
        oversamp = _int_or_none(header.get("OVERSAMP"))
        if pixel_arcsec is None and found is not None:
            pixel_arcsec, scale_key = found
        if detector_pixel_arcsec is None and header_scale is not None and oversamp:
            detector_pixel_arcsec = header_scale * oversamp
        if effective is None:
            extname = str(header.get("EXTNAME", "")).upper()
            if "DET_SAMP" in extname or (oversamp == 1 and "DET_SAMP" in header):
                effective = True
            else:
                effective = False
    if recenter:
        image, shift = recenter_half_pixel(image)
        if shift != (0, 0):
            source += f" recentred (trimmed {shift})"
    if pixel_arcsec is None:
        raise ConfigError("psf_pixel_arcsec", None, f"the PSF pixel scale in arcsec (no pixel-scale keyword in {path.name})")
    return PSF(
        array=image,
        pixel_arcsec=pixel_arcsec,
        effective=effective,
        source=source,
        detector_pixel_arcsec=detector_pixel_arcsec,
        scale_key=scale_key,
    )


def recenter_half_pixel(image: np.ndarray, *, radius_fwhm: float = 1.5, threshold_px: float = 0.375):
    """Trim an image so that its centre ((n−1)/2) is the PSF core to ½ pixel.

    The core centroid is measured iteratively within ``radius_fwhm`` FWHM of
    the peak; on each axis whose centroid lies more than ``threshold_px`` from
    the array centre, k = round(2·offset) rows are removed from one side, which
    moves the array centre by k/2 pixels. Only whole pixels are removed (no
    interpolation). The threshold is deliberately above ¼ pixel: real PSF cores
    are asymmetric at the 0.1–0.3 pixel level, which is not a centring error.

    Returns (trimmed image, (k0, k1)) with k > 0 meaning rows removed at the start.
    """
    a = np.asarray(image, dtype=np.float64)
    fwhm_pix = fwhm_arcsec(PSF(a, 1.0, False))
    r = max(radius_fwhm * fwhm_pix, 1.5)
    idx0, idx1 = np.indices(a.shape)
    c = np.array(np.unravel_index(np.argmax(a), a.shape), dtype=float)
    for _ in range(20):
        m = (idx0 - c[0]) ** 2 + (idx1 - c[1]) ** 2 < r**2
        w = a * m
        new = np.array([(w * idx0).sum(), (w * idx1).sum()]) / w.sum()
        if np.allclose(new, c, atol=1e-6):
            break
        c = new
    shifts = []
    for axis, n in enumerate(a.shape):
        offset = c[axis] - (n - 1) / 2.0
        k = int(np.round(2.0 * offset)) if abs(offset) > threshold_px else 0
        shifts.append(k)
        sl = [slice(None), slice(None)]
        sl[axis] = slice(k, None) if k > 0 else slice(0, n + k if k < 0 else None)
        a = a[tuple(sl)]
    return a, (shifts[0], shifts[1])


def _stdpsf_detector_pixel(name: str) -> float | None:
    key = re.sub(r"[^A-Z0-9]", "", name.upper())
    for tag, scale in _STDPSF_DETECTOR_PIXEL_ARCSEC.items():
        if tag in key:
            return scale
    return None


def _int_or_none(value) -> int | None:
    try:
        return int(value)
    except (TypeError, ValueError):
        return None


@contextlib.contextmanager
def _quiet_fits():
    """STDPSF files trip astropy's padding warning; it says nothing useful here."""
    import warnings

    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="Unexpected extra padding")
        yield


# ----------------------------------------------------------------------------
# Resampling
# ----------------------------------------------------------------------------


def _overlap_matrix(n_in: int, pitch_in: float, n_out: int, pitch_out: float,
                    shift: float = 0.0) -> np.ndarray:
    """Fraction of input pixel i that falls in output pixel j, shape (n_out, n_in)
    (`pixels.overlap_matrix` on two grids centred on 0: edges at (k − n/2)·pitch, so the
    array centres coincide; the output's moved by `shift`, in the input's units)."""
    from .pixels import overlap_matrix
    return overlap_matrix((np.arange(n_in + 1) - n_in / 2.0) * pitch_in,
                          (np.arange(n_out + 1) - n_out / 2.0) * pitch_out + shift,
                          src_pixel=pitch_in)


def resample_psf(psf: PSF, target_pixel_arcsec: float, *, size: int | None = None,
                 shift_arcsec: tuple = (0.0, 0.0)) -> np.ndarray:
    """The PSF on a grid of pitch ``target_pixel_arcsec``, flux-conserving.

    The output has an odd number of pixels per axis (``size``, or by default the
    smallest odd number covering the whole input) and its central pixel is
    centred on the PSF centre, or ``shift_arcsec`` (x, y) from it (the kernel a
    little way off its nodes: `model.detector.psf_kernel`). Each output pixel
    receives the area overlap of the input pixels (treated as piecewise
    constant), computed with separable overlap matrices, so any ratio of pixel
    scales works and the total is conserved; the result is renormalised to unit
    sum (which only matters when ``size``, or the shift, cuts off some of the PSF).

    Note: for an *effective* PSF, area-averaging onto coarser pixels blurs it by
    the target pixel once more; to get a detector-pixel kernel from an
    oversampled effective PSF, sample it at detector pixel centres instead
    (``sample_psf``).
    """
    require(
        isinstance(target_pixel_arcsec, (int, float, np.floating)) and math.isfinite(target_pixel_arcsec) and target_pixel_arcsec > 0,
        "target_pixel_arcsec",
        target_pixel_arcsec,
        "a positive pixel scale in arcsec",
    )
    n0, n1 = psf.array.shape
    p = psf.pixel_arcsec
    if size is None:
        extent = max(n0, n1) * p
        m = int(math.ceil(extent / target_pixel_arcsec - 1e-9))
        size = m if m % 2 == 1 else m + 1
    require(
        isinstance(size, (int, np.integer)) and size >= 1 and size % 2 == 1,
        "psf_size",
        size,
        "an odd number of pixels >= 1",
    )
    w0 = _overlap_matrix(n0, p, int(size), target_pixel_arcsec, shift_arcsec[1])
    w1 = _overlap_matrix(n1, p, int(size), target_pixel_arcsec, shift_arcsec[0])
    out = w0 @ psf.array @ w1.T
    total = out.sum()
    require(total > 0, "psf_size", size, "a kernel large enough to hold some of the PSF flux")
    return out / total


def sample_psf(psf: PSF, target_pixel_arcsec: float, *, size: int | None = None,
               shift_arcsec: tuple = (0.0, 0.0)) -> np.ndarray:
    """Point-sample the PSF at the pixel centres of an odd target grid (moved by
    ``shift_arcsec`` (x, y) from the PSF centre where given).

    The right operation for an *effective* PSF (which already holds the
    detector pixel integral at every position): its value at a detector pixel
    centre is that pixel's response, so a detector-pixel kernel is a set of
    samples, not an area average. Samples are taken by cubic-spline
    interpolation at centre + j·target_pixel (exact at the input nodes, so an
    odd STDPSF at 4x gives every 4th pixel unchanged). The output has ``size``
    pixels per axis (odd; default the largest odd grid inside the input) and
    unit sum.
    """
    from scipy import ndimage

    require(
        isinstance(target_pixel_arcsec, (int, float, np.floating)) and math.isfinite(target_pixel_arcsec) and target_pixel_arcsec > 0,
        "target_pixel_arcsec",
        target_pixel_arcsec,
        "a positive pixel scale in arcsec",
    )
    step = target_pixel_arcsec / psf.pixel_arcsec  # input pixels per target pixel
    c0, c1 = psf.center
    if size is None:
        half = int(math.floor(min(c0, c1) / step + 1e-9))
        size = 2 * half + 1
    require(isinstance(size, (int, np.integer)) and size >= 1 and size % 2 == 1, "psf_size", size, "an odd number of pixels >= 1")
    offsets = (np.arange(size) - (size - 1) / 2.0) * step
    g0, g1 = np.meshgrid(c0 + offsets + shift_arcsec[1] / psf.pixel_arcsec,
                         c1 + offsets + shift_arcsec[0] / psf.pixel_arcsec, indexing="ij")
    out = ndimage.map_coordinates(psf.array, [g0, g1], order=3, mode="constant", cval=0.0)
    total = out.sum()
    require(total > 0, "psf_size", size, "a kernel large enough to hold some of the PSF flux")
    return out / total


def rotate_psf(psf: PSF, angle_rad: float) -> PSF:
    """The PSF seen in a frame whose axes are turned by −angle_rad from its own: for a
    band whose pixel axes are turned by angle_rad (counter-clockwise) from the fit
    frame's, the PSF image (given along the band's pixels) on the fit frame's axes.

    Cubic-spline interpolation at the input's pixel scale, on an odd square that holds
    the whole rotated input; values clipped at 0 (spline ringing) and renormalised to
    unit sum. An identity for angle_rad = 0 (up to the padding)."""
    from scipy import ndimage

    from .pixels import rotation_matrix
    n0, n1 = psf.array.shape
    size = int(math.ceil(math.hypot(n0, n1)))
    size += 1 - size % 2
    c = (size - 1) / 2.0
    c0, c1 = psf.center
    # output pixel (row j, column i) at frame offset v = (i − c, j − c) reads the input at
    # u = Rᵀ v along the band's axes
    j, i = np.mgrid[:size, :size] - c
    x_in, y_in = np.einsum("ba,bjk->ajk", rotation_matrix(angle_rad), np.stack([i, j]))
    out = ndimage.map_coordinates(psf.array, [c0 + y_in, c1 + x_in], order=3, mode="constant",
                                  cval=0.0)
    out = np.clip(out, 0.0, None)
    return PSF(array=out, pixel_arcsec=psf.pixel_arcsec, effective=psf.effective,
               source=f"{psf.source} rotated by {math.degrees(angle_rad):.3f} deg",
               detector_pixel_arcsec=psf.detector_pixel_arcsec, scale_key=psf.scale_key)


# ----------------------------------------------------------------------------
# Diagnostics
# ----------------------------------------------------------------------------


def fwhm_arcsec(psf: PSF, *, upsample: int = 8) -> float:
    """FWHM [arcsec] from the area above half maximum: 2 sqrt(A/π).

    The array is first upsampled ``upsample`` x by cubic-spline interpolation
    so that the half-maximum contour is resolved for well-sampled PSFs. For a
    Gaussian and an Airy core alike this equals the usual FWHM.
    """
    from scipy import ndimage

    arr = psf.array
    c0, c1 = (np.array(arr.shape) - 1) // 2
    half = 24  # only the core matters; keeps the upsampling cheap
    core = arr[max(c0 - half, 0) : c0 + half + 1, max(c1 - half, 0) : c1 + half + 1]
    fine = ndimage.zoom(core, upsample, order=3)
    peak = fine.max()
    area_pix = np.count_nonzero(fine >= 0.5 * peak)
    # zoom maps the first and last samples onto each other: (n − 1) input pixels span
    # (m − 1) output ones, not 1/upsample each (6 % too wide a FWHM for a 15-pixel PSF)
    step = [(n - 1) / (m - 1) for n, m in zip(core.shape, fine.shape)]
    area = area_pix * step[0] * step[1] * psf.pixel_arcsec**2
    return float(2.0 * math.sqrt(area / math.pi))


# ----------------------------------------------------------------------------
# Built-in diffraction PSFs (poppy)
# ----------------------------------------------------------------------------

# Diameters used for λ/D (the circumscribed JWST aperture is 6.6 m; the
# commonly quoted effective diameter 6.5 m).
TELESCOPE_DIAMETER_M = {"JWST": 6.5, "HST": 2.4}
_PUPIL_MODEL_VERSION = "1"  # bump when the pupil or the method changes (cache key)


def _telescope(instrument: str) -> str:
    name = instrument.strip().upper()
    if name.startswith("JWST") or "NIRCAM" in name:
        return "JWST"
    if name.startswith("HST") or name.replace("-", "").replace("/", "").startswith(("ACS", "WFC3")):
        return "HST"
    raise ConfigError("instrument", instrument, "one of HST/ACS, HST/WFC3-IR, JWST/NIRCam")


def _pupil(telescope: str):
    """Analytic pupil as poppy optics.

    JWST: 18 hexagonal segments (flat-to-flat 1.32 m, gaps 7 mm, no central
    segment) with a 0.74 m-diameter secondary obscuration on three 0.1 m struts.
    HST: 2.4 m circular primary, secondary obscuration of 0.33 of the diameter
    (radius 0.396 m), four 0.0264 m spiders at 45°.
    """
    import poppy

    optic = _kept_transmission_optic()
    if telescope == "JWST":
        return optic(
            opticslist=[
                poppy.MultiHexagonAperture(rings=2, flattoflat=1.32, gap=0.007, segmentlist=list(range(1, 19))),
                poppy.SecondaryObscuration(secondary_radius=0.37, n_supports=3, support_width=0.1),
            ],
            name="JWST-like segmented pupil",
        ), 6.6
    return optic(
        opticslist=[
            poppy.CircularAperture(radius=1.2),
            poppy.SecondaryObscuration(secondary_radius=0.396, n_supports=4, support_width=0.0264, support_angle_offset=45.0),
        ],
        name="HST-like pupil",
    ), 2.4


@functools.cache
def _kept_transmission_optic():
    """poppy's CompoundAnalyticOptic, keeping the transmission it computes for a wavefront
    grid: a pupil's transmission depends on the pupil-plane grid (shape and metres per
    pixel), not on the wavelength, yet poppy evaluates the analytic apertures anew for each
    of a band's wavelengths (~40 % of a diffraction PSF's time). The same values, computed
    once per grid and optic."""
    import poppy

    class KeptTransmissionOptic(poppy.CompoundAnalyticOptic):
        def get_transmission(self, wave):
            key = (tuple(wave.shape), str(wave.pixelscale), str(wave.planetype),
                   getattr(wave, "oversample", None))
            kept = self.__dict__.setdefault("_kept_transmission", {})
            if key not in kept:
                kept[key] = super().get_transmission(wave)
            return kept[key]

    return KeptTransmissionOptic


def _band_sampling(wavelength_aa: np.ndarray, throughput: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """n wavelengths [m] and weights for a photon-counting detector.

    The band (where the cumulative T·λ weight lies between 0.5 % and 99.5 %) is
    cut into n equal-width bins; each bin contributes its integrated T·λ at its
    T·λ-weighted mean wavelength.
    """
    w = throughput * wavelength_aa
    cum = np.concatenate([[0.0], np.cumsum(0.5 * (w[1:] + w[:-1]) * np.diff(wavelength_aa))])
    cum /= cum[-1]
    lo, hi = np.interp([0.005, 0.995], cum, wavelength_aa)
    edges = np.linspace(lo, hi, n + 1)
    fine = np.linspace(lo, hi, 40 * n + 1)
    wf = np.interp(fine, wavelength_aa, w)
    waves, weights = [], []
    for a, b in zip(edges[:-1], edges[1:]):
        sel = (fine >= a) & (fine <= b)
        x, y = fine[sel], wf[sel]
        mass = np.trapezoid(y, x)
        waves.append(np.trapezoid(y * x, x) / mass if mass > 0 else 0.5 * (a + b))
        weights.append(mass)
    weights = np.array(weights)
    keep = weights > 0
    return np.array(waves)[keep] * 1e-10, weights[keep] / weights[keep].sum()


def default_cache_dir() -> Path | bool:
    """$CLUMPYLEN_CACHE/psf if set, else ~/.cache/clumpylen_jax/psf; False (no caching)
    when CLUMPYLEN_NO_CACHE is set (`clumpylen_jax.cache`)."""
    from .cache import cache_enabled, cache_root
    return cache_root() / "psf" if cache_enabled() else False


def diffraction_psf(
    instrument: str,
    filter_name,
    *,
    pixel_arcsec: float,
    size_arcsec: float | None = None,
    cache_dir=None,
    n_wavelengths: int = 9,
    pupil_npix: int = 256,
) -> PSF:
    """A polychromatic diffraction PSF from an analytic pupil (poppy), cached on disk.

    Args:
        instrument: "JWST/NIRCam", "HST/ACS" or "HST/WFC3-IR" (picks the pupil).
        filter_name: band name (e.g. "F200W") or a ``filters.Filter``; its
            throughput weights the wavelengths (T·λ, photon counting).
        pixel_arcsec: pixel scale of the result (typically the detector pixel
            over an oversampling factor).
        size_arcsec: field of view; default 32 λ_pivot/D (≈ 98 % of the light of
            an unobscured aperture). Rounded up to an odd number of pixels.
        cache_dir: default ``default_cache_dir()``; ``False`` disables caching.
        n_wavelengths: wavelengths across the band.
        pupil_npix: pupil sampling (pixels across the aperture).

    Returns an optical PSF (``effective=False``): each value is the PSF
    integrated over that pixel (computed by matrix Fourier transforms on a
    sub-grid no coarser than λ_min/(4D), then binned), unit sum over the array,
    centred on the central pixel. Requires the ``poppy`` package.

    The cache key is a hash of every input (pupil model version, throughput
    curve, sampling); files are written atomically, so concurrent runs are safe.
    """
    telescope = _telescope(instrument)
    require(
        isinstance(pixel_arcsec, (int, float, np.floating)) and math.isfinite(pixel_arcsec) and pixel_arcsec > 0,
        "psf_pixel_arcsec",
        pixel_arcsec,
        "a positive pixel scale in arcsec",
    )
    require(isinstance(n_wavelengths, int) and 1 <= n_wavelengths <= 64, "n_wavelengths", n_wavelengths, "an integer in [1, 64]")
    band = _instrument_filter(instrument, filter_name)
    diameter_m = TELESCOPE_DIAMETER_M[telescope]
    waves_m, weights = _band_sampling(np.asarray(band.wavelength_aa), np.asarray(band.throughput), n_wavelengths)
    lam_over_d_arcsec = float(band.pivot_wavelength_aa) * 1e-10 / diameter_m * ARCSEC_PER_RAD
    n_pix = _psf_pixels(32.0 * lam_over_d_arcsec if size_arcsec is None else size_arcsec, pixel_arcsec)
    sub = _subsampling(pixel_arcsec, waves_m, diameter_m)

    key = _diffraction_key(telescope, pupil_npix, waves_m, weights, pixel_arcsec, n_pix, sub)
    source = f"poppy diffraction PSF {telescope} {band.name} ({len(waves_m)} wavelengths)"
    cache_path = _psf_cache_path(cache_dir, telescope, band.name, key)
    if cache_path is not None and cache_path.is_file():
        try:
            return PSF(np.load(cache_path), pixel_arcsec, False, source + " [cached]", None)
        except (OSError, ValueError, ConfigError):
            pass  # a corrupt cache file is recomputed and replaced
    array = _compute_diffraction(telescope, waves_m, weights, pixel_arcsec, n_pix, sub, pupil_npix)
    if cache_path is not None:
        _atomic_save_npy(cache_path, array)
    return PSF(array, pixel_arcsec, False, source, None)


def _instrument_filter(instrument: str, filter_name):
    """The filter curve of `filter_name` (a band name or a ``filters.Filter``) on `instrument`."""
    from .filters import load_filter

    # A bare band name is qualified with the instrument so that the curve is the
    # instrument's own (filters.load_filter accepts "JWST/NIRCam F200W").
    is_bare = isinstance(filter_name, str) and "/" not in filter_name and " " not in filter_name.strip()
    return load_filter(f"{instrument} {filter_name.strip()}" if is_bare else filter_name)


def _psf_pixels(size_arcsec, pixel_arcsec: float) -> int:
    """Pixels across a PSF of field size_arcsec at pixel_arcsec, rounded up to odd (≤ 2049)."""
    require(
        isinstance(size_arcsec, (int, float, np.floating)) and math.isfinite(size_arcsec) and size_arcsec > 0,
        "psf_size_arcsec",
        size_arcsec,
        "a positive field of view in arcsec",
    )
    n_pix = int(math.ceil(size_arcsec / pixel_arcsec - 1e-9))
    n_pix += 1 - n_pix % 2
    require(n_pix <= 2049, "psf_size_arcsec", size_arcsec, f"at most 2049 pixels of {pixel_arcsec} arcsec")
    return n_pix


def _subsampling(pixel_arcsec: float, waves_m, diameter_m: float) -> int:
    """Computed points per pixel side, so that each is ≤ λ_min/(4D): the binned values
    are then pixel integrals, not point samples, even for coarse pixels."""
    lam_min_over_d = waves_m.min() / diameter_m * ARCSEC_PER_RAD
    return max(1, int(math.ceil(pixel_arcsec / (lam_min_over_d / 4.0) - 1e-9)))


def _psf_cache_path(cache_dir, telescope: str, band_name: str, key: str) -> Path | None:
    """The PSF's cache file; None when caching is off (cache_dir False, or None and
    `default_cache_dir()` False)."""
    if cache_dir is None:
        cache_dir = default_cache_dir()
    if cache_dir is False:
        return None
    return Path(cache_dir) / f"{telescope}_{band_name}_{key}.npy"


def _diffraction_key(telescope, pupil_npix, waves_m, weights, pixel_arcsec, n_pix, sub) -> str:
    """Cache key of a diffraction PSF: a hash of every input (pupil model version, sampled
    wavelengths [m] and weights to 10 digits, pixels, sub-sampling, poppy version)."""
    key_data = {
        "telescope": telescope,
        "pupil": _PUPIL_MODEL_VERSION,
        "pupil_npix": pupil_npix,
        "waves_m": [float(f"{x:.9e}") for x in waves_m],
        "weights": [float(f"{x:.9e}") for x in weights],
        "pixel_arcsec": float(pixel_arcsec),
        "n_pix": n_pix,
        "sub": sub,
        "poppy": _poppy_version(),
    }
    return hashlib.sha256(json.dumps(key_data, sort_keys=True).encode()).hexdigest()[:24]


def _poppy_version() -> str:
    # from the installed package's metadata: importing poppy (scipy.signal, ...) costs
    # ~1 s, which a cached PSF does not need
    from importlib.metadata import PackageNotFoundError, version
    try:
        return version("poppy")
    except PackageNotFoundError as exc:
        raise ConfigError("psf", "diffraction", "the poppy package (pip install poppy) for built-in diffraction PSFs") from exc


def _compute_diffraction(telescope, waves_m, weights, pixel_arcsec, n_pix, sub, pupil_npix) -> np.ndarray:
    import poppy

    logging.getLogger("poppy").setLevel(logging.WARNING)
    optic, pupil_diameter_m = _pupil(telescope)
    osys = poppy.OpticalSystem(npix=pupil_npix, oversample=2, pupil_diameter=pupil_diameter_m, verbose=False)
    osys.add_pupil(optic)
    osys.add_detector(pixelscale=pixel_arcsec / sub, fov_pixels=n_pix * sub, oversample=1)
    hdul = osys.calc_psf(source={"wavelengths": waves_m, "weights": weights}, normalize="first")
    fine = np.asarray(hdul[0].data, dtype=np.float64)
    # poppy centres an N-pixel detector on (N−1)/2; binning sub x sub blocks of
    # an (n·sub)-grid keeps that point at the centre of the central coarse pixel.
    return fine.reshape(n_pix, sub, n_pix, sub).sum(axis=(1, 3))


def _atomic_save_npy(path: Path, array: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=path.name + ".", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            np.save(fh, array)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


# ----------------------------------------------------------------------------
# Scene hook
# ----------------------------------------------------------------------------


def psf_for_band(
    spec,
    *,
    instrument: str,
    filter_name: str,
    detector_pixel_arcsec: float,
    psf_pixel_arcsec: float | None = None,
    oversampling: int = 4,
    base_dir=None,
    cache_dir=None,
    setting: str = "psf",
    grid_oversampling: int | None = None,
) -> PSF | None:
    """Resolve a band's ``psf`` setting (SCENE.md): "none", "diffraction" or a path.

    "none" (or None) → None; "diffraction" → ``diffraction_psf`` at
    detector_pixel / oversampling; otherwise a FITS file (relative paths from
    ``base_dir``) read with ``load_psf_fits``, ``psf_pixel_arcsec`` overriding
    or supplying its pixel scale. setting: the scene key errors name (``bands[i].psf``).
    grid_oversampling: the factor of the grid the PSF will act on (detector pixel /
    factor): with it, a file's PSF is checked by ``check_psf_for_band``.
    """
    if spec is None or (isinstance(spec, str) and spec.strip().lower() == "none"):
        return None
    require(isinstance(spec, (str, os.PathLike)), "psf", spec, '"none", "diffraction" or a FITS path')
    if isinstance(spec, str) and spec.strip().lower() == "diffraction":
        return diffraction_psf(
            instrument, filter_name, pixel_arcsec=detector_pixel_arcsec / oversampling, cache_dir=cache_dir
        )
    path = Path(spec)
    if not path.is_absolute() and base_dir is not None:
        path = Path(base_dir) / path
    band = setting.rpartition(".")[0]
    try:
        psf = load_psf_fits(path, pixel_arcsec=psf_pixel_arcsec)
    except ConfigError as exc:   # name the scene key: bands[i].psf, bands[i].psf_pixel_arcsec
        key = f"{band}.{exc.setting}" if band and exc.setting.startswith("psf") else exc.setting
        raise ConfigError(key, exc.value, exc.expected) from exc
    if grid_oversampling is not None:
        check_psf_for_band(psf, detector_pixel_arcsec=detector_pixel_arcsec,
                           grid_pixel_arcsec=detector_pixel_arcsec / grid_oversampling,
                           setting=setting)
    return psf


# A PSF sampled coarser than this many detector pixels is not the band's PSF: most often a
# pixel scale in mas read as arcsec (PIXELSCL = 10 for 10 mas), which would resample a 31²
# file onto a 30 000² kernel
PSF_MAX_PIXEL_RATIO = 2.0
# The largest kernel side (pixels of the grid the PSF acts on): 8191² float64 is 0.5 GB
PSF_MAX_KERNEL_SIDE = 8191


def check_psf_for_band(psf: PSF, *, detector_pixel_arcsec: float, grid_pixel_arcsec: float,
                       setting: str = "psf") -> None:
    """Refuse, before any array is made, a PSF whose pixel scale cannot be this band's, or
    whose kernel on the grid of `grid_pixel_arcsec` would be larger than PSF_MAX_KERNEL_SIDE."""
    band = setting.rpartition(".")[0]
    key = psf.scale_key or "its pixel scale"
    where = f"{psf.source}: {key} = {psf.pixel_arcsec:g} arcsec"
    hint = (f"; a scale in mas read as arcsec? set {band}.psf_pixel_arcsec" if band else "")
    if psf.pixel_arcsec > PSF_MAX_PIXEL_RATIO * detector_pixel_arcsec:
        raise ConfigError(setting, where, f"a PSF sampled at or below {PSF_MAX_PIXEL_RATIO:g} "
                          f"detector pixels ({detector_pixel_arcsec:g}\"){hint}")
    side = math.ceil(max(psf.shape) * psf.pixel_arcsec / grid_pixel_arcsec - 1e-9)
    if side > PSF_MAX_KERNEL_SIDE:
        raise ConfigError(setting, f"{where}, {max(psf.shape)} pixels: a kernel of {side} pixels "
                          f"of {grid_pixel_arcsec:g}\"", f"a PSF at most {PSF_MAX_KERNEL_SIDE} "
                          f"pixels of {grid_pixel_arcsec:g}\" wide (crop the file){hint}")
