"""Filters, zero points, pixel scales and presets."""

import numpy as np
import pytest

from clumpylen_jax.errors import ConfigError
from clumpylen_jax.filters import PAPER_BANDS, filter_from_arrays, filter_from_file, load_filter
from clumpylen_jax.instruments import (PUBLISHED_ZEROPOINTS_AB, band_defaults, get_instrument,
                                       instrument_for_filter, preset, zeropoint_ab)


def test_all_paper_bands_load_with_sane_pivots():
    # pivot wavelengths (Å) from the STScI/JDox tables, to 1 %
    pivots = {"F435W": 4329, "F606W": 5922, "F814W": 8045, "F105W": 10552, "F125W": 12486,
              "F160W": 15369, "F115W": 11543, "F150W": 15007, "F200W": 19886, "F277W": 27617,
              "F356W": 35684, "F444W": 44037}
    for band in PAPER_BANDS:
        f = load_filter(band)
        assert f.pivot_wavelength_aa == pytest.approx(pivots[band], rel=0.01)
        assert np.all(np.diff(f.wavelength_aa) > 0) and np.all(f.throughput >= 0)


def test_names_case_insensitive_and_with_instrument():
    assert load_filter("f200w") is load_filter("JWST/NIRCam F200W")
    assert load_filter("hst/acs/f435w") is load_filter("F435W")
    assert load_filter("wfc3_ir_f160w").instrument == "HST/WFC3-IR"
    assert instrument_for_filter("F444W") == "JWST/NIRCam"
    with pytest.raises(ConfigError, match="did you mean F160W"):
        load_filter("F160X")
    with pytest.raises(ConfigError):
        load_filter("HST/ACS/F200W")


def test_user_curves(tmp_path):
    lam = np.linspace(4000.0, 6000.0, 50)
    thr = np.exp(-0.5 * ((lam - 5000.0) / 300.0) ** 2)
    p = tmp_path / "box.txt"
    np.savetxt(p, np.c_[lam, thr])
    f = filter_from_file(p)
    assert f.pivot_wavelength_aa == pytest.approx(4980, rel=0.01)
    assert load_filter(str(p)).name == "box"
    from astropy.table import Table

    Table({"wavelength_aa": lam, "throughput": thr}).write(tmp_path / "box.ecsv", format="ascii.ecsv")
    assert filter_from_file(tmp_path / "box.ecsv").pivot_wavelength_aa == pytest.approx(f.pivot_wavelength_aa)
    for bad_lam, bad_thr in [(lam, -thr), (lam[::-1], thr), (np.where(lam > 5000, np.nan, lam), thr)]:
        with pytest.raises(ConfigError):
            filter_from_arrays("bad", bad_lam, bad_thr)
    np.savetxt(tmp_path / "neg.txt", np.c_[lam, thr - 0.5])
    with pytest.raises(ConfigError):
        filter_from_file(tmp_path / "neg.txt")


@pytest.mark.parametrize("key", sorted(PUBLISHED_ZEROPOINTS_AB))
def test_hst_zeropoints_match_published(key):
    inst, band = key
    assert zeropoint_ab(inst, band) == pytest.approx(PUBLISHED_ZEROPOINTS_AB[key], abs=0.05)


def test_nircam_zeropoints_plausible():
    # JWST's 25.4 m² with PCE ~0.2–0.5: ZP(e⁻/s) ≈ 27.5–28.3 for the wide bands
    for band in ("F115W", "F150W", "F200W", "F277W", "F356W", "F444W"):
        assert 27.3 < zeropoint_ab("JWST/NIRCam", band) < 28.5


def test_pixel_scales():
    assert band_defaults("HST/ACS", "F606W")["pixel_arcsec"] == 0.05
    assert band_defaults("HST/WFC3-IR", "F160W")["pixel_arcsec"] == 0.13
    assert band_defaults("JWST/NIRCam", "F200W")["pixel_arcsec"] == 0.031
    assert band_defaults("JWST/NIRCam", "F277W")["pixel_arcsec"] == 0.063
    assert get_instrument("nircam").collecting_area_cm2 == pytest.approx(25.4e4)
    with pytest.raises(ConfigError):
        get_instrument("HST/WFPC2")
    with pytest.raises(ConfigError):
        band_defaults("HST/ACS", "F444W")


def test_presets_match_paper_tables():
    m = preset("macs0416")
    assert set(m) == {"F105W", "F125W", "F160W", "F115W", "F150W", "F200W", "F277W", "F356W", "F444W"}
    assert m["F160W"] == {"instrument": "HST/WFC3-IR", "exptime_s": 5511.747, "sky_counts_per_s": 0.5331}
    assert m["F444W"]["exptime_s"] == 3779.34 and m["F444W"]["sky_counts_per_s"] == 0.2402224
    a = preset("Abell2744")
    assert len(a) == 12
    assert a["F435W"] == {"instrument": "HST/ACS", "exptime_s": 1284.0, "sky_counts_per_s": 0.0166096}
    assert a["F125W"]["exptime_s"] == 602.93 and a["F200W"]["sky_counts_per_s"] == 0.17107
    for band, v in a.items():
        assert instrument_for_filter(band) == v["instrument"]
    a["F435W"]["exptime_s"] = 0.0  # a copy: the preset itself is unchanged
    assert preset("abell2744")["F435W"]["exptime_s"] == 1284.0
    with pytest.raises(ConfigError, match="macs0416"):
        preset("macs0417")
