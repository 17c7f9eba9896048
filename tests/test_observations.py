"""Observed images in (issue 17): units through the zero point, every bad input, a mock fit back.

Units are checked against independent computations (astropy units, the AB definition);
bad inputs go through the CLI (exit 2, one line naming the file or setting, before any
compilation); the mock fit (MJy/sr, rotated WCS, two pixel scales) checks pulls.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from astropy.io import fits

import clumpylen_jax  # noqa: F401  (float64)
from clumpylen_jax.cli import main
from clumpylen_jax.errors import ConfigError
from clumpylen_jax.observations import (ObservationSpec, read_observation, resolve_units,
                                        write_cutout)
from clumpylen_jax.observations.config import parse_observation_scene
from clumpylen_jax.observations.frame import fit_frame
from clumpylen_jax.observations.units import zeropoint_mjy_sr, zeropoint_photflam

RA0, DEC0 = 64.038142, -24.067472


def celestial_header(shape, pixel_arcsec, rot_deg=0.0, center=(RA0, DEC0)):
    """A TAN WCS header, north-up east-left rotated by rot_deg, centred on the image."""
    ny, nx = shape
    c, s = math.cos(math.radians(rot_deg)), math.sin(math.radians(rot_deg))
    p = pixel_arcsec / 3600.0
    h = fits.Header()
    h.update(CTYPE1="RA---TAN", CTYPE2="DEC--TAN", CRVAL1=center[0], CRVAL2=center[1],
             CRPIX1=(nx + 1) / 2.0, CRPIX2=(ny + 1) / 2.0,
             CD1_1=-p * c, CD1_2=p * s, CD2_1=p * s, CD2_2=p * c)
    return h


def gaussian_psf_file(path, sigma_pix=1.2, size=15, pixel_arcsec=0.03, scale=1.0):
    y, x = np.mgrid[:size, :size] - (size - 1) / 2
    psf = np.exp(-(x**2 + y**2) / (2 * sigma_pix**2)) * scale
    h = fits.Header()
    h["PIXSCALE"] = pixel_arcsec
    fits.PrimaryHDU(psf, h).writeto(path, overwrite=True)
    return str(path)


# ----------------------------------------------------------------------------- units


def test_mjy_sr_with_pixar_gives_the_ab_magnitude_of_a_known_source(tmp_path):
    """A 25.0 AB source spread over pixels in MJy/sr: Σ data × ZP(PIXAR_SR) gives 25.0 back."""
    pixar = 2.2588e-14
    f_jy = 3631.0 * 10 ** (-0.4 * 25.0)                 # AB definition
    y, x = np.mgrid[:21, :21] - 10
    blob = np.exp(-(x**2 + y**2) / 8.0)
    sci = blob / blob.sum() * f_jy / (1e6 * pixar)      # MJy/sr per pixel
    path = write_cutout(tmp_path / "i2d.fits", sci, np.full(sci.shape, 1e-3),
                        extra={"PIXAR_SR": pixar, "PIXSCALE": 0.031})
    ob = read_observation(ObservationSpec(filter="F200W", image=path))
    assert ob.units_how == "MJy/sr x PIXAR_SR"
    assert ob.zeropoint_ab - 2.5 * np.log10(ob.data.sum()) == pytest.approx(25.0, abs=1e-5)
    # with only a pixel scale, Ω = (pixel / 206264.8″)²
    import astropy.units as u
    omega = ((0.031 * u.arcsec) ** 2).to_value(u.sr)
    assert zeropoint_mjy_sr(omega) == pytest.approx(
        -2.5 * np.log10((1 * u.MJy / u.sr * omega * u.sr / (3631 * u.Jy)).decompose().value),
        abs=1e-9)


def test_photflam_zero_point_matches_astropy_units():
    """ZP from PHOTFLAM/PHOTPLAM equals the AB magnitude of 1 e-/s computed with astropy units."""
    import astropy.units as u
    photflam, photplam = 7.0332e-20, 8057.0          # ACS/WFC F814W-like
    flam = photflam * u.erg / u.s / u.cm**2 / u.AA
    fnu = flam.to(u.Jy, equivalencies=u.spectral_density(photplam * u.AA))
    expected = -2.5 * np.log10((fnu / (3631 * u.Jy)).decompose().value)
    assert zeropoint_photflam(photflam, photplam) == pytest.approx(expected, abs=2e-3)
    assert zeropoint_photflam(photflam, photplam) == pytest.approx(25.94, abs=0.01)


def test_counts_are_divided_by_exptime_and_explicit_zero_point_wins():
    r = resolve_units({"BUNIT": "ELECTRONS", "EXPTIME": 500.0, "PHOTFLAM": 1e-19, "PHOTPLAM": 8000.0},
                      where="x")
    assert r["scale"] == pytest.approx(1 / 500.0) and r["counts_per_unit"] == 1.0
    r = resolve_units({"BUNIT": "e-/s"}, zeropoint_ab=25.5, where="x")
    assert r["zeropoint_ab"] == 25.5
    assert resolve_units({"BUNIT": "nJy"}, where="x")["zeropoint_ab"] == pytest.approx(31.4, abs=1e-3)


def test_weight_map_is_inverse_variance_and_zero_weight_is_masked(tmp_path):
    sci = np.random.default_rng(0).normal(size=(20, 20))
    wht = np.full(sci.shape, 4.0)
    wht[3, 4] = 0.0
    path = write_cutout(tmp_path / "drz.fits", sci, header=None, bunit="ELECTRONS/S",
                        extra={"PHOTFLAM": 1e-19, "PHOTPLAM": 8000.0, "PIXSCALE": 0.05}, wht=wht)
    ob = read_observation(ObservationSpec(filter="F814W", image=path))
    assert ob.variance[0, 0] == pytest.approx(0.25)
    assert not ob.mask[3, 4] and ob.mask.sum() == 399


def test_noise_model_without_map(tmp_path):
    sci = np.abs(np.random.default_rng(1).normal(size=(20, 20)))
    path = write_cutout(tmp_path / "hst.fits", sci, bunit=None, extra={"PIXSCALE": 0.05})
    spec = ObservationSpec(filter="F814W", image=path, units="e-/s", zeropoint_ab=25.94,
                           noise={"background_rms": 0.0075, "exptime_s": 1980.0})
    ob = read_observation(spec)
    mu = np.full(sci.shape, 3.0)
    assert ob.variance_for(mu)[0, 0] == pytest.approx(0.0075**2 + 3.0 / 1980.0)


# ----------------------------------------------------------------------------- frames


def test_two_pixel_scales_and_a_rotated_wcs_share_one_frame():
    """NIRCam SW 0.031″ and LW 0.063″ cutouts of one field, rotated 30°: the LW grid lands
    on the SW frame with its own scale, and θ follows the sky (West, North)."""
    from clumpylen_jax.observations.frame import BandFrame, celestial_wcs
    sw = BandFrame((64, 64), 0.031, celestial_wcs(celestial_header((64, 64), 0.031, 30.0)))
    lw = BandFrame((32, 32), 0.062, celestial_wcs(celestial_header((32, 32), 0.062, 30.0)))
    fr = fit_frame([sw, lw], ["F150W", "F444W"])
    g = fr.grids[1]
    assert g.pixel_arcsec == pytest.approx(0.062, rel=1e-6)
    # both centred on the same sky point: the grids' centres coincide
    assert g.x0_arcsec + 15.5 * g.pixel_arcsec == pytest.approx(0.0, abs=1e-6)
    # a point 1″ along the SW pixel x axis (rotated 30° from West towards North)
    th = fr.theta(np.array([1.0, 0.0]))
    assert th == pytest.approx([math.cos(math.radians(30)), math.sin(math.radians(30))], abs=1e-5)


def test_a_band_turned_against_the_first_lands_where_its_wcs_puts_it():
    """A LW band whose WCS is turned 20° against the SW band's: its grid is a RotatedGrid,
    and every pixel it places in φ is where the two WCSs put it (sky → SW pixels)."""
    from clumpylen_jax.observations.frame import BandFrame, celestial_wcs
    from clumpylen_jax.pixels import RotatedGrid
    sw_w = celestial_wcs(celestial_header((64, 64), 0.031, 30.0))
    lw_w = celestial_wcs(celestial_header((31, 33), 0.062, 50.0, (RA0 + 2e-4, DEC0 - 1e-4)))
    fr = fit_frame([BandFrame((64, 64), 0.031, sw_w), BandFrame((31, 33), 0.062, lw_w)],
                   ["F150W", "F444W"])
    g = fr.grids[1]
    assert isinstance(g, RotatedGrid) and g.shape == (31, 33)
    assert math.degrees(g.angle_rad) == pytest.approx(20.0, abs=1e-3)
    xy = np.array([[0.0, 0.0], [32.0, 0.0], [5.0, 30.0], [17.3, 11.8]])
    ra, dec = lw_w.wcs_pix2world(xy[:, 0], xy[:, 1], 0)
    want = np.stack(sw_w.wcs_world2pix(ra, dec, 0), -1)
    assert np.allclose(fr.pixel_of(fr.phi_of_pixel(xy, 1), 0), want, atol=2e-3)
    assert np.allclose(fr.pixel_of(fr.phi_of_pixel(xy, 1), 1), xy, atol=1e-9)


# ----------------------------------------------------------------------------- bad input


def _toml(v):
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{k} = {_toml(x)}" for k, x in v.items()) + " }"
    if isinstance(v, list):
        return "[" + ", ".join(_toml(x) for x in v) + "]"
    return f"{v!r}".replace("'", '"')


def _scene(tmp_path, obs_tables, fit="clumps = \"none\"\n"):
    text = "[scene]\nname = \"t\"\n"
    for t in obs_tables:
        text += "\n[[observations]]\n" + "".join(f"{k} = {_toml(v)}\n" for k, v in t.items())
    text += "\n[fit]\n" + fit
    p = tmp_path / "scene.toml"
    p.write_text(text)
    return str(p)


def _good(tmp_path, name="good.fits", **kw):
    sci = np.random.default_rng(2).normal(size=(24, 24))
    return write_cutout(tmp_path / name, sci, np.ones_like(sci),
                        extra={"PIXSCALE": 0.031, **kw.pop("extra", {})}, **kw)


def _fails(argv, capsys, *needles):
    rc = main(argv)
    err = capsys.readouterr().err.strip()
    assert rc == 2, err
    assert len(err.splitlines()) == 1 and "Traceback" not in err
    for n in needles:
        assert n in err, err
    return err


@pytest.mark.parametrize("case", ["no_sci", "unknown_units", "no_units", "nan_sigma", "neg_sigma",
                                  "psf_zero", "all_nan", "zero_variance", "no_overlap",
                                  "mirrored_band", "no_uncertainty", "unknown_key", "dup_filter"])
def test_bad_observation_input_is_one_line_and_exit_2(tmp_path, capsys, case):
    good = _good(tmp_path)
    obs = {"filter": "F150W", "image": good}
    tables, needles = [obs], []
    sci = np.random.default_rng(3).normal(size=(24, 24))
    if case == "no_sci":
        p = tmp_path / "table.fits"
        fits.HDUList([fits.PrimaryHDU(), fits.BinTableHDU.from_columns(
            [fits.Column("a", "E", array=np.ones(3))])]).writeto(p)
        obs["image"], needles = str(p), ["observations[F150W].image", "SCI"]
    elif case == "unknown_units":
        obs["image"] = write_cutout(tmp_path / "u.fits", sci, np.ones_like(sci), bunit="furlongs",
                                    extra={"PIXSCALE": 0.03})
        needles = ["units", "zeropoint_ab", "u.fits"]
    elif case == "no_units":
        obs["image"] = write_cutout(tmp_path / "n.fits", sci, np.ones_like(sci), bunit=None,
                                    extra={"PIXSCALE": 0.03})
        needles = ["BUNIT", "n.fits"]
    elif case in ("nan_sigma", "neg_sigma"):
        err = np.ones_like(sci)
        err[5, 5] = np.nan if case == "nan_sigma" else -1.0
        obs["image"] = write_cutout(tmp_path / "e.fits", sci, err, extra={"PIXSCALE": 0.03})
        needles = ["observations[F150W].error", "e.fits"]
    elif case == "psf_zero":
        obs["psf"] = gaussian_psf_file(tmp_path / "psf.fits", scale=0.0)
        needles = ["observations[F150W].psf", "psf.fits"]
    elif case == "all_nan":
        obs["image"] = write_cutout(tmp_path / "nan.fits", np.full_like(sci, np.nan),
                                    np.ones_like(sci), extra={"PIXSCALE": 0.03})
        needles = ["nan.fits", "usable pixels"]
    elif case == "zero_variance":
        obs["image"] = write_cutout(tmp_path / "z.fits", sci, np.zeros_like(sci),
                                    extra={"PIXSCALE": 0.03})
        needles = ["z.fits", "usable pixels"]
    elif case in ("no_overlap", "mirrored_band"):
        far = (RA0 + 0.01, DEC0) if case == "no_overlap" else (RA0, DEC0)
        hdr = celestial_header(sci.shape, 0.03, 20.0, far)
        if case == "mirrored_band":     # East to the right: not the sky's parity
            hdr["CD1_1"], hdr["CD1_2"] = -hdr["CD1_1"], -hdr["CD1_2"]
        obs["image"] = write_cutout(tmp_path / "a.fits", sci, np.ones_like(sci),
                                    header=celestial_header(sci.shape, 0.03))
        tables.append({"filter": "F200W", "image": write_cutout(
            tmp_path / "b.fits", sci, np.ones_like(sci), header=hdr)})
        needles = ["observations[F200W]", "b.fits"] + (["flipped"] if case == "mirrored_band"
                                                       else [])
    elif case == "no_uncertainty":
        obs["image"] = write_cutout(tmp_path / "s.fits", sci, None, extra={"PIXSCALE": 0.03})
        needles = ["observations[F150W].error", "s.fits"]
    elif case == "unknown_key":
        obs["eror"] = "ERR"
        needles = ["observations[F150W].eror", "error"]
    elif case == "dup_filter":
        tables.append(dict(obs))
        needles = ["observations.filter", "F150W"]
    scene = _scene(tmp_path, tables)
    _fails(["fit", scene, "--out", str(tmp_path / "out")], capsys, *needles)
    assert not (tmp_path / "out").exists()


def test_repeated_or_unknown_image_band_is_an_error(tmp_path, capsys):
    good = _good(tmp_path)
    scene = _scene(tmp_path, [{"filter": "F150W", "image": good}])
    _fails(["fit", scene, "--image", f"F150W={good}", "--image", f"f150w={good}", "--out",
            str(tmp_path / "o")], capsys, "--image", "twice")
    _fails(["fit", scene, "--image", f"F444W={good}", "--out", str(tmp_path / "o")], capsys,
           "--image", "F444W")
    # the simulation path names --image too
    _fails(["fit", "single-sersic", "--image", f"F444W={good}", "--out", str(tmp_path / "o")],
           capsys, "--image", "F444W")


def test_scene_parsing_resolves_paths_and_checks_fit_keys(tmp_path):
    doc = {"observations": [{"filter": "f150w", "image": "a.fits", "error": "ERR",
                             "weight": None}], "fit": {"clumps": "starts.ecsv"}}
    doc["observations"][0].pop("weight")
    sc = parse_observation_scene(doc, str(tmp_path / "s.toml"))
    assert sc.observations[0].filter == "F150W"
    assert sc.observations[0].image == str(tmp_path / "a.fits")
    assert sc.observations[0].error == "ERR"          # an HDU name stays a name
    assert sc.fit.clumps == str(tmp_path / "starts.ecsv")
    with pytest.raises(ConfigError, match="fit.clump_re_max_arcsec"):
        parse_observation_scene({"observations": doc["observations"],
                                 "fit": {"clump_re_max_arcsec": -1.0}})
    # the samplers ([fit] method, SCENE.md) and their settings, checked before anything runs
    sc = parse_observation_scene({"observations": doc["observations"],
                                  "fit": {"method": "nuts", "sampler_samples": 50}})
    assert sc.fit.method == "nuts" and sc.fit.sampler_samples == 50
    for key, bad in (("method", "hmc"), ("sampler_samples", 5), ("sampler_chains", 0),
                     ("sampler_warmup", -1)):
        with pytest.raises(ConfigError, match=f"fit.{key}"):
            parse_observation_scene({"observations": doc["observations"], "fit": {key: bad}})
    # the SED fit's age prior: the simulator's clump ages unless `[sps] ages` says otherwise
    sc = parse_observation_scene({"observations": doc["observations"], "scene": {"z_source": 2.0},
                                  "sps": {"ages": {"max_myr": 1000.0}, "dust_av": 0.1}})
    assert sc.age_prior == (-0.5, 1.0, 1000.0) and dict(sc.sps) == {"dust_av": 0.1}
    with pytest.raises(ConfigError, match="sps"):
        parse_observation_scene({"observations": doc["observations"], "sps": "bc03"})
    for ages, setting in (({"min_myr": 0.0}, "sps.ages.min_myr"),
                          ({"min_myr": 50.0, "max_myr": 20.0}, "sps.ages.min_myr"),
                          ({"slope": "flat"}, "sps.ages.slope"), ({"max": 3.0}, r"sps\.ages\.max ="),
                          ({"min_myr": 5000.0, "max_myr": 9000.0}, "sps.ages.min_myr")):
        with pytest.raises(ConfigError, match=setting):   # the last: older than the universe
            parse_observation_scene({"observations": doc["observations"],
                                     "scene": {"z_source": 2.0}, "sps": {"ages": ages}})


# ----------------------------------------------------------------------------- a mock fitted back


def _mock_scene(tmp_path, seed=0):
    """Two bands in MJy/sr (0.03″ and 0.06″ pixels) with a WCS rotated by 35°: a host and two
    clumps rendered by the fit's own model on the data grids, Gaussian noise; starts for the
    clumps offset by ~1.5 pixels from the truth (never the truth)."""
    import jax.numpy as jnp

    from clumpylen_jax.observations import FitOptions
    from clumpylen_jax.observations.fit import make_model_factory
    from clumpylen_jax.observations.frame import BandFrame, celestial_wcs
    from clumpylen_jax.source import Clumps, Sersic, Source

    rng = np.random.default_rng(seed)
    pixar = {0.03: (0.03 / 206264.806) ** 2, 0.06: (0.06 / 206264.806) ** 2}
    bands = [("F150W", 0.03, (40, 40), 0.004), ("F444W", 0.06, (20, 20), 0.003)]
    headers = [celestial_header(shape, pix, 35.0) for _, pix, shape, _ in bands]
    frames = [BandFrame(shape, pix, celestial_wcs(h)) for (_, pix, shape, _), h in
              zip(bands, headers)]
    frame = fit_frame(frames, [b[0] for b in bands])
    f = lambda v: jnp.asarray(v, jnp.float64)  # noqa: E731
    truth = Source(
        bulge=Sersic(flux=f([1.2, 1.0]), re_arcsec=f(0.2), n=f(1.0), q=f(0.45), pa_rad=f(0.6),
                     center_arcsec=f([0.02, -0.03])),
        clumps=Clumps(center_arcsec=f([[0.15, 0.10], [-0.2, -0.12]]), flux=f([[0.3, 0.15],
                                                                             [0.2, 0.25]]),
                      re_arcsec=f([0.03, 0.05]), n=f([1.0, 1.0]), q=f([1.0, 1.0]),
                      pa_rad=f([0.0, 0.0])))

    class _Ob:   # what make_model_factory reads of an observation
        def __init__(self, name, psf):
            self.name, self.psf = name, psf

    from clumpylen_jax.psf import load_psf_fits
    psfs = [load_psf_fits(gaussian_psf_file(tmp_path / f"psf_{n}.fits", 1.3, 15, pix))
            for n, pix, _, _ in bands]
    opts = FitOptions(clumps="starts.ecsv", clump_n=1.0)   # the truth's clumps: n = 1
    model = make_model_factory([_Ob(b[0], p) for b, p in zip(bands, psfs)], frame, opts)(truth)
    images = [np.asarray(i) for i in model.band_images(truth)]
    tables = []
    for (name, pix, shape, sigma), h, img in zip(bands, headers, images):
        sci = img + rng.normal(0, sigma, shape)
        path = write_cutout(tmp_path / f"{name}_i2d.fits", sci, np.full(shape, sigma), header=h,
                            extra={"PIXAR_SR": pixar[pix]})
        tables.append({"filter": name, "image": path, "psf": str(tmp_path / f"psf_{name}.fits")})
    # starts: the truth moved by ~1.5 SW pixels, written as RA/Dec
    start = np.asarray(truth.clumps.center_arcsec) + np.array([[0.04, -0.03], [-0.03, -0.04]])
    ra, dec = frame.radec(start)
    from astropy.table import Table
    Table({"ra_deg": ra, "dec_deg": dec}).write(tmp_path / "starts.ecsv", overwrite=True)
    scene = _scene(tmp_path, tables, fit='clumps = "starts.ecsv"\nclump_n = 1.0\n')
    zps = [zeropoint_mjy_sr(pixar[b[1]]) for b in bands]
    return scene, truth, frame, zps


@pytest.mark.slow
def test_mock_mjy_sr_rotated_wcs_two_scales_fitted_back_with_honest_pulls(tmp_path):
    import json

    from astropy.table import Table
    scene, truth, frame, zps = _mock_scene(tmp_path)
    assert main(["fit", scene, "--out", str(tmp_path / "out"), "-q"]) == 0
    t = Table.read(tmp_path / "out" / "fit.ecsv")
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["success"] and summary["n_clumps"] == 2
    for band, chi2 in summary["chi2_per_dof"].items():
        assert 0.85 < chi2 < 1.15, (band, chi2)
    # match rows to the truth by position (the fit may reorder nothing, but say so)
    true_radec = frame.radec(np.asarray(truth.clumps.center_arcsec))
    pulls = []
    for i in range(2):
        j = int(np.argmin(np.hypot(t["ra_deg"] - true_radec[0][i], t["dec_deg"] - true_radec[1][i])))
        for b, (name, zp) in enumerate(zip(("F150W", "F444W"), zps)):
            true_flux = float(truth.clumps.flux[i, b])
            if t[f"uplim_{name}"][j]:   # not detected there (flag 16): the flux's pull
                assert t["flag"][j] & 16 and not np.isfinite(t[f"mag_{name}_err"][j])
                pulls.append((t[f"flux_{name}"][j] - true_flux) / t[f"flux_{name}_err"][j])
                continue
            true_mag = zp - 2.5 * np.log10(true_flux)
            pulls.append((t[f"mag_{name}"][j] - true_mag) / t[f"mag_{name}_err"][j])
        pulls.append((t["ra_deg"][j] - true_radec[0][i]) / t["ra_deg_err"][j])
        pulls.append((t["dec_deg"][j] - true_radec[1][i]) / t["dec_deg_err"][j])
        pulls.append((t["re_arcsec"][j] - float(truth.clumps.re_arcsec[i])) / t["re_arcsec_err"][j])
    pulls = np.asarray(pulls, float)
    assert np.all(np.isfinite(pulls)) and np.max(np.abs(pulls)) < 4.0, pulls
    host = summary["host"]
    assert abs(host["re_arcsec"] - 0.2) < 4 * host["re_arcsec_err"]
    for name in ("residuals_F150W.fits", "residuals_F444W.fits", "clumps.reg", "fit.png"):
        assert (tmp_path / "out" / name).is_file()
    with fits.open(tmp_path / "out" / "residuals_F444W.fits") as h:
        assert [x.name for x in h[1:]] == ["DATA", "MODEL", "RESIDUAL", "CHI"]
        assert h["CHI"].header["CTYPE1"].startswith("RA")


def _elliptical_psf_file(path, sx, sy, pixel_arcsec, size=41):
    """A Gaussian PSF elongated along the image's x axis (σ in its own pixels), PIXSCALE set."""
    y, x = np.mgrid[:size, :size] - (size - 1) / 2
    h = fits.Header()
    h["PIXSCALE"] = pixel_arcsec
    fits.PrimaryHDU(np.exp(-0.5 * ((x / sx) ** 2 + (y / sy) ** 2)), h).writeto(path, overwrite=True)
    return str(path)


def test_a_band_turned_30_degrees_is_fitted_on_its_own_pixels(tmp_path):
    """F150W (0.03″, WCS at 35°) and F444W (0.06″, WCS at 65°, offset), each with an elliptical
    PSF along its own pixels. The truth of each band is drawn by the aligned renderer in the
    band's own frame (its WCS → positions, PAs turned), 5 sub-pixels per pixel; the fit (3)
    draws F444W on φ-aligned pixels turned onto the data's.

    1. The fit's model at the truth reproduces that independent drawing to < 0.1 σ in both
       bands (the frame from the WCSs, the PSF turned, the overlaps); < 0.2 σ at the edges,
       where the turned band also draws the host's light from beyond its field.
    2. The CLI fit, its clumps started ~1.5 SW pixels off: χ²/dof ≈ 1, and the clumps'
       fluxes (both bands), positions and sizes within 4σ of the truth."""
    import json

    import equinox as eqx
    import jax.numpy as jnp
    from astropy.table import Table

    from clumpylen_jax.model import Accuracy, Band, build_model
    from clumpylen_jax.observations.config import load_observation_scene
    from clumpylen_jax.observations.fit import make_model_factory
    from clumpylen_jax.observations.frame import BandFrame, celestial_wcs
    from clumpylen_jax.observations.run import read_scene_data
    from clumpylen_jax.source import Clumps, Sersic, Source

    rng = np.random.default_rng(5)
    bands = [("F150W", 0.03, (40, 40), 35.0, (RA0, DEC0), 0.004, (1.5, 1.0)),
             ("F444W", 0.06, (24, 24), 65.0, (RA0 + 3e-5, DEC0 - 2e-5), 0.003, (1.3, 0.9))]
    headers = [celestial_header(b[2], b[1], b[3], b[4]) for b in bands]
    wcs = [celestial_wcs(h) for h in headers]
    frame = fit_frame([BandFrame(b[2], b[1], w) for b, w in zip(bands, wcs)], [b[0] for b in bands])
    f = lambda v: jnp.asarray(v, jnp.float64)  # noqa: E731
    host = dict(re=0.35, n=1.0, q=0.45, pa=0.6, c=[0.02, -0.03], flux=[1.2, 1.0])
    clumps = dict(c=np.array([[0.15, 0.10], [-0.2, -0.12]]), re=[0.04, 0.06],
                  flux=np.array([[0.4, 0.3], [0.3, 0.35]]))

    def truth(k=None):
        """The truth in φ (k None), or in band k's own frame (φ of a frame of band k alone)."""
        move, turn, grid, flux = (lambda phi: np.atleast_2d(phi)), 0.0, None, slice(None)
        if k is not None:
            own = fit_frame([BandFrame(bands[k][2], bands[k][1], wcs[k])], [bands[k][0]])
            move = lambda phi: own.phi_of_radec(*frame.radec(np.atleast_2d(phi)))  # noqa: E731
            d = move([[0.0, 0.0], [1.0, 0.0]])
            turn = math.atan2(d[1, 1] - d[0, 1], d[1, 0] - d[0, 0])
            grid, flux = own.grids[0], slice(k, k + 1)
        return grid, Source(
            bulge=Sersic(flux=f(host["flux"][flux]), re_arcsec=f(host["re"]), n=f(host["n"]),
                         q=f(host["q"]), pa_rad=f(host["pa"] + turn),
                         center_arcsec=f(move(host["c"])[0])),
            clumps=Clumps(center_arcsec=f(move(clumps["c"])), flux=f(clumps["flux"][:, flux]),
                          re_arcsec=f(clumps["re"]), n=f([1.0, 1.0]), q=f([1.0, 1.0]),
                          pa_rad=f([0.0, 0.0])))

    tables, clean = [], []
    for k, (name, pix, shape, _, _, sigma, (sx, sy)) in enumerate(bands):
        psf_path = _elliptical_psf_file(tmp_path / f"psf_{name}.fits", sx * 3, sy * 3, pix / 3)
        grid, src = truth(k)
        band = Band(name, pix, 1.0, psf=fits.getdata(psf_path), psf_pixel_arcsec=pix / 3)
        clean.append(np.asarray(eqx.filter_jit(lambda m, x: m.band_images(x)[0])(build_model(
            src, [band], grids=[grid], accuracy=Accuracy(psf_oversampling=5)), src)))
        sci = clean[-1] + rng.normal(0, sigma, shape)
        path = write_cutout(tmp_path / f"{name}_i2d.fits", sci, np.full(shape, sigma),
                            header=headers[k], extra={"PIXAR_SR": (pix / 206264.806) ** 2})
        tables.append({"filter": name, "image": path, "psf": psf_path})
    start = clumps["c"] + np.array([[0.04, -0.03], [-0.03, -0.04]])
    ra, dec = frame.radec(start)
    Table({"ra_deg": ra, "dec_deg": dec}).write(tmp_path / "starts.ecsv", overwrite=True)
    scene = _scene(tmp_path, tables, fit='clumps = "starts.ecsv"\nclump_n = 1.0\n'
                   'psf_oversampling = 3\n')

    obs, fr = read_scene_data(load_observation_scene(scene))
    assert type(fr.grids[1]).__name__ == "RotatedGrid"
    _, src = truth()
    model = make_model_factory(obs, fr, load_observation_scene(scene).fit)(src)
    for k, mu in enumerate(eqx.filter_jit(lambda m, x: m.band_images(x))(model, src)):
        d = np.abs(np.asarray(mu) - clean[k]) / bands[k][5]
        # measured 0.022 σ (F150W), 0.065 σ (F444W) inside; 0.135 σ at F444W's edge
        assert d[4:-4, 4:-4].max() < 0.1 and d.max() < 0.2, (bands[k][0], d.max())

    assert main(["fit", scene, "--out", str(tmp_path / "out"), "-q"]) == 0
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["bands"]["F444W"]["axes_turned_deg"] == pytest.approx(30.0, abs=1e-3)
    assert summary["success"] and summary["n_clumps"] == 2
    for band, chi2 in summary["chi2_per_dof"].items():
        assert 0.85 < chi2 < 1.15, (band, chi2)
    t = Table.read(tmp_path / "out" / "fit.ecsv")
    true_radec = frame.radec(clumps["c"])
    pulls = []
    for i in range(2):
        j = int(np.argmin(np.hypot(t["ra_deg"] - true_radec[0][i], t["dec_deg"] - true_radec[1][i])))
        for b, (name, *_) in enumerate(bands):    # flux: defined below detection too
            pulls.append((t[f"flux_{name}"][j] - clumps["flux"][i, b]) / t[f"flux_{name}_err"][j])
        pulls.append((t["ra_deg"][j] - true_radec[0][i]) / t["ra_deg_err"][j])
        pulls.append((t["dec_deg"][j] - true_radec[1][i]) / t["dec_deg_err"][j])
        pulls.append((t["re_arcsec"][j] - clumps["re"][i]) / t["re_arcsec_err"][j])
    pulls = np.asarray(pulls, float)
    assert np.all(np.isfinite(pulls)) and np.max(np.abs(pulls)) < 4.0, pulls
    with fits.open(tmp_path / "out" / "residuals_F444W.fits") as h:
        assert h["CHI"].data.shape == (24, 24)


def test_simulation_fit_path_rejects_all_nan_and_reads_sci(tmp_path, capsys):
    """Issue 22: `fit SCENE --image` reads the SCI HDU and refuses an image with no usable pixel."""
    nan = write_cutout(tmp_path / "nan.fits", np.full((5, 5), np.nan), bunit=None)
    _fails(["fit", "single-sersic", "--image", f"F200W={nan}", "--out", str(tmp_path / "o")],
           capsys, "--image F200W", "usable pixels")
    from clumpylen_jax.cli import _read_fit_image
    img, var = _read_fit_image("F200W", write_cutout(tmp_path / "s.fits", np.ones((4, 6)), bunit=None))
    assert img.shape == (4, 6) and var is None


def test_fit_without_clumps_reports_the_host():
    """Issue 22: fit.ecsv's header carries the fitted host (flux, R_e, centre) with errors."""
    import jax.numpy as jnp

    from clumpylen_jax.inference.params import make_state, parametrize
    from clumpylen_jax.inference.catalog import host_meta
    from clumpylen_jax.source import Sersic, Source
    f = lambda v: jnp.asarray(v, jnp.float64)  # noqa: E731
    src = Source(bulge=Sersic(f([3.0]), f(0.2), f(1.0), f(0.7), f(0.1), f([0.01, -0.02])))
    param = parametrize(make_state(src, 1), ["bulge.flux", "bulge.re_arcsec", "bulge.center_arcsec"])
    meta = host_meta(param.template, param.labels, [0.1, 0.01, 0.002, 0.003])
    assert meta["bulge"]["flux"] == [3.0] and meta["bulge"]["flux_err"] == [0.1]
    assert meta["bulge"]["re_arcsec_err"] == 0.01
    assert meta["bulge"]["center_arcsec_err"] == [0.002, 0.003]


REAL = __import__("pathlib").Path(__file__).resolve().parents[1].parent / "shared" / "data" / "real"


@pytest.mark.skipif(not (REAL / "rxj1131").is_dir(), reason="real data absent")
def test_real_hst_cutout_with_noise_model_and_psf_extension(tmp_path, capsys):
    """RXJ1131 F814W: e-/s without BUNIT, BKG_RMS and EXPTIME, PSF in an extension."""
    path = str(REAL / "rxj1131" / "rxj1131_f814w.fits")
    spec = ObservationSpec(filter="F814W", image=path, units="e-/s", zeropoint_ab=25.94,
                           noise={"background_rms": 0.0075095, "exptime_s": 1980.0},
                           psf=path, psf_hdu="PSF")
    ob = read_observation(spec)
    assert ob.frame.pixel_arcsec == pytest.approx(0.04999) and ob.frame.wcs is None
    assert ob.mask.all() and ob.psf.array.sum() == pytest.approx(1.0)
    assert ob.variance_for(np.ones(ob.data.shape))[0, 0] == pytest.approx(0.0075095**2 + 1 / 1980.0)
    # without units the file is refused, naming the keyword to add
    scene = _scene(tmp_path, [{"filter": "F814W", "image": path,
                               "noise": {"background_rms": 0.0075, "exptime_s": 1980.0}}])
    _fails(["fit", scene, "--out", str(tmp_path / "o")], capsys, "BUNIT", "rxj1131_f814w.fits")


@pytest.mark.skipif(not (REAL / "abell_s1063_sys4_im1").is_dir(), reason="real data absent")
def test_real_jwst_cutouts_read_in_mjy_sr_with_pixscale():
    d = REAL / "abell_s1063_sys4_im1"
    obs = [read_observation(ObservationSpec(filter=f.upper(), image=str(d / f"s1063_sys4_im1_{f}.fits"),
                                            psf=str(d / f"psf_webbpsf_{f}.fits")))
           for f in ("f115w", "f150w", "f200w")]
    # 1 MJy/sr over a (0.03123″)² pixel: ZP = −2.5 log10(10⁶ Ω / 3631)
    omega = (0.031230659851709842 / 206264.80624709636) ** 2
    for ob in obs:
        assert ob.zeropoint_ab == pytest.approx(-2.5 * np.log10(1e6 * omega / 3631.0), abs=1e-9)
        assert ob.units_how == "MJy/sr x pixel_arcsec^2" and ob.mask.sum() == 120 * 120
    fr = fit_frame([o.frame for o in obs], [o.name for o in obs])
    assert all(g == fr.grids[0] for g in fr.grids)


def test_ds9_region_mask_leaves_pixels_out(tmp_path):
    sci = np.random.default_rng(4).normal(size=(30, 30))
    path = write_cutout(tmp_path / "m.fits", sci, np.ones_like(sci), extra={"PIXSCALE": 0.03})
    reg = tmp_path / "star.reg"
    reg.write_text("# Region file format: DS9\nimage\ncircle(11,21,3)\n")   # 1-based centre
    ob = read_observation(ObservationSpec(filter="F150W", image=path, mask=str(reg)))
    assert not ob.mask[20, 10] and ob.mask[20, 20] and 20 < (~ob.mask).sum() < 40


def test_local_lens_maps_image_ellipses_to_the_source_plane():
    """β = A θ: a round image of R_e r behind pure convergence κ is a round source of R_e
    (1 − κ) r; behind shear γ1 it is an ellipse of axes (1 − κ ∓ γ1) r along β1/β2."""
    from clumpylen_jax.observations.answers import _ellipse_through
    from clumpylen_jax.observations.config import LocalLens
    lens = LocalLens(0.6, (0.0, 0.0))
    re, q, _ = _ellipse_through(np.asarray(lens.matrix), 0.1, 1.0, 0.0)
    assert re == pytest.approx(0.04) and q == pytest.approx(1.0)
    assert lens.magnification == pytest.approx(1 / 0.4**2)
    lens = LocalLens(0.5, (0.2, 0.0))                      # A = diag(0.3, 0.7)
    re, q, pa = _ellipse_through(np.asarray(lens.matrix), 0.1, 1.0, 0.0)
    assert re == pytest.approx(0.07) and q == pytest.approx(0.3 / 0.7)
    assert abs(np.sin(pa)) == pytest.approx(1.0)           # major axis along β2


@pytest.mark.slow
def test_clump_that_grows_from_1_to_5_pixels_matches_a_start_at_5(tmp_path):
    """Issue 17 item 2: stamps are built for the R_e bound, so a clump started at R_e = 1 px
    that converges to 5 px is not truncated: the same answer as a start at 5 px."""
    import jax.numpy as jnp

    from clumpylen_jax.observations import FitOptions
    from clumpylen_jax.observations.fit import fit_observations, make_model_factory
    from clumpylen_jax.observations.run import read_scene_data
    from clumpylen_jax.observations.config import load_observation_scene
    from clumpylen_jax.source import Clumps, Source

    pix, shape = 0.03, (36, 36)
    f = lambda v: jnp.asarray(v, jnp.float64)  # noqa: E731
    truth = Source(clumps=Clumps(center_arcsec=f([[0.01, -0.02]]), flux=f([[2.0]]),
                                 re_arcsec=f([5 * pix]), n=f([1.0]), q=f([1.0]), pa_rad=f([0.0])))
    path = write_cutout(tmp_path / "c.fits", np.random.default_rng(6).normal(0, 0.01, shape),
                        np.full(shape, 0.01), extra={"PIXSCALE": pix})
    scene = load_observation_scene(_scene(tmp_path, [{"filter": "F150W", "image": path}],
                                          fit='host = "none"\nclumps = "none"\n'))
    obs, frame = read_scene_data(scene)
    # n = 1: the Sérsic stamps, whose size is what this checks (round n = 0.5 clumps have none)
    opts = FitOptions(host="none", clumps="none", clump_re_max_arcsec=0.3, clump_n=1.0)
    img = np.asarray(make_model_factory(obs, frame, opts)(truth).band_images(truth)[0])
    rng = np.random.default_rng(5)
    obs = [__import__("dataclasses").replace(obs[0], data=img + rng.normal(0, 0.01, shape))]
    answers = []
    for re0 in (1 * pix, 5 * pix):
        fit = fit_observations(obs, frame, opts, {"phi": np.array([[0.02, 0.0]]),
                                                  "re_arcsec": np.array([re0])})
        answers.append((float(fit.state.source.clumps.re_arcsec[0]),
                        float(fit.state.source.clumps.flux[0, 0])))
        assert fit.success
    (re_a, f_a), (re_b, f_b) = answers
    # the two optima agree to the solver's tolerance (2.5e-4 in R_e measured), far below σ
    assert re_a == pytest.approx(re_b, rel=1e-3) and f_a == pytest.approx(f_b, rel=1e-3)
    assert re_a == pytest.approx(5 * pix, rel=0.1)


def test_an_elliptical_clump_fitted_elliptical_gets_its_shape(tmp_path):
    """clump_shape = "elliptical": a clump of q 0.4 (R_e 3 px along PA 0.7) started without a
    shape (a catalogue's start: q = SHAPE_START_Q, PA 0) comes back with its q, PA and
    major-axis R_e. Started at q = 1, its bound, it stayed round (q had no inverse there and
    PA no gradient): 17 of 19 clumps of the elliptical pulls mocks did."""
    import dataclasses

    import jax.numpy as jnp

    from clumpylen_jax.observations import FitOptions
    from clumpylen_jax.observations.fit import _clumps, fit_observations, make_model_factory
    from clumpylen_jax.observations.run import read_scene_data
    from clumpylen_jax.observations.config import load_observation_scene
    from clumpylen_jax.source import Clumps, Source

    pix, shape, sigma = 0.03, (32, 32), 0.01
    f = lambda v: jnp.asarray(v, jnp.float64)  # noqa: E731
    truth = Source(clumps=Clumps(center_arcsec=f([[0.01, -0.02]]), flux=f([[3.0]]),
                                 re_arcsec=f([3 * pix]), n=f([1.0]), q=f([0.4]), pa_rad=f([0.7])))
    noise = np.random.default_rng(2).normal(0, sigma, shape)
    path = write_cutout(tmp_path / "c.fits", noise, np.full(shape, sigma), extra={"PIXSCALE": pix})
    scene = load_observation_scene(_scene(tmp_path, [{"filter": "F150W", "image": path}],
                                          fit='host = "none"\nclumps = "none"\n'))
    obs, frame = read_scene_data(scene)
    opts = FitOptions(host="none", clumps="none", clump_re_max_arcsec=0.2, clump_n=1.0,
                      clump_shape="elliptical")
    img = np.asarray(make_model_factory(obs, frame, opts)(truth).band_images(truth)[0])
    obs = [dataclasses.replace(obs[0], data=img + noise)]
    # the starts: a round one is moved inside q's bounds; none given: SHAPE_START_Q
    assert float(_clumps(np.zeros((1, 2)), np.ones((1, 1)), [pix], opts, q=[1.0]).q[0]) < 1.0
    fit = fit_observations(obs, frame, opts, {"phi": np.array([[0.0, 0.0]]),
                                              "re_arcsec": np.array([pix])})
    assert fit.success
    cl = fit.state.source.clumps
    err = dict(zip(fit.uncertainty.labels, np.asarray(fit.uncertainty.err)))
    q, re, pa = float(cl.q[0]), float(cl.re_arcsec[0]), float(cl.pa_rad[0])
    assert abs(q - 0.4) < 3 * err["clumps.q[0]"] and err["clumps.q[0]"] < 0.05, (q, err)
    assert abs(re - 3 * pix) < 3 * err["clumps.re_arcsec[0]"], (re, err)
    dpa = (pa - 0.7 + 0.5 * np.pi) % np.pi - 0.5 * np.pi     # PA and PA + π: one ellipse
    assert abs(dpa) < max(3 * err["clumps.pa_rad[0]"], 0.05), (pa, err)


def test_an_unresolved_clump_has_finite_errors_and_a_size_upper_limit(tmp_path):
    """A point source (R_e 0.2 px under a PSF of σ 1.2 px, S/N ~18) started at R_e = 1 px:
    R_e runs to its lower bound. There the LM once pushed u to −446 (dx/du 1e-196), JᵀJ
    underflowed, and the flux and position errors came back as 3500 and 78″; now the flux
    error is the point source's. Its size is flagged unresolved, and the upper limit from
    χ² profiled over the flux is where refitting everything else with R_e held there
    costs Δχ² between 2 and 2.706 (2.706 if nothing but the flux moved)."""
    import dataclasses

    import jax.numpy as jnp

    from clumpylen_jax.inference.size_limits import DELTA_CHI2_UL, re_upper_limit
    from clumpylen_jax.observations import FitOptions
    from clumpylen_jax.observations.config import load_observation_scene
    from clumpylen_jax.observations.fit import (_clumps, fit_observations, free_parameters,
                                                make_model_factory, run_stage)
    from clumpylen_jax.observations.run import read_scene_data
    from clumpylen_jax.source import Clumps, Source

    pix, shape, sigma, psf_sigma = 0.03, (32, 32), 0.01, 1.2
    f = lambda v: jnp.asarray(v, jnp.float64)  # noqa: E731
    truth = Source(clumps=Clumps(center_arcsec=f([[0.01, -0.02]]), flux=f([[1.0]]),
                                 re_arcsec=f([0.2 * pix]), n=f([1.0]), q=f([1.0]),
                                 pa_rad=f([0.0])))
    noise = np.random.default_rng(1).normal(0, sigma, shape)
    path = write_cutout(tmp_path / "c.fits", noise, np.full(shape, sigma), extra={"PIXSCALE": pix})
    psf = gaussian_psf_file(tmp_path / "psf.fits", psf_sigma, 15, pix)
    scene = load_observation_scene(_scene(tmp_path, [{"filter": "F150W", "image": path,
                                                      "psf": psf}],
                                          fit='host = "none"\nclumps = "none"\n'))
    obs, frame = read_scene_data(scene)
    opts = FitOptions(host="none", clumps="none", clump_re_max_arcsec=0.2, clump_n=1.0)
    make_model = make_model_factory(obs, frame, opts)
    obs = [dataclasses.replace(obs[0], data=np.asarray(make_model(truth).band_images(truth)[0])
                               + noise)]
    fit = fit_observations(obs, frame, opts, {"phi": np.array([[0.0, 0.0]]),
                                              "re_arcsec": np.array([pix])})
    assert fit.success
    err = dict(zip(fit.uncertainty.labels, np.asarray(fit.uncertainty.err)))
    # a point source's flux error: σ / √(Σ P²), P the PSF's pixels summing to 1
    p = fits.getdata(psf)
    p = p / p.sum()
    point = sigma / np.sqrt(np.sum(p * p))
    assert point < err["clumps.flux[0,0]"] < 1.6 * point, (err, point)
    assert err["clumps.center_arcsec[0,0]"] < 0.2 * pix, err
    re = float(fit.state.source.clumps.re_arcsec[0])
    assert err["clumps.re_arcsec[0]"] > re                              # flag 16
    model, state = fit.drawing()
    ul = re_upper_limit(model, fit.data, state, 0, opts.clump_re_max_arcsec)
    assert re < 0.2 * pix < ul < psf_sigma * pix, (re, ul)
    held = Source(clumps=_clumps(np.asarray(fit.state.source.clumps.center_arcsec),
                                 np.asarray(fit.state.source.clumps.flux), [ul], opts))
    free = free_parameters(held, frame, opts)
    free.pop("clumps.re_arcsec")
    steps = []
    run_stage("held", make_model(held), obs, held, free, steps)
    rise = steps[-1]["chi2"] - fit.steps[-1]["chi2"]
    assert 2.0 < rise <= DELTA_CHI2_UL * 1.01, rise


# ----------------------------------------------------------------------------- lens models

FIX = __import__("pathlib").Path(__file__).resolve().parents[1] / "fixtures"
MAPS = {"hff": ("lens_hff_x-arcsec-deflect.fits", "lens_hff_y-arcsec-deflect.fits"),
        "lenstool": ("lens_lenstool_dplx.fits", "lens_lenstool_dply.fits")}


def _lens_scene(tmp_path, image, lens: dict, z_source=2.0):
    text = "[scene]\nname = \"t\"\n" + ("" if z_source is None else f"z_source = {z_source}\n")
    text += f"\n[[observations]]\nfilter = \"F200W\"\nimage = \"{image}\"\n"
    text += "\n[fit]\nclumps = \"none\"\n\n[lens]\n"
    text += "".join(f"{k} = {_toml(v)}\n" for k, v in lens.items())
    p = tmp_path / "lensed.toml"
    p.write_text(text)
    return str(p)


def _sis_source_plane(theta_lens, theta_e):
    """β and A of an SIS at θ_L [N, 2] (arcsec): β = θ − θ_E n, A = I − θ_E/r (I − n nᵀ)."""
    r = np.hypot(*theta_lens.T)
    n = theta_lens / r[:, None]
    A = np.eye(2) - (theta_e / r)[:, None, None] * (np.eye(2) - n[:, :, None] * n[:, None, :])
    return theta_lens - theta_e * n, A


@pytest.mark.parametrize("style", ["hff", "lenstool"])
def test_deflection_maps_placed_by_the_cutouts_wcs_give_the_sis_answers(tmp_path, style):
    """Issue 17: a lens model with its own WCS lands on the right sky position. The i2d fixture
    (WCS rotated 25°) is centred on the fixture SIS; β and A at clumps 1.2–1.6" from the lens
    centre agree with the analytic SIS to the 0.2" maps' interpolation (β within 4e-3",
    central-difference A within 0.01)."""
    from clumpylen_jax.lensing._distances import dls_ds
    from clumpylen_jax.observations.config import load_observation_scene
    from clumpylen_jax.observations.lens import source_plane, place_lens
    from clumpylen_jax.observations.run import read_scene_data
    hdr = fits.getheader(FIX / MAPS[style][0])
    scene = load_observation_scene(_lens_scene(tmp_path, FIX / "jwst_like_f200w_i2d.fits", {
        "z_lens": hdr["Z_LENS"], "center_radec_deg": [hdr["LENS_RA"], hdr["LENS_DEC"]],
        "deflection": {"x": str(FIX / MAPS[style][0]), "y": str(FIX / MAPS[style][1])}}))
    obs, frame = read_scene_data(scene)
    lens = place_lens(scene, frame)
    theta = np.array([[1.2, 0.3], [-0.8, 1.1], [0.5, -1.5]])     # fit frame = lens frame here
    np.testing.assert_allclose(lens.lens_theta(theta), theta, atol=1e-8)
    sp = source_plane(lens, theta)
    beta, A = _sis_source_plane(theta, hdr["THETA_E"] * dls_ds(hdr["Z_LENS"], 2.0))
    np.testing.assert_allclose(sp.beta, beta, atol=4e-3)
    np.testing.assert_allclose(sp.A, A, atol=0.01)
    np.testing.assert_allclose(sp.mu, 1 / np.linalg.det(A), rtol=0.03)


def test_analytic_lens_placed_by_an_offset_on_a_bare_cutout_is_exact(tmp_path):
    """A cutout with only a pixel scale, placed by cutout_center_arcsec in an analytic SIS:
    β, A and μ are the SIS's to rounding, and the answers' intrinsic R_e is the image ellipse
    mapped through each clump's own A."""
    from clumpylen_jax.observations.answers import _source_plane_columns
    from clumpylen_jax.observations.config import load_observation_scene
    from clumpylen_jax.observations.lens import source_plane, place_lens
    from clumpylen_jax.observations.run import read_scene_data
    from astropy.table import Table
    scene = load_observation_scene(_lens_scene(tmp_path, _good(tmp_path), {
        "z_lens": 0.4, "components": [{"kind": "sis", "theta_e_arcsec": 0.9}],
        "cutout_center_arcsec": [1.3, -0.4]}))
    obs, frame = read_scene_data(scene)
    lens = place_lens(scene, frame)
    theta = np.array([[0.1, 0.2], [-0.3, 0.05]])
    sp = source_plane(lens, theta)
    beta, A = _sis_source_plane(theta + [1.3, -0.4], 0.9)
    np.testing.assert_allclose(sp.beta, beta, atol=1e-12)
    np.testing.assert_allclose(sp.A, A, atol=1e-12)
    t = Table()
    re, _, _ = _source_plane_columns(t, sp, [np.eye(2) * 1e-6] * 2, np.array([0.1, 0.1]),
                                  np.array([0.01, 0.01]), np.ones(2), np.zeros(2))
    # a round image of R_e r through A is an ellipse whose major axis is r × A's largest
    # singular value (the radial direction, where the SIS does not magnify)
    np.testing.assert_allclose(re, 0.1 * np.linalg.svd(A, compute_uv=False)[:, 0], rtol=1e-12)
    np.testing.assert_allclose(t["magnification"], np.abs(1 / np.linalg.det(A)), rtol=1e-12)


@pytest.mark.parametrize("case", ["off_map", "no_z_source", "unplaced", "both_placements",
                                  "radec_with_wcs", "local_and_model"])
def test_lens_model_bad_input_is_one_line_and_exit_2(tmp_path, capsys, case):
    hdr = fits.getheader(FIX / MAPS["hff"][0])
    maps = {"x": str(FIX / MAPS["hff"][0]), "y": str(FIX / MAPS["hff"][1])}
    lens = {"z_lens": 0.396, "center_radec_deg": [hdr["LENS_RA"], hdr["LENS_DEC"]],
            "deflection": maps}
    image, z = _good(tmp_path), 2.0
    if case == "off_map":                 # 40" from the centre of a 12" map
        lens["cutout_center_radec_deg"] = [hdr["LENS_RA"] + 0.012, hdr["LENS_DEC"]]
        needles = ["lens.deflection", "cover the cutout"]
    elif case == "no_z_source":
        z, needles = None, ["scene.z_source"]
    elif case == "unplaced":
        needles = ["lens.cutout_center_radec_deg", "cutout_center_arcsec"]
    elif case == "both_placements":
        lens.update(cutout_center_arcsec=[0.0, 0.0],
                    cutout_center_radec_deg=[hdr["LENS_RA"], hdr["LENS_DEC"]])
        needles = ["lens", "at most one"]
    elif case == "radec_with_wcs":
        image = str(FIX / "jwst_like_f200w_i2d.fits")
        lens["cutout_center_radec_deg"] = [hdr["LENS_RA"], hdr["LENS_DEC"]]
        needles = ["lens.cutout_center_radec_deg", "WCS"]
    else:
        lens["local"] = {"convergence": 0.5}
        needles = ["lens", "[lens.local] alone"]
    _fails(["fit", _lens_scene(tmp_path, image, lens, z), "--out", str(tmp_path / "out")],
           capsys, *needles)
    assert not (tmp_path / "out").exists()


def test_source_plane_panel_maps_both_images_of_a_source_back_to_it(tmp_path):
    """fit.png's source-plane panel: a compact source at β = (0.15, 0.05)" behind an analytic
    SIS (θ_E 0.9") seen as its two images on 0.1" pixels; the data mapped back peak at β
    within 0.02" (a fifth of a pixel: the pixel centres sample the source that coarsely)."""
    import types

    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from astropy.table import Table

    from clumpylen_jax.observations.config import load_observation_scene
    from clumpylen_jax.observations.lens import place_lens, source_plane
    from clumpylen_jax.observations.outputs import _source_plane_panel
    from clumpylen_jax.observations.run import read_scene_data
    scene = load_observation_scene(_lens_scene(tmp_path, _good(tmp_path, extra={"PIXSCALE": 0.1}), {
        "z_lens": 0.4, "components": [{"kind": "sis", "theta_e_arcsec": 0.9}],
        "cutout_center_arcsec": [0.0, 0.0]}))
    obs, frame = read_scene_data(scene)      # 24 × 24 pixels of 0.1"
    lens = place_lens(scene, frame)
    ny, nx = obs[0].data.shape
    xy = np.stack(np.meshgrid(np.arange(nx, dtype=float), np.arange(ny, dtype=float)), -1)
    beta = source_plane(lens, frame.theta(frame.phi_of_pixel(xy.reshape(-1, 2), 0))).beta
    d2 = np.sum((beta - [0.15, 0.05]) ** 2, -1).reshape(ny, nx)
    ob = types.SimpleNamespace(data=100 * np.exp(-d2 / (2 * 0.05**2)), mask=np.ones((ny, nx), bool),
                               variance=np.ones((ny, nx)), name="F200W")
    fig, ax = plt.subplots()
    _source_plane_panel(ax, ob, frame, lens, Table({"beta1_arcsec": [0.15], "beta2_arcsec": [0.05]}))
    img = ax.images[0]
    x0, x1, y0, y1 = img.get_extent()
    a = np.ma.filled(img.get_array(), np.nan)
    j, i = np.unravel_index(np.nanargmax(a), a.shape)
    step = ((x1 - x0) / a.shape[1], (y1 - y0) / a.shape[0])
    peak = (x0 + (i + 0.5) * step[0], y0 + (j + 0.5) * step[1])
    assert np.hypot(peak[0] - 0.15, peak[1] - 0.05) < 0.02, (peak, step)
    plt.close(fig)


def test_flags_share_the_mock_fits_bits_and_mark_unresolved_sizes():
    """Observation fits use `inference.auto.FLAGS`: R_e at a bound 2, the field's edge 4, and 16
    where σ(R_e) > R_e (a size the data do not measure); NaN σ (R_e held) is not flagged."""
    import types

    import jax.numpy as jnp

    from clumpylen_jax.inference.auto import FLAGS
    from clumpylen_jax.observations import FitOptions
    from clumpylen_jax.observations.answers import _flags
    from clumpylen_jax.pixels import Grid
    opts = FitOptions()
    re = jnp.asarray([0.05, opts.clump_re_min_arcsec, 0.05, 0.05])
    fit = types.SimpleNamespace(success=True, clump_unconverged=None, state=types.SimpleNamespace(
        source=types.SimpleNamespace(clumps=types.SimpleNamespace(re_arcsec=re))))
    frame = types.SimpleNamespace(grids=[Grid(0.0, 0.0, 0.03, 20, 20)])
    pix = np.array([[10.0, 10.0], [10.0, 10.0], [0.2, 10.0], [10.0, 10.0]])
    re_err = np.array([0.01, 0.01, 0.01, 0.2])
    flags = _flags(fit, frame, pix, opts, re_err > np.asarray(re))
    assert list(flags) == [0, FLAGS["re_at_bound"] | FLAGS["size_unresolved"],
                           FLAGS["position_at_box_edge"], FLAGS["size_unresolved"]]
    held = _flags(fit, frame, pix, opts, np.full(4, np.nan) > np.asarray(re))
    assert list(held) == [0, FLAGS["re_at_bound"], FLAGS["position_at_box_edge"], 0]
    # 64 where the counting's host alternative moves the clump (`host_alternative_fluxes`)
    alt = _flags(fit, frame, pix, opts, np.full(4, np.nan) > np.asarray(re),
                 np.array([True, False, False, True]))
    assert list(alt) == [FLAGS["host_alternative"], FLAGS["re_at_bound"],
                         FLAGS["position_at_box_edge"], FLAGS["host_alternative"]]
    # 1 where a sampler's chains did not mix for that clump (`sample.unmixed_clumps`)
    fit.clump_unconverged = np.array([False, False, True, False])
    mixed = _flags(fit, frame, pix, opts, np.full(4, np.nan) > np.asarray(re))
    assert list(mixed) == [0, FLAGS["re_at_bound"],
                           FLAGS["position_at_box_edge"] | FLAGS["not_converged"], 0]


def test_alternative_magnitudes_are_the_alternatives_fluxes_in_ab():
    """`mag_alt_<F>`: the AB magnitude of the flux each clump has in the host alternative
    (`host_alternative_fluxes`), NaN where none moves it (NaN) or where it has no clump (0)."""
    import types

    from astropy.table import Table

    from clumpylen_jax.observations.answers import _alternative_columns
    t = Table({"id": [0, 1, 2]})
    obs = [types.SimpleNamespace(name="F150W", zeropoint_ab=28.0),
           types.SimpleNamespace(name="F444W", zeropoint_ab=27.0)]
    _alternative_columns(t, np.array([[10.0, 1.0], [np.nan, np.nan], [0.0, 0.0]]), obs)
    assert np.allclose(t["mag_alt_F150W"][:1], 28.0 - 2.5) and np.allclose(t["mag_alt_F444W"][:1], 27.0)
    assert np.isnan(t["mag_alt_F150W"][1:]).all() and np.isnan(t["mag_alt_F444W"][1:]).all()


def test_final_images_drawn_by_the_counting_model_are_the_fits_own():
    """`observations.fit._chi2` with the automatic stage's model and clump capacity
    (`render`: the state padded with dark clumps, a program the counting compiled) gives
    the χ² and images of the joint fit's own model, to rounding."""
    import dataclasses

    import jax.numpy as jnp

    from clumpylen_jax.inference.likelihood import make_data
    from clumpylen_jax.inference.mock import TOY_ACCURACY, toy_bands
    from clumpylen_jax.inference.params import make_state
    from clumpylen_jax.model import build_model
    from clumpylen_jax.observations.fit import _chi2
    from clumpylen_jax.source import Clumps, Sersic, Source

    bands = toy_bands(2, psf_sigma_pix=1.0)
    acc = dataclasses.replace(TOY_ACCURACY, clump_pixels="exponential_mog")
    field = ((-0.6, 0.6), (-0.6, 0.6))
    host = Sersic(jnp.array([40.0, 30.0]), jnp.asarray(0.25), jnp.asarray(1.5), jnp.asarray(0.7),
                  jnp.asarray(0.4), jnp.array([0.02, -0.01]))

    def source(n, shift=0.0):
        c = np.array([[-0.2, 0.1], [0.2, -0.15], [0.05, 0.25], [0.3, 0.3], [-0.3, -0.3]])[:n]
        return Source(bulge=host, clumps=Clumps(
            jnp.asarray(c + shift), jnp.asarray(np.arange(1.0, 2 * n + 1).reshape(n, 2)),
            jnp.full(n, 0.03 + shift), jnp.ones(n), jnp.ones(n), jnp.zeros(n)))
    own = build_model(source(3), bands, field_arcsec=field, accuracy=acc)
    counting = build_model(source(5, 0.01), bands, field_arcsec=field, accuracy=acc)
    state = make_state(source(3), 2, background_counts_per_s=np.array([0.1, -0.2]))
    shape = own.layouts[0].grid.shape
    rng = np.random.default_rng(3)
    data = make_data(own, [rng.normal(1.0, 0.1, shape) for _ in bands],
                     [np.full(shape, 0.01)] * 2, kind="gaussian")
    chi2, images = _chi2(own, data, state)
    chi2_r, images_r = _chi2(own, data, state, render=(counting, 5))
    assert np.allclose(chi2_r, chi2, rtol=1e-12, atol=0)
    for a, b in zip(images_r, images):
        assert np.abs(a - b).max() <= 1e-12 * np.abs(b).max()


def test_fit_method_nuts_samples_the_observed_fit_from_its_optimum(tmp_path):
    """`clumpylen fit SCENE --method nuts` on the two-band mock (clumps started off the truth):
    the sampler runs from the joint fit's optimum and the catalogue reports the chains'
    median and standard deviation (checked against chains.npz), summary.json the sampler's
    diagnostics, fit.ecsv's header that its errors are posterior ones. A short run: the
    slow suite's mock pull test is where accuracy is judged."""
    import json

    from astropy.table import Table
    scene, truth, frame, zps = _mock_scene(tmp_path)
    text = open(scene).read() + "sampler_chains = 1\nsampler_warmup = 40\nsampler_samples = 40\n"
    open(scene, "w").write(text)
    assert main(["fit", scene, "--out", str(tmp_path / "out"), "-q", "--method", "nuts"]) == 0
    out = tmp_path / "out"
    t = Table.read(out / "fit.ecsv")
    summary = json.loads((out / "summary.json").read_text())
    s = summary["sampler"]
    assert s["method"] == "nuts" and s["chains"] == 1 and s["draws_per_chain"] == 40
    assert s["divergent"] == 0 and 0.3 < s["acceptance"] <= 1.0
    assert 0.3 < s["laplace_mismatch"] < 10   # the whitening describes this posterior
    assert s["metric"] == "fisher" and s["laplace_mismatch_fisher"] == s["laplace_mismatch"]
    assert t.meta["errors"] == "posterior (nuts)"
    with np.load(out / "chains.npz") as c:
        labels = list(c["labels"])
        x = c["samples_x"].reshape(-1, len(labels))
        assert c["samples_x"].shape == (1, 40, summary["n_free"]) and np.all(np.isfinite(x))
    for i in range(2):
        k = labels.index(f"clumps.flux[{i},0]")
        flux, err = np.median(x[:, k]), np.std(x[:, k], ddof=1)
        if t["uplim_F150W"][i]:    # flux/σ < detection_snr (3): the upper limit, no error
            assert flux < 3 * err and np.isnan(t["mag_F150W_err"][i])
            mag = zps[0] - 2.5 * np.log10(max(flux, 0.0) + 3 * err)
            assert abs(t["mag_F150W"][i] - mag) < 1e-9
            continue
        mag, mag_err = zps[0] - 2.5 * np.log10(flux), 2.5 / np.log(10) * err / flux
        assert abs(t["mag_F150W"][i] - mag) < 1e-9 and abs(t["mag_F150W_err"][i] - mag_err) < 1e-9
    for i in range(2):
        k = labels.index(f"clumps.re_arcsec[{i}]")
        assert abs(t["re_arcsec"][i] - np.median(x[:, k])) < 1e-12
    assert all(0.8 < v < 1.25 for v in summary["chi2_per_dof"].values())
    assert [st["stage"] for st in summary["steps"]][-1] == "nuts"


def test_unmixed_chains_flag_only_their_clumps():
    """A clump is flagged "not converged" (bit 1) when R̂ of one of its own parameters is above
    the limit or not finite; the host's R̂ flags no clump."""
    from types import SimpleNamespace

    from clumpylen_jax.observations.sample import unmixed_clumps
    chains = SimpleNamespace(
        labels=("bulge.n[]", "clumps.flux[0,0]", "clumps.flux[1,1]", "clumps.re_arcsec[2]",
                "clumps.re_arcsec[11]", "background[0]"),
        rhat=np.array([3.0, 1.01, 1.2, np.nan, 1.05, 2.0]))
    np.testing.assert_array_equal(unmixed_clumps(chains, 12),
                                  [False, True, True] + [False] * 9)
    np.testing.assert_array_equal(unmixed_clumps(chains, 12, rhat_max=1.001),
                                  [True, True, True] + [False] * 8 + [True])


@pytest.mark.slow
def test_fit_method_emcee_from_the_scene_writes_walkers_chains(tmp_path):
    """`[fit] method = "emcee"` (no --method): 2 × parameters + 2 walkers started around the
    optimum; burn-in = sampler_warmup steps dropped; the catalogue is the walkers' median."""
    import json

    from astropy.table import Table
    scene, truth, frame, zps = _mock_scene(tmp_path)
    text = open(scene).read() + 'method = "emcee"\nsampler_warmup = 20\nsampler_samples = 30\n'
    open(scene, "w").write(text)
    assert main(["fit", scene, "--out", str(tmp_path / "out"), "-q"]) == 0
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    n = summary["n_free"]
    assert summary["sampler"]["method"] == "emcee" and summary["sampler"]["chains"] == 2 * n + 2
    t = Table.read(tmp_path / "out" / "fit.ecsv")
    assert t.meta["errors"] == "posterior (emcee)"
    with np.load(tmp_path / "out" / "chains.npz") as c:
        assert c["samples_x"].shape == (2 * n + 2, 30, n)
        k = list(c["labels"]).index("clumps.re_arcsec[1]")
        assert abs(t["re_arcsec"][1] - np.median(c["samples_x"][..., k])) < 1e-12


def test_images_of_one_source_behind_an_sis_share_a_source_id(tmp_path):
    """Behind an analytic SIS (θ_E 0.9") the two images of β = (0.15, 0.05)" (θ± = (|β| ± θ_E)
    β/|β|, opposite parity) get one source_id; a neighbour 0.15" from the outer image, whose
    β is only 0.023" away (below the 0.1" match), stays its own: same parity and close, so
    not another image of the clump; a clump of another source stays alone. The colours' χ²
    of a group is that of the members about their weighted mean."""
    from astropy.table import Table

    from clumpylen_jax.observations.config import load_observation_scene
    from clumpylen_jax.observations.lens import place_lens, source_plane
    from clumpylen_jax.observations.multiple_images import group_images, image_groups
    from clumpylen_jax.observations.run import read_scene_data
    scene = load_observation_scene(_lens_scene(tmp_path, _good(tmp_path, extra={"PIXSCALE": 0.1}), {
        "z_lens": 0.4, "components": [{"kind": "sis", "theta_e_arcsec": 0.9}],
        "cutout_center_arcsec": [0.0, 0.0]}))
    obs, frame = read_scene_data(scene)
    lens = place_lens(scene, frame)
    b = np.array([0.15, 0.05])
    u = b / np.hypot(*b)
    b2 = np.array([-0.3, 0.2])
    theta = np.array([(np.hypot(*b) + 0.9) * u, (np.hypot(*b) - 0.9) * u,
                      (np.hypot(*b) + 0.9) * u + 0.15 * np.array([-u[1], u[0]]),
                      (np.hypot(*b2) + 0.9) * b2 / np.hypot(*b2)])
    sp = source_plane(lens, theta)
    np.testing.assert_allclose(sp.beta[:2], [b, b], atol=1e-12)
    assert sp.mu[0] > 0 > sp.mu[1] and 0.01 < np.hypot(*(sp.beta[2] - b)) < 0.1
    sid = group_images(sp.beta, np.zeros((4, 2, 2)), sp.mu, theta, 0.1, 1.0)
    assert sid[0] == sid[1] and len({sid[0], sid[2], sid[3]}) == 3, sid
    # a looser separation rule links the same-parity neighbour too: the rule is what keeps it out
    assert len(set(group_images(sp.beta, np.zeros((4, 2, 2)), sp.mu, theta, 0.1, 0.1))) == 2
    t = Table({"id": np.arange(4), "source_id": sid, "beta1_arcsec": sp.beta[:, 0],
               "beta2_arcsec": sp.beta[:, 1], "mag_A": [25.5, 26.7, 27.0, 26.0],
               "mag_A_err": [0.06, 0.08, 0.1, 0.1], "mag_B": [25.0, 26.0, 26.5, 25.0],
               "mag_B_err": [0.08, 0.06, 0.1, 0.1]})
    (g,) = image_groups(t, ["A", "B"])
    assert g["members"] == [0, 1] and g["colour_dof"] == 1
    np.testing.assert_allclose(g["colours"]["A-B"], [0.5, 0.7])
    # two colours 0.2 apart, each σ = 0.1: χ² = 0.2² / (0.1² + 0.1²) = 2
    np.testing.assert_allclose(g["colour_chi2"], 2.0, rtol=1e-12)
    np.testing.assert_allclose(g["beta_arcsec"], b, atol=1e-12)
