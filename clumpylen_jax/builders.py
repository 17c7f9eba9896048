"""From names and physical quantities to the model's inputs, without a scene file.

`make_band` turns an instrument and a filter name into a model `Band` through the scene
parser itself (the same defaults, checks and messages as a `[[bands]]` table: a scene file
and the Python API cannot disagree). `band_counts_per_s` turns AB magnitudes, or stellar
masses and ages (SPS), into the per-band count rates that `Sersic.flux` and `Clumps.flux`
hold. Example::

    import clumpylen_jax as cl
    cl.enable_float64()
    bands = [cl.make_band("JWST/NIRCam", f, exptime_s=2000.0, sky_counts_per_s=0.16)
             for f in ("F150W", "F200W")]
    flux = cl.band_counts_per_s(bands, mass_msun=[1e6, 3e6], age_myr=[10.0, 50.0], z_source=2.0)
    clumps = cl.Clumps(center_arcsec, flux, re_arcsec, n, q, pa_rad)   # flux: [N, 2] counts/s
"""

from __future__ import annotations

import numpy as np

from . import scene as scene_mod
from .accuracy import ACCURACY_PRESETS, Accuracy
from .errors import ConfigError
from .instruments import zeropoint_ab
from .model import Band
from .photometry import ab_magnitudes, mags_to_counts_per_s_or_zero


def _accuracy(accuracy) -> Accuracy:
    if isinstance(accuracy, Accuracy):
        return accuracy
    if accuracy not in ACCURACY_PRESETS:
        raise ConfigError("accuracy", accuracy, f"an Accuracy or one of {', '.join(ACCURACY_PRESETS)}")
    return ACCURACY_PRESETS[accuracy]


def model_band(b: scene_mod.Band, accuracy, *, base_dir=None, setting="bands[0]") -> Band:
    """The model's Band of a resolved scene band: its PSF read or made for the accuracy's
    sub-grid (the one route from a scene band, or `builders.make_band`, to a model Band)."""
    from .psf import psf_for_band
    if b.pixel_arcsec is None or b.zeropoint_ab is None:
        raise ConfigError(setting, b.filter, "a band with pixel_arcsec and zeropoint_ab")
    psf = psf_for_band(b.psf, instrument=b.instrument, filter_name=b.filter,
                       detector_pixel_arcsec=b.pixel_arcsec,
                       psf_pixel_arcsec=b.psf_pixel_arcsec,
                       oversampling=max(accuracy.psf_oversampling, 2) * 2 - 1,
                       base_dir=base_dir, setting=f"{setting}.psf",
                       grid_oversampling=accuracy.psf_oversampling)
    return Band(
        b.filter, float(b.pixel_arcsec), float(b.exptime_s or 1.0), float(b.sky_counts_per_s),
        None if psf is None else psf.array, None if psf is None else psf.pixel_arcsec,
        bool(b.psf_effective or (psf is not None and psf.effective)))


def make_band(instrument: str, filter_name: str, *, accuracy="default", base_dir=None,
              **settings) -> Band:
    """A model `Band` for `filter_name` of `instrument` ("HST/ACS", "HST/WFC3-IR", "JWST/NIRCam").

    settings: the keys of a scene's `[[bands]]` table (SCENE.md), with its defaults:
    exptime_s (s), sky_counts_per_s (counts/s per detector pixel, default 0), pixel_arcsec and
    zeropoint_ab (default: the instrument's), psf ("none", "diffraction" (default) or a FITS
    path, relative to base_dir), psf_pixel_arcsec, psf_effective.
    accuracy: the preset name or `Accuracy` given to `build_model` (the PSF is made for its
    sub-grid). The band's zero point (AB mag of 1 count/s) is `band_zeropoint_ab(band)`
    unless zeropoint_ab was given.
    """
    table = {"instrument": instrument, "filter": filter_name, **settings}
    resolved = scene_mod._band(table, 0, base_dir, noise=False, path=f"band {filter_name}")
    return model_band(resolved, _accuracy(accuracy), base_dir=base_dir,
                      setting=f"band {filter_name}")


def band_zeropoint_ab(band, instrument: str | None = None) -> float:
    """The AB magnitude that gives 1 count/s in `band` (a Band or a filter name), from the
    filter's throughput and the telescope's collecting area."""
    name = band.name if isinstance(band, Band) else str(band)
    if instrument is None:
        from .instruments import instrument_for_filter
        instrument = instrument_for_filter(name)
    return zeropoint_ab(instrument, name)


def band_counts_per_s(bands, *, mag_ab=None, mass_msun=None, age_myr=None, z_source=None,
                      zeropoints_ab=None, **sps) -> np.ndarray:
    """Count rates (counts/s) per band, shape [..., B] for B bands, of components given either
    their AB magnitudes (`mag_ab`, [..., B]) or a stellar mass (M☉) and age (Myr) at
    redshift `z_source` through the stellar-population model (`sps`: the keywords of
    `ab_magnitudes`: metallicity, sfh, sfh_duration_myr, dust_av, ...).

    bands: model Bands or filter names; zeropoints_ab: one per band (default: each filter's
    instrument zero point). A magnitude of +inf gives 0 counts/s.
    """
    names = [b.name if isinstance(b, Band) else str(b) for b in bands]
    zps = np.asarray(zeropoints_ab if zeropoints_ab is not None
                     else [band_zeropoint_ab(n) for n in names], float)
    if zps.shape != (len(names),):
        raise ConfigError("zeropoints_ab", zeropoints_ab, f"one zero point per band ({len(names)})")
    if (mag_ab is None) == (mass_msun is None):
        raise ConfigError("band_counts_per_s", "mag_ab" if mag_ab is not None else None,
                          "either mag_ab, or mass_msun with age_myr and z_source")
    if mag_ab is None:
        if age_myr is None or z_source is None:
            raise ConfigError("age_myr" if age_myr is None else "z_source", None,
                              "an age (Myr) and a source redshift with mass_msun")
        mag_ab = np.asarray(ab_magnitudes(np.asarray(mass_msun, float), np.asarray(age_myr, float),
                                          filters=names, z=float(z_source), **sps))
    mag_ab = np.asarray(mag_ab, float)
    if mag_ab.shape[-1:] != (len(names),):
        raise ConfigError("mag_ab (shape)", mag_ab.shape, f"[..., {len(names)}]: one per band")
    return mags_to_counts_per_s_or_zero(mag_ab, zps)
