"""Instruments, per-band defaults (pixel scale, zero point) and observation presets.

Zero points are computed from the total-system throughput T(λ) (filters.py)
and the telescope's collecting area A: the count rate of an AB source of
magnitude 0 is

    N_0 = A ∫ f_λ,AB(λ) T(λ) λ / (h c) dλ = (A f_ν,AB / h) ∫ T(λ) / λ dλ,

with f_ν,AB = 3631 Jy, and ZP_AB = 2.5 log10(N_0) is the AB magnitude that gives
1 e⁻/s (counts = electrons, DESIGN.md).

Collecting areas: HST, 45,238.93 cm² = π (120 cm)², the unobstructed 2.4 m
aperture that STScI's synphot uses with throughputs that already include the
obscuration; JWST, 25.4 m² (JWST User Documentation, "JWST Telescope" /
NIRCam sensitivity pages), with the NIRCam PCE curves (which include the OTE).

Presets are the exposure times and sky levels of the ClumPyLen paper
(Tables 1–2 for MACS J0416: CLASH WFC3-IR and the Cycle 1 GTO NIRCam data;
the Abell 2744 table: ACS from HST 11689, WFC3-IR from 13386, NIRCam GTO).
"""

from __future__ import annotations

import dataclasses
import difflib

import numpy as np

from .errors import ConfigError
from .filters import Filter, load_filter

H_ERG_S = 6.62607015e-27
AB_FNU_CGS = 3631e-23  # erg/s/cm²/Hz
HST_AREA_CM2 = 45238.93
JWST_AREA_CM2 = 25.4e4

NIRCAM_SW_PIXEL_ARCSEC = 0.031
NIRCAM_LW_PIXEL_ARCSEC = 0.063
NIRCAM_SW_LW_SPLIT_AA = 24000.0  # dichroic at ~2.4 μm: F070W–F212N short, F250M+ long


@dataclasses.dataclass(frozen=True)
class Instrument:
    """A camera: name, telescope, collecting area (cm²) and pixel scale(s) (arcsec)."""

    name: str
    telescope: str
    collecting_area_cm2: float
    pixel_arcsec: float
    pixel_arcsec_long: float | None = None  # NIRCam long-wavelength channel

    def pixel_arcsec_for(self, filt: Filter) -> float:
        """Native pixel scale for a filter (NIRCam: short or long channel by pivot wavelength)."""
        if self.pixel_arcsec_long is not None and filt.pivot_wavelength_aa >= NIRCAM_SW_LW_SPLIT_AA:
            return self.pixel_arcsec_long
        return self.pixel_arcsec


INSTRUMENTS = {
    # The paper uses 0.05″/pix for ACS/WFC (native 0.0495″).
    "HST/ACS": Instrument("HST/ACS", "HST", HST_AREA_CM2, 0.05),
    "HST/WFC3-IR": Instrument("HST/WFC3-IR", "HST", HST_AREA_CM2, 0.13),
    "JWST/NIRCam": Instrument("JWST/NIRCam", "JWST", JWST_AREA_CM2, NIRCAM_SW_PIXEL_ARCSEC,
                              NIRCAM_LW_PIXEL_ARCSEC),
}

_ALIASES = {
    "hst/acs": "HST/ACS", "acs": "HST/ACS", "acs/wfc": "HST/ACS", "hst/acs/wfc": "HST/ACS",
    "hst/wfc3-ir": "HST/WFC3-IR", "hst/wfc3/ir": "HST/WFC3-IR", "wfc3-ir": "HST/WFC3-IR",
    "wfc3/ir": "HST/WFC3-IR", "wfc3ir": "HST/WFC3-IR",
    "jwst/nircam": "JWST/NIRCam", "nircam": "JWST/NIRCam",
}


def get_instrument(name) -> Instrument:
    """An Instrument by name ("HST/ACS", "HST/WFC3-IR", "JWST/NIRCam"; case-insensitive)."""
    if isinstance(name, Instrument):
        return name
    key = _ALIASES.get(str(name).strip().lower()) if isinstance(name, str) else None
    if key is None:
        near = difflib.get_close_matches(str(name), list(INSTRUMENTS), n=1, cutoff=0.3)
        hint = f" (did you mean {near[0]}?)" if near else ""
        raise ConfigError("instrument", name, f"one of {', '.join(INSTRUMENTS)}{hint}")
    return INSTRUMENTS[key]


def instrument_for_filter(filter_name) -> str:
    """The instrument a built-in filter belongs to ("F200W" → "JWST/NIRCam")."""
    filt = load_filter(filter_name)
    if filt.instrument is None:
        raise ConfigError("filter", filt.name, "a built-in filter (user curves need an explicit instrument)")
    return filt.instrument


def _filter_for(instrument: Instrument, filter_name) -> Filter:
    filt = load_filter(filter_name)
    if filt.instrument is not None and filt.instrument != instrument.name:
        # "F200W" on HST/WFC3-IR etc.: look the band up on the asked instrument.
        try:
            filt = load_filter(f"{instrument.name}/{filt.name}")
        except ConfigError:
            raise ConfigError("filter", filter_name, f"a filter of {instrument.name}") from None
    return filt


def zeropoint_ab(instrument, filter_name) -> float:
    """AB magnitude giving 1 e⁻/s, from the throughput curve and the collecting area."""
    inst = get_instrument(instrument)
    filt = _filter_for(inst, filter_name)
    lam, thr = filt.wavelength_aa, filt.throughput
    n0 = inst.collecting_area_cm2 * AB_FNU_CGS / H_ERG_S * np.trapezoid(thr / lam, lam)
    return float(2.5 * np.log10(n0))


def band_defaults(instrument, filter_name) -> dict:
    """{"pixel_arcsec": native pixel scale, "zeropoint_ab": ZP for e⁻/s} of a band."""
    inst = get_instrument(instrument)
    filt = _filter_for(inst, filter_name)
    return {"pixel_arcsec": inst.pixel_arcsec_for(filt), "zeropoint_ab": zeropoint_ab(inst, filt)}


# Published zero points for checks (AB, e⁻/s, infinite aperture):
# ACS/WFC from the STScI ACS zeropoint calculator (post-SM4, ~2016),
# WFC3/IR from the WFC3 IR photometric calibration (2012; 2020 values within 0.01 mag).
PUBLISHED_ZEROPOINTS_AB = {
    ("HST/ACS", "F435W"): 25.66, ("HST/ACS", "F606W"): 26.49, ("HST/ACS", "F814W"): 25.94,
    ("HST/WFC3-IR", "F105W"): 26.27, ("HST/WFC3-IR", "F125W"): 26.23, ("HST/WFC3-IR", "F160W"): 25.95,
}


def _band(instrument, texp, sky):
    return {"instrument": instrument, "exptime_s": texp, "sky_counts_per_s": sky}


_PRESETS = {
    # Paper Table 1 (CLASH WFC3-IR) and Table 2 (NIRCam, GTO PI Windhorst), MACS J0416.1-2403.
    "macs0416": {
        "F105W": _band("HST/WFC3-IR", 5511.747, 0.694285),
        "F125W": _band("HST/WFC3-IR", 5511.747, 0.547766),
        "F160W": _band("HST/WFC3-IR", 5511.747, 0.5331),
        "F115W": _band("JWST/NIRCam", 3349.872, 0.207835),
        "F150W": _band("JWST/NIRCam", 2920.4, 0.20776),
        "F200W": _band("JWST/NIRCam", 2920.4, 0.160606),
        "F277W": _band("JWST/NIRCam", 2920.4, 0.0948052),
        "F356W": _band("JWST/NIRCam", 2920.4, 0.0935602),
        "F444W": _band("JWST/NIRCam", 3779.34, 0.2402224),
    },
    # Paper's Abell 2744 table.
    "abell2744": {
        "F435W": _band("HST/ACS", 1284.0, 0.0166096),
        "F606W": _band("HST/ACS", 1284.0, 0.0876545),
        "F814W": _band("HST/ACS", 1284.0, 0.0669051),
        "F105W": _band("HST/WFC3-IR", 652.94, 0.297923),
        "F125W": _band("HST/WFC3-IR", 602.93, 0.351991),
        "F160W": _band("HST/WFC3-IR", 702.94, 0.271799),
        "F115W": _band("JWST/NIRCam", 3349.872, 0.228858),
        "F150W": _band("JWST/NIRCam", 2490.932, 0.209639),
        "F200W": _band("JWST/NIRCam", 2490.932, 0.17107),
        "F277W": _band("JWST/NIRCam", 2490.932, 0.220765),
        "F356W": _band("JWST/NIRCam", 2490.932, 0.209639),
        "F444W": _band("JWST/NIRCam", 3349.872, 0.228858),
    },
}
_PRESET_ALIASES = {"macs0416": "macs0416", "macsj0416": "macs0416", "macs j0416": "macs0416",
                   "macs0416-2403": "macs0416", "cosmic-archipelago": "macs0416",
                   "abell2744": "abell2744", "a2744": "abell2744", "abell 2744": "abell2744",
                   "a2744-system3": "abell2744"}


def preset_names() -> list[str]:
    return sorted(_PRESETS)


def preset(name) -> dict:
    """{filter: {"instrument", "exptime_s", "sky_counts_per_s"}} of a named observation preset.

    "macs0416" (paper Tables 1–2) or "abell2744" (paper's Abell 2744 table).
    Sky levels are e⁻/s per native detector pixel. Returns a fresh copy.
    """
    key = _PRESET_ALIASES.get(str(name).strip().lower())
    if key is None:
        near = difflib.get_close_matches(str(name).lower(), list(_PRESET_ALIASES), n=1, cutoff=0.4)
        hint = f" (did you mean {_PRESET_ALIASES[near[0]]}?)" if near else ""
        raise ConfigError("preset", name, f"one of {', '.join(preset_names())}{hint}")
    return {band: dict(v) for band, v in _PRESETS[key].items()}
