"""analysis: limiting magnitudes from empty-sky apertures and clump S/N, on synthetic runs."""

import json
import math

import numpy as np
import pytest

from _fake_run import make_fake_run
from clumpylen_jax import analysis
from clumpylen_jax.errors import ConfigError


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    root = tmp_path_factory.mktemp("analysis")
    return {"short": make_fake_run(root / "short", exptime_s=1000.0),
            "long": make_fake_run(root / "long", exptime_s=16000.0),
            "lensed": make_fake_run(root / "lensed", lensed=True)}


@pytest.fixture(scope="module")
def results(runs):
    return {k: analysis.analyze_run(d, seed=1) for k, d in runs.items()}


def test_limiting_magnitude_finite_and_matches_variance(results):
    for res in results.values():
        for band in res["bands"].values():
            lim = band["limit"]
            assert lim["n_apertures"] == 100
            assert math.isfinite(lim["mag_lim"]) and 24 < lim["mag_lim"] < 34
            # 100 apertures: the std is known to ~7 %, i.e. ~0.1 mag (plus pixel correlations: none here).
            assert abs(lim["mag_lim"] - lim["mag_lim_expected"]) < 0.25


def test_limit_deepens_with_exposure(results):
    for f in ("F150W", "F200W"):
        short = results["short"]["bands"][f]["limit"]["mag_lim"]
        long_ = results["long"]["bands"][f]["limit"]["mag_lim"]
        # Sky-limited: σ ∝ t^-1/2, so 16× the time is 2.5 log10(4) = 1.505 mag deeper.
        assert long_ - short == pytest.approx(1.505, abs=0.3)


def test_limit_formula_against_direct_computation(runs):
    """m_lim = ZP − 2.5 log10(5 σ) with σ the analytic aperture-sum noise of a flat sky."""
    band = analysis.band_data(runs["short"] / "bands" / "F200W.fits")
    r = 0.1
    lim = analysis.limiting_magnitude(band, radius_arcsec=r, n_apertures=100, seed=3)
    area_px = math.pi * (r / band["pixel_arcsec"]) ** 2
    sigma = math.sqrt(area_px * band["sky"] / band["exptime_s"])
    assert lim["mag_lim_expected"] == pytest.approx(band["zp"] - 2.5 * math.log10(5 * sigma), abs=0.02)


def test_apertures_avoid_the_source(runs):
    band = analysis.band_data(runs["short"] / "bands" / "F200W.fits")
    mask = analysis.empty_sky_mask(band["noiseless"], band["variance"], band["sky"])
    assert 0.5 < mask.mean() < 1.0
    x, y = analysis.theta_to_pixel(0.4, 0.3, band["crpix"], band["pixel_arcsec"])
    assert not mask[int(round(float(y))), int(round(float(x)))]  # the bright clump is not "empty"


def test_bright_clump_has_higher_snr(results):
    for key in ("short", "lensed"):
        for band in results[key]["bands"].values():
            c = band["clumps"]
            assert c["n_clumps"] == c["n_measured"] == 2
            by_id = {b["id"]: b for b in c["brightest"]}
            assert by_id[0]["snr"] > 10 * by_id[1]["snr"] > 0
            assert c["brightest"][0]["id"] == 0  # ranked by apparent magnitude
            assert c["n_above_threshold"] >= 1


def test_snr_matches_known_flux(runs):
    """Σ(image − sky) in a 3σ-PSF aperture recovers ~99 % of a Gaussian's flux; S/N = F/√ΣV."""
    band = analysis.band_data(runs["long"] / "bands" / "F150W.fits")
    snr, flux = analysis.aperture_snr(band, np.array([0.4]), np.array([0.3]), 0.2)
    assert flux[0] == pytest.approx(2.0, rel=0.05)
    assert snr[0] > 50
    off, _ = analysis.aperture_snr(band, np.array([10.0]), np.array([0.0]), 0.2)
    assert np.isnan(off[0])  # outside the image


def test_lensed_positions_are_brightest_images(runs):
    from astropy.table import Table

    cat = Table.read(runs["lensed"] / "catalog.ecsv")
    lens = analysis._lens_from_summary(json.loads((runs["lensed"] / "summary.json").read_text()),
                                       runs["lensed"])
    t1, t2, mu = analysis.clump_image_positions(cat, lens, ((-1.5, 1.5), (-1.5, 1.5)))
    np.testing.assert_allclose(t1, [1.1, -0.9], atol=1e-6)
    np.testing.assert_allclose(t2, [0.3, -0.8], atol=1e-6)
    r = np.hypot([1.1, -0.9], [0.3, -0.8])
    np.testing.assert_allclose(mu, r / (r - 1.0), rtol=1e-6)  # SIS: |μ| = r / (r − θ_E)


def test_summary_keeps_other_keys(runs, results):
    s = json.loads((runs["short"] / "summary.json").read_text())
    assert "scene" in s and "timings_s" in s
    assert s["analysis"]["bands"]["F150W"]["limit"]["mag_lim"] == pytest.approx(
        results["short"]["bands"]["F150W"]["limit"]["mag_lim"])


def test_reproducible_with_seed(runs, results):
    again = analysis.analyze_run(runs["short"], seed=1)
    assert again["bands"]["F200W"]["limit"] == results["short"]["bands"]["F200W"]["limit"]


def test_bad_arguments(runs, tmp_path):
    with pytest.raises(ConfigError):
        analysis.analyze_run(runs["short"], n_apertures=1)
    with pytest.raises(ConfigError):
        analysis.analyze_run(runs["short"], aperture_radius_arcsec=-1.0)
    with pytest.raises(FileNotFoundError):
        analysis.analyze_run(tmp_path)


def test_cli_analyze(runs, capsys):
    from clumpylen_jax.cli import main

    assert main(["analyze", str(runs["short"]), "--snr-threshold", "5"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["settings"]["snr_threshold"] == 5.0
