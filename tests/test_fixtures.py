"""The shared files in fixtures/: regenerated bit for bit by their script, and read by the package as
what they claim to be (deflection maps in both conventions, PSFs of each kind, cutouts, catalogue)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest
from astropy.io import fits

from clumpylen_jax.cosmology import dls_ds

FIX = Path(__file__).resolve().parents[1] / "fixtures"


def _script():
    spec = importlib.util.spec_from_file_location("make_fixtures", FIX / "make_fixtures.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_fixtures_are_what_the_script_makes_and_small():
    files = _script().build()
    for name, data in files.items():
        assert (FIX / name).read_bytes() == data, f"{name}: rerun python fixtures/make_fixtures.py"
    assert sum(len(b) for b in files.values()) < 1_000_000
    for name in files:
        if name.endswith(".fits"):
            with fits.open(FIX / name) as h:
                assert h[0].header["ORIGIN"] == "clumpylen_jax fixtures"  # provenance in every file


@pytest.mark.parametrize("style", ["hff", "lenstool"])
def test_deflection_fixture_is_the_sis_it_says(style):
    from clumpylen_jax.lensing.fits import load_deflection_maps

    m = _script()
    names = {"hff": ("lens_hff_x-arcsec-deflect.fits", "lens_hff_y-arcsec-deflect.fits"),
             "lenstool": ("lens_lenstool_dplx.fits", "lens_lenstool_dply.fits")}[style]
    hdr = fits.getheader(FIX / names[0])
    grid = load_deflection_maps(FIX / names[0], FIX / names[1],
                                lens_center_radec_deg=(hdr["LENS_RA"], hdr["LENS_DEC"]),
                                z_lens=hdr["Z_LENS"], z_source=m.Z_SOURCE)
    assert grid.scale == pytest.approx(dls_ds(m.Z_LENS, m.Z_SOURCE))
    # Away from the SIS centre (where bilinear interpolation of the cusp is poor) the map is the SIS.
    t1 = np.array([2.0, -3.0, 0.5, -1.5, 4.0])
    t2 = np.array([1.0, 2.5, -3.0, -2.0, -0.5])
    a1, a2 = (np.asarray(a) for a in grid.deflection(t1, t2))
    r = np.hypot(t1, t2)
    want = hdr["THETA_E"] * grid.scale
    np.testing.assert_allclose(a1, want * t1 / r, atol=3e-3)
    np.testing.assert_allclose(a2, want * t2 / r, atol=3e-3)


def test_psf_fixtures_load_as_their_kind():
    from clumpylen_jax.psf import fwhm_arcsec, load_psf_fits

    det = load_psf_fits(FIX / "psf_nircam_f200w_detsamp.fits")
    assert det.effective and det.pixel_arcsec == pytest.approx(0.031)
    over = load_psf_fits(FIX / "psf_nircam_f115w_webbpsf_like.fits")
    assert not over.effective and over.pixel_arcsec == pytest.approx(0.031 / 4)
    assert over.detector_pixel_arcsec == pytest.approx(0.031)
    std = load_psf_fits(FIX / "PSFSTD_WFC3IR_F160W_tiny.fits")
    assert std.effective and std.pixel_arcsec == pytest.approx(0.032)
    # Airy FWHM ≈ 1.03 λ/D: F115W on 6.5 m ≈ 0.038"; the pixel-integrated ones are broader.
    assert fwhm_arcsec(over) == pytest.approx(1.03 * 1.15e-6 / 6.5 * 206265, rel=0.1)
    assert fwhm_arcsec(det) > 1.03 * 2.0e-6 / 6.5 * 206265
    for p in (det, over, std):
        assert np.isclose(np.sum(p.array), 1.0)


def test_cutouts_have_real_product_headers():
    from astropy.wcs import WCS

    with fits.open(FIX / "jwst_like_f200w_i2d.fits") as h:
        sci = h["SCI"].header
        assert sci["BUNIT"] == "MJy/sr" and sci["PIXAR_SR"] > 0 and sci["PHOTMJSR"] > 0
        w = WCS(sci)
        assert w.has_celestial and abs(w.pixel_scale_matrix[0, 1]) > 0  # rotated
        assert np.all(h["ERR"].data > 0) and h["SCI"].data.shape == h["ERR"].data.shape
        # The arc's total flux is the lensed host + clumps: magnified, so brighter than the host alone.
        pix_sr = sci["PIXAR_SR"]
        total_jy = np.sum(h["SCI"].data) * 1e6 * pix_sr
        assert -2.5 * np.log10(total_jy / 3631) < h[0].header["TRU_HMAG"] - 1.0
    with fits.open(FIX / "hst_like_f160w_drz.fits") as h:
        sci = h["SCI"].header
        assert sci["BUNIT"] == "ELECTRONS/S" and sci["PHOTFLAM"] > 0 and sci["PHOTPLAM"] > 0
        assert sci["EXPTIME"] > 0 and np.all(h["WHT"].data > 0)


def test_clump_catalogue_is_a_scene_catalogue(tmp_path):
    from clumpylen_jax.scene import _check_catalog

    _check_catalog(str(FIX / "clumps.ecsv"), "source.clumps.catalog", ["F115W", "F150W", "F200W", "F160W"])


def test_study_scene_fixture_is_a_scene():
    """fixtures/study_tiny.toml parses as the scene it says (no JAX needed)."""
    from clumpylen_jax.scene import load_scene

    s = load_scene(FIX / "study_tiny.toml")
    assert s.name == "tiny" and [b.filter for b in s.bands] == ["F200W"] and s.lens is None
