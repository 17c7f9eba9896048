"""Tests of PSF records, FITS loading, resampling and diffraction PSFs."""

import importlib.util
import os
import time
from pathlib import Path

import numpy as np
import pytest
from astropy.io import fits

from clumpylen_jax.errors import ConfigError
from clumpylen_jax.psf import (
    PSF,
    diffraction_psf,
    fwhm_arcsec,
    load_psf_fits,
    psf_for_band,
    recenter_half_pixel,
    resample_psf,
    sample_psf,
)


def _shared_data() -> Path:
    env = os.environ.get("CLUMPYLEN_SHARED_DATA")
    return Path(env) if env else Path(__file__).resolve().parents[2] / "shared" / "data"


PSF_DIR = _shared_data() / "psf"
needs_data = pytest.mark.skipif(not PSF_DIR.is_dir(), reason=f"shared PSF data not found at {PSF_DIR}")
needs_poppy = pytest.mark.skipif(
    importlib.util.find_spec("poppy") is None, reason="poppy not installed (optional dependency for diffraction PSFs)"
)


def gaussian(n0, n1, sigma_pix, offset=(0.0, 0.0)):
    """A Gaussian centred on the array centre ((n−1)/2) plus `offset`, point-sampled."""
    i0, i1 = np.indices((n0, n1), dtype=float)
    c0, c1 = (n0 - 1) / 2 + offset[0], (n1 - 1) / 2 + offset[1]
    return np.exp(-((i0 - c0) ** 2 + (i1 - c1) ** 2) / (2 * sigma_pix**2))


def centroid(a):
    i0, i1 = np.indices(a.shape)
    return (a * i0).sum() / a.sum(), (a * i1).sum() / a.sum()


# ----------------------------------------------------------------------------- record


def test_psf_record_normalises_and_centre():
    psf = PSF(gaussian(6, 8, 1.5) * 7.0, 0.01, True, "test")
    assert abs(psf.array.sum() - 1.0) < 1e-14
    assert psf.center == (2.5, 3.5)
    assert psf.array.dtype == np.float64 and not psf.array.flags.writeable


@pytest.mark.parametrize(
    "array, pixel, setting",
    [
        (np.full((5, 5), np.nan), 0.01, "psf"),
        (np.zeros((5, 5)), 0.01, "psf"),
        (-np.ones((5, 5)), 0.01, "psf"),
        (np.ones((3, 5, 5)), 0.01, "psf"),
        (np.ones((5, 5)), 0.0, "psf_pixel_arcsec"),
        (np.ones((5, 5)), float("inf"), "psf_pixel_arcsec"),
    ],
)
def test_psf_record_validation(array, pixel, setting):
    with pytest.raises(ConfigError) as err:
        PSF(array, pixel, False)
    assert err.value.setting == setting


# ----------------------------------------------------------------------------- resampling


@pytest.mark.parametrize("n", [31, 32, 64, 65])
@pytest.mark.parametrize("ratio", [1.0, 2.0, 3.7, 0.45])
def test_resample_centring_and_sum(n, ratio):
    # A symmetric PSF about the array centre: the resampled kernel's centroid
    # must be the central pixel of the odd output for odd and even inputs.
    psf = PSF(gaussian(n, n, 3.0), 0.01, False)
    k = resample_psf(psf, 0.01 * ratio)
    m = k.shape[0]
    assert k.shape[0] == k.shape[1] and m % 2 == 1
    assert m * 0.01 * ratio >= n * 0.01  # default size covers the whole input
    assert abs(k.sum() - 1.0) < 1e-12
    c = centroid(k)
    assert abs(c[0] - (m - 1) / 2) < 1e-6 and abs(c[1] - (m - 1) / 2) < 1e-6


def test_resample_conserves_flux_without_renormalising():
    # The overlap matrices alone conserve the total for a non-integer ratio.
    from clumpylen_jax.psf import _overlap_matrix

    for n_in, p_in, p_out in [(40, 0.0162, 0.0317), (101, 0.0125, 0.0079), (154, 0.0648, 0.0317)]:
        n_out = int(np.ceil(n_in * p_in / p_out)) | 1
        w = _overlap_matrix(n_in, p_in, n_out, p_out)
        np.testing.assert_allclose(w.sum(axis=0), 1.0, atol=1e-12)
    rng = np.random.default_rng(0)
    a = rng.random((37, 41))
    psf = PSF(a, 0.013, False)
    w0 = _overlap_matrix(37, 0.013, 23, 0.0317)
    w1 = _overlap_matrix(41, 0.013, 23, 0.0317)
    assert abs((w0 @ psf.array @ w1.T).sum() - 1.0) < 1e-12


def test_resample_identity_and_integer_binning():
    a = gaussian(21, 21, 2.0, offset=(0.3, -0.7))
    psf = PSF(a, 0.02, False)
    np.testing.assert_allclose(resample_psf(psf, 0.02), psf.array, atol=1e-15)
    # Binning 3 x 3 blocks of a 21 x 21 grid (odd ratio: grids align).
    k = resample_psf(psf, 0.06)
    expected = psf.array.reshape(7, 3, 7, 3).sum(axis=(1, 3))
    np.testing.assert_allclose(k, expected, atol=1e-15)


def test_resample_even_input_half_pixel():
    # Even input, same pitch: each output pixel straddles two input pixels.
    a = np.zeros((4, 4))
    a[1:3, 1:3] = 1.0  # symmetric about the corner at (1.5, 1.5)
    k = resample_psf(PSF(a, 1.0, False), 1.0)
    assert k.shape == (5, 5)
    np.testing.assert_allclose(k[2, 2], 0.25)
    np.testing.assert_allclose(k[1:4, 1:4], np.array([[1, 2, 1], [2, 4, 2], [1, 2, 1]]) / 16)


def test_resample_truncation_and_validation():
    psf = PSF(gaussian(41, 41, 4.0), 0.01, False)
    k = resample_psf(psf, 0.01, size=9)
    assert k.shape == (9, 9) and abs(k.sum() - 1.0) < 1e-12
    for bad in [8, 0, -3, 2.5]:
        with pytest.raises(ConfigError) as err:
            resample_psf(psf, 0.01, size=bad)
        assert err.value.setting == "psf_size"
    with pytest.raises(ConfigError):
        resample_psf(psf, -0.01)


def test_recenter_half_pixel_synthetic():
    # Core at pixel (20, 20) of a 40 x 40 array: half a pixel off the centre.
    a = gaussian(40, 40, 1.2, offset=(0.5, 0.5))
    out, shift = recenter_half_pixel(a)
    assert shift == (1, 1) and out.shape == (39, 39)
    c = centroid(out)
    assert abs(c[0] - 19) < 1e-3 and abs(c[1] - 19) < 1e-3
    # Small asymmetries are left alone.
    _, shift = recenter_half_pixel(gaussian(41, 41, 1.2, offset=(0.2, -0.2)))
    assert shift == (0, 0)
    _, shift = recenter_half_pixel(gaussian(41, 41, 1.2, offset=(-1.0, 0.0)))
    assert shift == (-2, 0)


# ----------------------------------------------------------------------------- FITS


def test_fits_header_keywords(tmp_path):
    a = gaussian(25, 25, 2.0)
    p = tmp_path / "a.fits"
    fits.PrimaryHDU(a, header=fits.Header({"PIXSCALE": 0.015})).writeto(p)
    psf = load_psf_fits(p)
    assert psf.pixel_arcsec == 0.015 and psf.effective is False
    assert load_psf_fits(p, pixel_arcsec=0.02, effective=True).pixel_arcsec == 0.02

    p = tmp_path / "b.fits"
    fits.PrimaryHDU(a, header=fits.Header({"CDELT1": -0.01 / 3600, "CDELT2": 0.01 / 3600})).writeto(p)
    assert abs(load_psf_fits(p).pixel_arcsec - 0.01) < 1e-12

    p = tmp_path / "c.fits"
    fits.HDUList([fits.PrimaryHDU(), fits.ImageHDU(a, header=fits.Header({"PIXELSCL": 0.0079, "OVERSAMP": 4}), name="OVERSAMP")]).writeto(p)
    psf = load_psf_fits(p)
    assert psf.pixel_arcsec == 0.0079 and psf.detector_pixel_arcsec == pytest.approx(0.0316)
    assert load_psf_fits(p, hdu="OVERSAMP").source.endswith("[1]")


def test_fits_errors(tmp_path):
    a = gaussian(25, 25, 2.0)
    p = tmp_path / "noscale.fits"
    fits.PrimaryHDU(a).writeto(p)
    with pytest.raises(ConfigError) as err:
        load_psf_fits(p)
    assert err.value.setting == "psf_pixel_arcsec"
    assert load_psf_fits(p, pixel_arcsec=0.01).pixel_arcsec == 0.01

    bad = a.copy()
    bad[3, 3] = np.nan
    p = tmp_path / "nan.fits"
    fits.PrimaryHDU(bad, header=fits.Header({"PIXSCALE": 0.01})).writeto(p)
    with pytest.raises(ConfigError) as err:
        load_psf_fits(p)
    assert err.value.setting == "psf"

    p = tmp_path / "neg.fits"
    fits.PrimaryHDU(-a, header=fits.Header({"PIXSCALE": 0.01})).writeto(p)
    with pytest.raises(ConfigError):
        load_psf_fits(p)

    p = tmp_path / "cube.fits"
    fits.PrimaryHDU(np.ones((2, 5, 5)), header=fits.Header({"PIXSCALE": 0.01})).writeto(p)
    with pytest.raises(ConfigError):
        load_psf_fits(p)

    with pytest.raises(ConfigError):
        load_psf_fits(tmp_path / "missing.fits")
    p = tmp_path / "junk.fits"
    p.write_text("not a fits file")
    with pytest.raises(ConfigError):
        load_psf_fits(p)
    with pytest.raises(ConfigError) as err:
        load_psf_fits(tmp_path / "noscale.fits", hdu=3, pixel_arcsec=0.01)
    assert err.value.setting == "psf_hdu"


def test_psf_for_band_dispatch(tmp_path):
    assert psf_for_band("none", instrument="JWST/NIRCam", filter_name="F200W", detector_pixel_arcsec=0.031) is None
    assert psf_for_band(None, instrument="JWST/NIRCam", filter_name="F200W", detector_pixel_arcsec=0.031) is None
    fits.PrimaryHDU(gaussian(11, 11, 1.0)).writeto(tmp_path / "p.fits")
    psf = psf_for_band(
        "p.fits", instrument="JWST/NIRCam", filter_name="F200W", detector_pixel_arcsec=0.031, psf_pixel_arcsec=0.008, base_dir=tmp_path
    )
    assert psf.pixel_arcsec == 0.008


# ----------------------------------------------------------------------------- real files


@needs_data
@pytest.mark.parametrize(
    "name, pixel, fwhm_range",
    [
        ("PSFSTD_ACSWFC_F435W.fits", 0.0125, (0.07, 0.11)),
        ("PSFSTD_ACSWFC_F814W.fits", 0.0125, (0.07, 0.11)),
        ("PSFSTD_WFC3IR_F105W.fits", 0.032, (0.13, 0.18)),
        ("PSFSTD_WFC3IR_F160W.fits", 0.032, (0.14, 0.19)),
    ],
)
def test_real_stdpsf(name, pixel, fwhm_range):
    psf = load_psf_fits(PSF_DIR / "hst_stdpsf" / name)
    assert psf.shape == (101, 101) and psf.effective
    assert psf.pixel_arcsec == pytest.approx(pixel)
    assert psf.detector_pixel_arcsec == pytest.approx(4 * pixel)
    assert np.unravel_index(np.argmax(psf.array), psf.shape) == (50, 50)
    assert fwhm_range[0] < fwhm_arcsec(psf) < fwhm_range[1]
    # Another fiducial position of the cube gives a different, valid PSF.
    corner = load_psf_fits(PSF_DIR / "hst_stdpsf" / name, detector_xy=(0, 0))
    assert "(0, 0)" in corner.source and not np.allclose(corner.array, psf.array)


@needs_data
@pytest.mark.parametrize(
    "name, pixel, fwhm_range",
    [
        ("WebbPSF_F115W_trunc.fits", 0.0317, (0.035, 0.065)),
        ("WebbPSF_F200W_trunc.fits", 0.0317, (0.055, 0.085)),
        ("WebbPSF_F277W_trunc.fits", 0.0648, (0.10, 0.15)),
        ("WebbPSF_F444W_trunc.fits", 0.0648, (0.13, 0.18)),
    ],
)
def test_real_webbpsf_detector_sampled(name, pixel, fwhm_range):
    psf = load_psf_fits(PSF_DIR / "jwst_webbpsf_revV" / name)
    assert psf.effective and psf.pixel_arcsec == pixel and psf.detector_pixel_arcsec == pixel
    assert fwhm_range[0] < fwhm_arcsec(psf) < fwhm_range[1]
    # Centring: after half-pixel recentring the core sits on the array centre.
    rc = load_psf_fits(PSF_DIR / "jwst_webbpsf_revV" / name, recenter=True)
    core = rc.array
    c = np.array(rc.center)
    i0, i1 = np.indices(core.shape)
    m = (i0 - c[0]) ** 2 + (i1 - c[1]) ** 2 < 3.0**2
    cc = np.array([(core * i0 * m).sum(), (core * i1 * m).sum()]) / (core * m).sum()
    assert np.all(np.abs(cc - c) < 0.3), (cc, c)


@needs_data
def test_real_webbpsf_oversampled_vs_detector():
    path = PSF_DIR / "jwst_webbpsf_revV" / "PSF_NIRCam_F444W_revV-1.fits"
    over = load_psf_fits(path)
    det = load_psf_fits(path, hdu=1)
    assert over.shape == (616, 616) and not over.effective and over.pixel_arcsec == 0.0162
    assert det.shape == (154, 154) and det.effective and det.pixel_arcsec == 0.0648
    assert over.detector_pixel_arcsec == pytest.approx(0.0648)
    # The oversampled optical PSF is sharper than its detector-binned version,
    # and area-resampling it to detector pixels reproduces that version's width.
    f_over, f_det = fwhm_arcsec(over), fwhm_arcsec(det)
    assert 0.13 < f_over < f_det < 0.17
    binned = PSF(resample_psf(over, 0.0648), 0.0648, True)
    assert abs(fwhm_arcsec(binned) - f_det) / f_det < 0.05


# ----------------------------------------------------------------------------- diffraction


@needs_poppy
@pytest.mark.parametrize(
    "instrument, band, pixel, diameter_m",
    [("JWST/NIRCam", "F200W", 0.0079, 6.5), ("HST/WFC3-IR", "F160W", 0.032, 2.4)],
)
def test_diffraction_psf_fwhm_and_cache(tmp_path, instrument, band, pixel, diameter_m):
    from clumpylen_jax.filters import load_filter

    t0 = time.perf_counter()
    psf = diffraction_psf(instrument, band, pixel_arcsec=pixel, size_arcsec=1.0, cache_dir=tmp_path)
    t_first = time.perf_counter() - t0
    assert not psf.effective and psf.shape[0] % 2 == 1
    lam_m = load_filter(f"{instrument} {band}").pivot_wavelength_aa * 1e-10
    expected = 1.03 * lam_m / diameter_m * 206264.806
    assert abs(fwhm_arcsec(psf) / expected - 1.0) < 0.2, (fwhm_arcsec(psf), expected)
    # |FT(real pupil)|² is centro-symmetric: the centroid is the central pixel.
    c = centroid(psf.array)
    m = psf.shape[0]
    assert abs(c[0] - (m - 1) / 2) < 1e-3 and abs(c[1] - (m - 1) / 2) < 1e-3
    files = list(tmp_path.glob("*.npy"))
    assert len(files) == 1 and not list(tmp_path.glob("*.tmp"))
    t0 = time.perf_counter()
    again = diffraction_psf(instrument, band, pixel_arcsec=pixel, size_arcsec=1.0, cache_dir=tmp_path)
    t_second = time.perf_counter() - t0
    np.testing.assert_array_equal(again.array, psf.array)
    assert t_second < 0.1 < t_first or t_second < t_first / 5


@needs_poppy
@pytest.mark.parametrize("instrument, band", [("JWST/NIRCam", "F150W"), ("HST/WFC3-IR", "F125W")])
def test_pupil_transmission_kept_across_wavelengths_gives_poppys_psf(monkeypatch, instrument, band):
    """The pupil optic that keeps its transmission per wavefront grid (computed once, not per
    wavelength) gives the PSF of poppy's own CompoundAnalyticOptic bit for bit, and computes
    the transmission once per grid however many wavelengths."""
    import poppy

    from clumpylen_jax import psf as psf_mod
    kw = dict(pixel_arcsec=0.02, size_arcsec=0.6, n_wavelengths=4, cache_dir=False)
    kept_cls = psf_mod._kept_transmission_optic()
    calls = []
    original = poppy.CompoundAnalyticOptic.get_transmission
    monkeypatch.setattr(poppy.CompoundAnalyticOptic, "get_transmission",
                        lambda self, wave: calls.append(1) or original(self, wave))
    kept = diffraction_psf(instrument, band, **kw).array
    assert len(calls) == 1
    monkeypatch.setattr(psf_mod, "_kept_transmission_optic", lambda: poppy.CompoundAnalyticOptic)
    plain = diffraction_psf(instrument, band, **kw).array
    assert len(calls) == 1 + 4 and issubclass(kept_cls, poppy.CompoundAnalyticOptic)
    assert kept.tobytes() == plain.tobytes()


@needs_poppy
def test_diffraction_psf_env_cache_and_coarse_pixels(tmp_path, monkeypatch):
    monkeypatch.setenv("CLUMPYLEN_CACHE", str(tmp_path))
    # Coarse (detector) pixels: pixel-integrated values, still unit sum and centred.
    psf = diffraction_psf("HST/ACS", "F814W", pixel_arcsec=0.05, size_arcsec=1.0)
    assert list((tmp_path / "psf").glob("HST_F814W_*.npy"))
    assert abs(psf.array.sum() - 1.0) < 1e-12
    assert np.unravel_index(np.argmax(psf.array), psf.shape) == ((psf.shape[0] - 1) // 2,) * 2
    with pytest.raises(ConfigError) as err:
        diffraction_psf("Keck/NIRC2", "F814W", pixel_arcsec=0.05)
    assert err.value.setting == "instrument"


def test_sample_psf_point_samples():
    # Odd input, integer ratio: samples are every k-th input pixel exactly.
    a = gaussian(41, 41, 6.0, offset=(0.4, -0.3))
    psf = PSF(a, 0.01, True)
    k = sample_psf(psf, 0.04)
    assert k.shape == (11, 11)
    np.testing.assert_allclose(k, psf.array[0::4, 0::4] / psf.array[0::4, 0::4].sum(), rtol=1e-10)
    # Symmetric even input, non-integer ratio: centred on the central pixel.
    k = sample_psf(PSF(gaussian(64, 64, 8.0), 0.01, True), 0.037)
    m = k.shape[0]
    assert m % 2 == 1 and abs(k.sum() - 1) < 1e-12
    c = centroid(k)
    assert abs(c[0] - (m - 1) / 2) < 1e-6 and abs(c[1] - (m - 1) / 2) < 1e-6
    with pytest.raises(ConfigError):
        sample_psf(psf, 0.04, size=10)


@needs_data
def test_sample_stdpsf_at_detector_pixels():
    # Anderson's normalisation: the 4x effective PSF sums to ~16, so its samples
    # at detector-pixel centres sum to ~1 (unit flux at detector sampling).
    from astropy.io import fits

    path = PSF_DIR / "hst_stdpsf" / "PSFSTD_WFC3IR_F160W.fits"
    psf = load_psf_fits(path)
    k = sample_psf(psf, psf.detector_pixel_arcsec)
    assert k.shape == (25, 25)
    with fits.open(path, ignore_missing_end=True) as hdul:
        raw = np.asarray(hdul[0].data[4], dtype=float)  # the central PSF of the 3 x 3 grid
    np.testing.assert_allclose(k, raw[2::4, 2::4] / raw[2::4, 2::4].sum(), rtol=1e-8, atol=1e-15)
    assert 0.9 < raw[2::4, 2::4].sum() / (raw.sum() / 16) < 1.1


@pytest.mark.parametrize("size", [15, 61])
@pytest.mark.parametrize("sigma_pix", [1.0, 1.3, 3.0])
def test_fwhm_of_a_gaussian_on_small_and_large_arrays(size, sigma_pix):
    """FWHM = 2.3548 σ within 1 %, whatever the array size (the upsampled grid's step is
    (n − 1)/(m − 1) pixels, not 1/upsample: a 15-pixel array read 6 % wide before)."""
    r = np.arange(size) - (size - 1) / 2
    g = np.exp(-0.5 * (r[:, None] ** 2 + r[None, :] ** 2) / sigma_pix**2)
    fwhm = fwhm_arcsec(PSF(g / g.sum(), 0.03, False))
    assert fwhm == pytest.approx(2 * np.sqrt(2 * np.log(2)) * sigma_pix * 0.03, rel=0.01)
