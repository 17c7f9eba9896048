"""Image units → the AB zero point of one data unit per pixel (never a silent guess).

A fit works in the data's own units (the model is linear in flux, so any unit
per pixel will do); what turns a fitted flux F (data units summed over pixels)
into an AB magnitude is the zero point ZP = the AB magnitude of one data unit:

    m_AB = ZP − 2.5 log10 F

Where it comes from, per unit (the first that applies):
- surface brightness "MJy/sr" (JWST i2d): one unit in a pixel of solid angle Ω
  (``PIXAR_SR``, else the pixel scale squared) is 10⁶ Ω Jy, so
  ZP = −2.5 log10(10⁶ Ω / 3631);
- "Jy" / "uJy" / "nJy" per pixel: ZP = 8.90, 23.90, 31.40;
- count rates "e-/s", "counts/s", "DN/s" (HST drizzled products): from
  ``PHOTFLAM`` (erg/s/cm²/Å per count/s) and ``PHOTPLAM`` (Å):
  ZP = −2.5 log10 PHOTFLAM − 5 log10 PHOTPLAM − 2.408 (STScI's AB formula,
  −21.10 + 18.692), else the scene's ``zeropoint_ab``;
- counts "e-" / "counts" (not per second): divided by ``EXPTIME`` first.
An explicit ``zeropoint_ab`` always wins. Anything else is a ConfigError that
names the file and the keyword to add.
"""

from __future__ import annotations

import math

from ..errors import ConfigError

JY_AB_ZP = 2.5 * math.log10(3631.0)  # AB magnitude of 1 Jy (3631 Jy = 0 mag): 8.8999
ARCSEC_PER_RAD = 180.0 * 3600.0 / math.pi

# spellings after `normalise_units` → kind
_RATE = {"e-/s", "counts/s", "count/s", "cps", "dn/s", "e/s", "adu/s"}
_COUNTS = {"e-", "counts", "count", "dn", "adu", "e"}
_JY = {"jy": 0.0, "mjy": 2.5 * 3, "ujy": 2.5 * 6, "njy": 2.5 * 9}  # mag offsets from 1 Jy
_MJY_SR = {"mjy/sr", "mjy/steradian", "mjysr-1", "mjy.sr**-1", "mjy/sr**1"}


def normalise_units(text) -> str | None:
    """Lower-case units without blanks, the usual spellings unified; None for blank."""
    if text is None:
        return None
    s = str(text).strip().lower().replace(" ", "")
    if not s:
        return None
    s = s.replace("electrons", "e-").replace("electron", "e-").replace("/sec", "/s")
    return s.replace("µ", "u").replace("μ", "u")


def _kind(units: str) -> str | None:
    if units in _MJY_SR:
        return "mjy/sr"
    if units in _RATE:
        return "rate"
    if units in _COUNTS:
        return "counts"
    if units in _JY:
        return "jy"
    return None


def pixel_solid_angle_sr(pixel_arcsec: float) -> float:
    """Solid angle of a square pixel of side `pixel_arcsec`."""
    return (pixel_arcsec / ARCSEC_PER_RAD) ** 2


def zeropoint_mjy_sr(pixar_sr: float) -> float:
    """AB magnitude of 1 MJy/sr spread over a pixel of solid angle `pixar_sr`."""
    return JY_AB_ZP - 2.5 * math.log10(1.0e6 * pixar_sr)


def zeropoint_photflam(photflam: float, photplam_aa: float) -> float:
    """AB zero point (1 count/s) of an HST product from PHOTFLAM and PHOTPLAM (STScI)."""
    return -2.5 * math.log10(photflam) - 5.0 * math.log10(photplam_aa) - 2.408


def _positive(header, key):
    try:
        v = float(header[key])
    except (KeyError, TypeError, ValueError):
        return None
    return v if math.isfinite(v) and v > 0 else None


def resolve_units(header, *, units=None, zeropoint_ab=None, pixel_arcsec=None,
                  exptime_s=None, where: str) -> dict:
    """How to turn the image into fluxes: {units, zeropoint_ab, scale, counts_per_unit, how}.

    header: the image HDU's header merged over the primary's (astropy Header or dict).
    units, zeropoint_ab, exptime_s: the scene's overrides (None: from the header).
    pixel_arcsec: the pixel scale (for MJy/sr without PIXAR_SR).
    where: "observations[F150W]" and the file, for error messages.
    Returns scale (multiply the data by it: counts → counts/s), counts_per_unit (e-/s of
    one unit after scaling: 1 for count rates, None when unknown) and `how` (provenance).
    """
    raw = units if units is not None else header.get("BUNIT")
    u = normalise_units(raw)
    if u is None and zeropoint_ab is None:
        raise ConfigError(f"{where}.units", None,
                          "image units: add BUNIT to the image header or units = \"MJy/sr\" | "
                          "\"e-/s\" | \"counts/s\" | \"e-\" to the [[observations]] table")
    kind = None if u is None else _kind(u)
    if u is not None and kind is None and zeropoint_ab is None:
        raise ConfigError(f"{where}.units", raw, "known units (MJy/sr, Jy/uJy/nJy per pixel, "
                          "e-/s, counts/s, DN/s, e-, counts), or zeropoint_ab = the AB magnitude "
                          "of one data unit per pixel")
    scale, counts_per_unit = 1.0, None
    if kind == "counts":
        t = exptime_s if exptime_s is not None else _positive(header, "EXPTIME")
        if t is None:
            raise ConfigError(f"{where}.exptime_s", None,
                              f"an exposure time for an image in {raw} (add EXPTIME to the header "
                              "or exptime_s to the [[observations]] table)")
        scale, kind = 1.0 / t, "rate"
    if kind == "rate":
        counts_per_unit = 1.0
    if zeropoint_ab is not None:
        zp = float(zeropoint_ab)
        if not math.isfinite(zp):
            raise ConfigError(f"{where}.zeropoint_ab", zeropoint_ab, "a finite AB magnitude")
        return dict(units=raw, zeropoint_ab=zp, scale=scale, counts_per_unit=counts_per_unit,
                    how="zeropoint_ab given")
    if kind == "mjy/sr":
        pixar = _positive(header, "PIXAR_SR")
        how = "MJy/sr x PIXAR_SR"
        if pixar is None:
            if pixel_arcsec is None:
                raise ConfigError(f"{where}.pixel_arcsec", None,
                                  "PIXAR_SR in the header or a pixel scale, to convert MJy/sr")
            pixar, how = pixel_solid_angle_sr(pixel_arcsec), "MJy/sr x pixel_arcsec^2"
        return dict(units=raw, zeropoint_ab=zeropoint_mjy_sr(pixar), scale=scale,
                    counts_per_unit=None, how=how)
    if kind == "jy":
        return dict(units=raw, zeropoint_ab=JY_AB_ZP + _JY[u], scale=scale,
                    counts_per_unit=None, how=f"{raw} per pixel")
    flam, plam = _positive(header, "PHOTFLAM"), _positive(header, "PHOTPLAM")
    if flam is None or plam is None:
        raise ConfigError(f"{where}.zeropoint_ab", None,
                          f"a zero point for an image in {raw}: add PHOTFLAM and PHOTPLAM to the "
                          "header or zeropoint_ab to the [[observations]] table")
    return dict(units=raw, zeropoint_ab=zeropoint_photflam(flam, plam), scale=scale,
                counts_per_unit=counts_per_unit, how="PHOTFLAM/PHOTPLAM")
