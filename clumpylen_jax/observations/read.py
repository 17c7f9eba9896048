"""Read one observed band: image, uncertainty, mask, PSF, units — every check before any compile.

`ObservationSpec` is one `[[observations]]` table (SCENE.md, "Fitting observed
images (v2)"); `read_observation(spec)` returns an `Observation`: the image in
its own units × `scale` (counts → counts/s), its variance σ² (from ERR as σ, WHT
as inverse variance, a separate file, or a noise model σ² = rms² + μ/t refreshed
from the model during the fit), the mask of usable pixels (finite data with
positive finite variance, outside the DS9 regions of `mask`), the PSF (normalised),
the zero point of one data unit (`units.resolve_units`) and the pixel frame.

Every bad input raises ConfigError naming `observations[FILTER].<key>` and the file.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Optional

import numpy as np

from ..errors import ConfigError
from .frame import BandFrame, celestial_wcs, check_pixel_matrix, wcs_pixel_arcsec
from .units import resolve_units

_PIXEL_KEYS = ("PIXSCALE", "PIXELSCL", "PIXSCAL", "PIXSIZE")
_BKG_RMS_KEYS = ("BKG_RMS", "BKGRMS", "BACK_RMS", "SKY_RMS", "SKYRMS")
# σ above this many times a typical σ of the band (its 10th percentile: flagged pixels may be
# most of a cutout, e.g. off the detector, so not the median) marks a pixel left out: pipelines flag
# bad pixels with σ = 1e10, 1e30 or the float maximum rather than NaN. No real pixel comes
# near it (a saturated star's Poisson σ is ~10³ × the sky's), and keeping such pixels would
# count them as degrees of freedom that carry no information (χ²/dof biased low) and
# square σ towards overflow.
HUGE_SIGMA_FACTOR = 1.0e6


@dataclasses.dataclass(frozen=True)
class ObservationSpec:
    """One [[observations]] table, paths resolved. See SCENE.md for each key."""

    filter: str
    image: str
    instrument: Optional[str] = None
    hdu: Optional[object] = None
    error: Optional[str] = None          # HDU name of the image file, or a path: 1-σ map
    weight: Optional[str] = None         # HDU name or path: inverse-variance map
    noise: Optional[dict] = None         # {background_rms, exptime_s}
    psf: Optional[str] = None
    psf_hdu: Optional[object] = None
    psf_pixel_arcsec: Optional[float] = None
    psf_effective: Optional[bool] = None
    pixel_arcsec: Optional[float] = None
    pixel_matrix_arcsec: Optional[list] = None   # without a WCS: [[E/x, E/y], [N/x, N/y]] arcsec
    units: Optional[str] = None
    zeropoint_ab: Optional[float] = None
    exptime_s: Optional[float] = None
    mask: Optional[str] = None

    @property
    def where(self) -> str:
        return f"observations[{self.filter}]"


@dataclasses.dataclass(frozen=True)
class Observation:
    """One band ready for fitting (arrays float64 [ny, nx]; see the module doc)."""

    name: str
    path: str
    data: np.ndarray
    variance: np.ndarray             # σ² (1 where masked); with a noise model: rms² only
    mask: np.ndarray                 # bool, True = pixel used
    frame: BandFrame
    zeropoint_ab: float
    units: str
    units_how: str
    psf: Optional[object] = None     # psf.PSF
    noise_exptime_s: Optional[float] = None   # noise model: σ² = variance + max(μ, 0)/t
    instrument: Optional[str] = None
    noise_how: str = ""              # where σ came from (summary.json)
    frame_how: str = ""              # where the orientation came from (summary.json)

    def variance_for(self, model=None):
        """σ² for the likelihood: the map, plus the model's Poisson term with a noise model."""
        if self.noise_exptime_s is None or model is None:
            return self.variance
        return self.variance + np.maximum(np.asarray(model, float), 0.0) / self.noise_exptime_s


def _open(path: str, where: str, key: str):
    from astropy.io import fits
    p = Path(path)
    if not p.is_file():
        raise ConfigError(f"{where}.{key}", str(path), "an existing FITS file")
    try:
        return fits.open(p, memmap=False)
    except Exception as exc:
        raise ConfigError(f"{where}.{key}", str(path), f"a readable FITS file ({exc})") from exc


def find_image_hdu(hdul, path, setting: str, hdu=None, hdu_setting=None) -> int:
    """Index of the image HDU: `hdu` if given, else SCI, else the first 2-D image (also what
    `clumpylen fit SCENE --image` reads). setting / hdu_setting: named in the ConfigError."""
    names = [h.name for h in hdul]
    if hdu is not None:
        try:
            idx = hdul.index_of(hdu)
            hdul[idx]
        except (KeyError, IndexError):
            raise ConfigError(hdu_setting or setting, hdu, f"an HDU of {path} (it has {names})") from None
    elif "SCI" in names:
        idx = names.index("SCI")
    else:
        idx = next((i for i, h in enumerate(hdul) if getattr(h, "data", None) is not None
                    and np.ndim(h.data) == 2), None)
        if idx is None:
            raise ConfigError(setting, path, f"a FITS file with a SCI HDU or a 2-D image (HDUs: {names})")
    data = hdul[idx].data
    if data is None or np.ndim(data) != 2 or min(np.shape(data)) < 2:
        raise ConfigError(setting, f"{path}[{names[idx]}] of shape {np.shape(data)}", "a 2-D image")
    return idx


def _image_hdu(hdul, hdu, path, where, key):
    return find_image_hdu(hdul, path, f"{where}.{key}", hdu, f"{where}.{'hdu' if key == 'image' else key}")


def _plane(ref: str, hdul, path, shape, where, key):
    """A map named by `ref`: an HDU of the image file, or a path (its SCI or first 2-D HDU)."""
    names = [h.name for h in hdul]
    if str(ref).upper() in names and not Path(str(ref)).is_file():
        arr, src = hdul[names.index(str(ref).upper())].data, f"{path}[{str(ref).upper()}]"
    else:
        with _open(ref, where, key) as other:
            arr, src = other[_image_hdu(other, None, ref, where, key)].data, ref
    arr = np.asarray(arr, float) if arr is not None else None
    if arr is None or arr.shape != tuple(shape):
        raise ConfigError(f"{where}.{key}", f"{src} of shape {None if arr is None else arr.shape}",
                          f"a map of the image's shape {tuple(shape)}")
    return arr, src


def _merged_header(hdul, idx):
    h = hdul[0].header.copy()
    if idx:
        h.update({k: v for k, v in hdul[idx].header.items() if k not in ("", "COMMENT", "HISTORY")})
    return h


_PIX2A = ("PIX2A11", "PIX2A12", "PIX2A21", "PIX2A22")


def header_pixel_matrix(header, where, path):
    """(matrix or None, how): the PIX2A11..PIX2A22 pixel-to-angle matrix of a header (arcsec,
    [[E/x, E/y], [N/x, N/y]]). With only the first row (PIX2A11, PIX2A12) the second follows
    from square pixels and the sky's parity: (PIX2A12, −PIX2A11) — the one orthogonal
    completion with det < 0 (a sky image is never mirrored); it is reported as completed."""
    have = [k for k in _PIX2A if k in header]
    if not have:
        return None, None
    try:
        v = {k: float(header[k]) for k in have}
    except (TypeError, ValueError):
        raise ConfigError(f"{where}.pixel_matrix_arcsec", {k: header[k] for k in have},
                          f"numbers in {', '.join(_PIX2A)} of {path}") from None
    if len(have) == 4:
        return [[v["PIX2A11"], v["PIX2A12"]], [v["PIX2A21"], v["PIX2A22"]]], "header PIX2A11..PIX2A22"
    if set(have) == {"PIX2A11", "PIX2A12"}:
        a, b = v["PIX2A11"], v["PIX2A12"]
        return [[a, b], [b, -a]], "header PIX2A11, PIX2A12; second row from square pixels, sky parity"
    raise ConfigError(f"{where}.pixel_matrix_arcsec", f"only {', '.join(have)} in {path}",
                      f"all of {', '.join(_PIX2A)} in the header, or pixel_matrix_arcsec in the "
                      "[[observations]] table")


def _pixel_frame(spec, header, shape, where):
    """BandFrame of the image, and how its orientation was found (for summary.json)."""
    wcs = celestial_wcs(header)
    if wcs is not None:
        pix = wcs_pixel_arcsec(wcs, where)
        return BandFrame(tuple(shape), pix, wcs), "celestial WCS"
    pix = spec.pixel_arcsec
    if pix is None:
        pix = next((float(header[k]) for k in _PIXEL_KEYS if k in header), None)
    if spec.pixel_matrix_arcsec is not None:
        matrix, how = spec.pixel_matrix_arcsec, "pixel_matrix_arcsec (scene)"
    else:
        matrix, how = header_pixel_matrix(header, where, spec.image)
    if matrix is not None:
        matrix = check_pixel_matrix(matrix, pix, f"{where}.pixel_matrix_arcsec")
        if pix is None:
            pix = float(np.sqrt(abs(np.linalg.det(np.asarray(matrix)))))
    if pix is None or not (math.isfinite(pix) and pix > 0):
        raise ConfigError(f"{where}.pixel_arcsec", pix,
                          f"a positive pixel scale in arcsec ({spec.image} has no celestial WCS "
                          "and no PIXSCALE keyword)")
    return (BandFrame(tuple(shape), float(pix), None, matrix),
            how or "no WCS, no pixel matrix: pixel x taken as West, y as North")


def _variance(spec, hdul, data, header, scale, counts_per_unit, where):
    """(σ² map or None, noise-model exptime or None, source), checked."""
    given = [k for k in ("error", "weight", "noise") if getattr(spec, k) is not None]
    if len(given) > 1:
        raise ConfigError(f"{where}", given, "one of error, weight or noise")
    names = [h.name for h in hdul]
    if not given:
        if "ERR" in names:
            given, spec = ["error"], dataclasses.replace(spec, error="ERR")
        elif "WHT" in names:
            given, spec = ["weight"], dataclasses.replace(spec, weight="WHT")
        elif any(k in header for k in _BKG_RMS_KEYS):
            # a product that ships its noise model in the header (BKG_RMS [+ EXPTIME]) and no
            # map: that model is the product's own statement of its noise, not a guess
            given, spec = ["noise"], dataclasses.replace(spec, noise={})
        else:
            raise ConfigError(f"{where}.error", None,
                              f"an uncertainty for {spec.image} (no ERR or WHT HDU): error = "
                              "\"ERR\" | path, weight = \"WHT\" | path, or noise = "
                              "{ background_rms = ..., exptime_s = ... }")
    key = given[0]
    if key == "noise":
        nz = dict(spec.noise)
        bad = [k for k in nz if k not in ("background_rms", "exptime_s")]
        if bad:
            raise ConfigError(f"{where}.noise.{bad[0]}", nz[bad[0]], "background_rms, exptime_s")
        rms, t = noise_from_header(nz, header)
        for name, v, keys in (("background_rms", rms, "/".join(_BKG_RMS_KEYS[:1])),
                              ("exptime_s", t, "EXPTIME")):
            if v is None:
                raise ConfigError(f"{where}.noise.{name}", None,
                                  f"a positive number (give it in the scene or add {keys} to the "
                                  f"header of {spec.image})")
            if not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0:
                raise ConfigError(f"{where}.noise.{name}", v, "a positive number")
        if counts_per_unit is None:
            raise ConfigError(f"{where}.noise", spec.noise,
                              "a count-rate image (units e-/s or counts/s) for a Poisson noise "
                              "model; give an error or weight map for other units")
        var = np.full(data.shape, (float(rms) * scale) ** 2)
        return var, float(t), (f"noise model: background rms {rms} (image units), exptime {t} s"
                               f" ({'scene' if spec.noise else 'header'}"
                               f"{' + header' if spec.noise and len(spec.noise) < 2 else ''})")
    arr, src = _plane(getattr(spec, key), hdul, spec.image, data.shape, where, key)
    use = np.isfinite(data)
    if key == "error":
        if np.any(np.isnan(arr) & use):
            raise ConfigError(f"{where}.error", src, "finite σ wherever the image is finite "
                              "(NaN σ found); mask those pixels or fix the map")
        if np.any(arr < 0):
            raise ConfigError(f"{where}.error", src, "σ ≥ 0 (negative values found)")
        with np.errstate(over="ignore", invalid="ignore"):
            var = (arr * scale) ** 2      # σ = 1e200 overflows to inf: masked below
        return var, None, f"{src} as sigma"
    if np.any(np.isnan(arr) & use) or np.any(arr < 0):
        raise ConfigError(f"{where}.weight", src, "inverse variances ≥ 0 and not NaN")
    with np.errstate(divide="ignore"):
        var = np.where(arr > 0, 1.0 / np.where(arr > 0, arr, 1.0), np.inf) * scale**2
    return var, None, f"{src} as inverse variance"


def noise_from_header(noise: dict, header):
    """(background_rms, exptime_s) of a noise model: the scene's values, each missing one from
    the header (BKG_RMS or an alias; EXPTIME); None where neither gives it."""
    rms = noise.get("background_rms")
    if rms is None:
        rms = next((header[k] for k in _BKG_RMS_KEYS if k in header), None)
    t = noise.get("exptime_s", header.get("EXPTIME"))
    return rms, t


def huge_sigma(var: np.ndarray) -> np.ndarray:
    """True where σ exceeds HUGE_SIGMA_FACTOR × the 10th percentile of the finite positive σ
    (or is infinite): the pixels a pipeline flagged with a huge σ."""
    ok = np.isfinite(var) & (var > 0)
    if not np.any(ok):
        return ~ok
    limit = HUGE_SIGMA_FACTOR**2 * float(np.percentile(var[ok], 10.0))
    return ~np.isfinite(var) | (var > limit)


def _region_mask(path, frame: BandFrame, where):
    """True inside the DS9 regions of `path` (pixel regions, or sky regions with a WCS)."""
    try:
        from regions import Regions
        regs = Regions.read(path, format="ds9")
    except FileNotFoundError:
        raise ConfigError(f"{where}.mask", path, "an existing DS9 region file") from None
    except Exception as exc:
        raise ConfigError(f"{where}.mask", path, f"a readable DS9 region file ({exc})") from None
    out = np.zeros(frame.shape, bool)
    for r in regs:
        if not hasattr(r, "to_mask"):
            if frame.wcs is None:
                raise ConfigError(f"{where}.mask", path,
                                  "pixel regions (sky regions need a celestial WCS)")
            r = r.to_pixel(frame.wcs)
        m = r.to_mask(mode="center").to_image(frame.shape)
        if m is not None:
            out |= m > 0
    return out


def psf_hdu_of(spec, where):
    """The PSF's HDU: `psf_hdu` if given; else the HDU named PSF when the file has one (HST and
    JWST cutouts often carry it beside SCI: `psf` may then be the image file itself); else None
    (the file's first image). The image file without a PSF HDU is an error: its SCI is no PSF."""
    if spec.psf_hdu is not None or not Path(spec.psf).is_file():
        return spec.psf_hdu
    from astropy.io import fits
    try:
        with fits.open(spec.psf, memmap=False, ignore_missing_end=True) as hdul:
            names = [h.name for h in hdul]
    except Exception:
        return None     # load_psf_fits names the unreadable file
    if "PSF" in names:
        return "PSF"
    if Path(spec.psf).resolve() == Path(spec.image).resolve():
        raise ConfigError(f"{where}.psf_hdu", None, f"the HDU of {spec.psf} that holds the PSF "
                          f"(the file is the image itself; it has {names})")
    return None


def _read_psf(spec, where, pixel_arcsec):
    if spec.psf is None:
        return None
    from ..psf import load_psf_fits
    try:
        psf = load_psf_fits(spec.psf, hdu=psf_hdu_of(spec, where), pixel_arcsec=spec.psf_pixel_arcsec,
                            effective=spec.psf_effective)
    except ConfigError as exc:
        raise ConfigError(f"{where}.{exc.setting}", exc.value,
                          f"{exc.expected} (file {spec.psf})") from None
    if psf.pixel_arcsec > 4 * pixel_arcsec or psf.pixel_arcsec * max(psf.shape) > 60:
        raise ConfigError(f"{where}.psf_pixel_arcsec", psf.pixel_arcsec,
                          f"a PSF pixel scale (arcsec) no coarser than the image's "
                          f"({pixel_arcsec:.4g}\") and a PSF under 60\" wide ({spec.psf})")
    return psf


def read_observation(spec: ObservationSpec) -> Observation:
    """Read and check one band (see the module doc)."""
    where = spec.where
    with _open(spec.image, where, "image") as hdul:
        idx = _image_hdu(hdul, spec.hdu, spec.image, where, "image")
        header = _merged_header(hdul, idx)
        data = np.asarray(hdul[idx].data, float)
        frame, frame_how = _pixel_frame(spec, header, data.shape, where)
        u = resolve_units(header, units=spec.units, zeropoint_ab=spec.zeropoint_ab,
                          pixel_arcsec=frame.pixel_arcsec, exptime_s=spec.exptime_s,
                          where=f"{where} ({spec.image})")
        var, noise_t, noise_how = _variance(spec, hdul, data, header, u["scale"],
                                    u["counts_per_unit"], where)
    data = data * u["scale"]
    mask = np.isfinite(data) & np.isfinite(var) & (var > 0) & ~huge_sigma(var)
    if noise_t is not None:
        mask = np.isfinite(data)
    if spec.mask is not None:
        mask &= ~_region_mask(spec.mask, frame, where)
    if not np.any(mask):
        raise ConfigError(f"{where}.image", spec.image,
                          "usable pixels (all are NaN, masked, or have zero/inf variance)")
    if np.ptp(data[mask]) == 0:
        raise ConfigError(f"{where}.image", spec.image, "an image that is not constant")
    data = np.where(mask, data, 0.0)
    var = np.where(mask, var, 1.0)
    psf = _read_psf(spec, where, frame.pixel_arcsec)
    return Observation(spec.filter, spec.image, data, var, mask, frame, u["zeropoint_ab"],
                       str(u["units"]), u["how"], psf, noise_t, spec.instrument, noise_how, frame_how)
