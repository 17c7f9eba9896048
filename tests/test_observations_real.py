"""Real-product conventions of observed images (issue 17): huge σ as a mask, the noise model
from the header, PIX2A pixel matrices without a WCS, the PSF extension of the image file, and
the two real cutouts of ../shared/data/real read as the benchmark scenes describe them.

Every case is read-only (no fit, no compile), so the file runs in seconds; the whole fits of
the real scenes are in benchmarks/bench_fit_observations.py and the slow test at the end.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from astropy.io import fits

import clumpylen_jax  # noqa: F401  (float64)
from clumpylen_jax.cli import main
from clumpylen_jax.errors import ConfigError
from clumpylen_jax.observations import ObservationSpec, read_observation, write_cutout
from clumpylen_jax.observations.config import load_observation_scene
from clumpylen_jax.observations.frame import fit_frame
from clumpylen_jax.observations.read import HUGE_SIGMA_FACTOR

ROOT = Path(__file__).resolve().parents[1]
REAL = ROOT.parent / "shared" / "data" / "real"
SCENES = ROOT / "benchmarks" / "real"
# the rxj1131 matrix (samana's transform_pix2angle): arcsec per pixel, East and North
RXJ_MATRIX = [[0.02065827, 0.04552853], [0.04552853, -0.02065827]]


def gaussian(size=11, sigma=1.3):
    y, x = np.mgrid[:size, :size] - (size - 1) / 2
    return np.exp(-(x**2 + y**2) / (2 * sigma**2))


# ----------------------------------------------------------------------------- huge σ


@pytest.mark.parametrize("flag", [1e10, 1e30, 3.0e38])   # 3e38: float32 max, σ² overflows
def test_pixels_with_a_huge_sigma_are_masked_without_numeric_trouble(tmp_path, flag):
    rng = np.random.default_rng(5)
    sci = rng.normal(size=(24, 24))
    err = np.full(sci.shape, 0.02)
    err[2:5, 3:9] = flag               # a pipeline's "do not use" σ
    sci[2:5, 3:9] = 1e4                # with garbage data under it
    ob = read_observation(ObservationSpec(filter="F150W", image=write_cutout(
        tmp_path / "h.fits", sci, err, extra={"PIXSCALE": 0.031})))
    assert (~ob.mask).sum() == 18 and not ob.mask[3, 5]
    assert np.all(np.isfinite(ob.variance)) and np.all(np.isfinite(ob.data))
    assert ob.data[3, 5] == 0.0        # not left to pull on anything
    # a σ up to the factor (a bright star's Poisson σ is ~10³ × the sky's) stays in
    err[2:5, 3:9] = 0.02 * HUGE_SIGMA_FACTOR / 10
    ob = read_observation(ObservationSpec(filter="F150W", image=write_cutout(
        tmp_path / "s.fits", sci, err, extra={"PIXSCALE": 0.031})))
    assert ob.mask.all()


def test_chi2_per_dof_does_not_count_huge_sigma_pixels(tmp_path):
    """Masked-by-σ pixels are no degrees of freedom (else χ²/dof is biased low)."""
    from clumpylen_jax.observations.outputs import chi2_per_dof
    sci = np.random.default_rng(6).normal(size=(20, 20))
    err = np.ones_like(sci)
    err[:10] = 1e30
    ob = read_observation(ObservationSpec(filter="F150W", image=write_cutout(
        tmp_path / "c.fits", sci, err, extra={"PIXSCALE": 0.031})))

    class Fit:      # the two things chi2_per_dof reads of a fit
        images = (np.zeros(sci.shape),)
        data = type("D", (), {"variances": (ob.variance,), "n_diffuse": (0,)})
        param = type("P", (), {"labels": ()})
    assert ob.mask.sum() == 200
    assert chi2_per_dof([ob], Fit)["F150W"] == pytest.approx(np.mean(sci[10:] ** 2), rel=1e-6)


# ----------------------------------------------------------------------------- noise from header


def test_noise_model_from_the_header_when_the_scene_gives_part_or_none_of_it(tmp_path):
    sci = np.abs(np.random.default_rng(1).normal(size=(20, 20)))
    path = write_cutout(tmp_path / "hst.fits", sci, bunit="e-/s",
                  extra={"PIXSCALE": 0.05, "BKG_RMS": 0.0075, "EXPTIME": 1980.0})
    mu = np.full(sci.shape, 3.0)
    want = 0.0075**2 + 3.0 / 1980.0
    for noise in ({}, None, {"exptime_s": 1980.0}, {"background_rms": 0.0075}):
        ob = read_observation(ObservationSpec(filter="F814W", image=path, zeropoint_ab=25.94,
                                              noise=noise))
        assert ob.variance_for(mu)[0, 0] == pytest.approx(want), noise
        assert "header" in ob.noise_how
    # the scene's value wins over the header's
    ob = read_observation(ObservationSpec(filter="F814W", image=path, zeropoint_ab=25.94,
                                          noise={"background_rms": 0.01}))
    assert ob.variance_for(mu)[0, 0] == pytest.approx(1e-4 + 3.0 / 1980.0)
    # noise = {} with no BKG_RMS anywhere names the setting and the keyword
    bare = write_cutout(tmp_path / "bare.fits", sci, bunit="e-/s", extra={"PIXSCALE": 0.05, "EXPTIME": 9.0})
    with pytest.raises(ConfigError) as e:
        read_observation(ObservationSpec(filter="F814W", image=bare, zeropoint_ab=25.0, noise={}))
    assert e.value.setting == "observations[F814W].noise.background_rms"
    assert "BKG_RMS" in str(e.value) and "bare.fits" in str(e.value)


# ----------------------------------------------------------------------------- pixel matrix


def test_pix2a_header_matrix_turns_pixels_into_theta(tmp_path):
    sci = np.random.default_rng(2).normal(size=(16, 16))
    full = {f"PIX2A{i + 1}{j + 1}": RXJ_MATRIX[i][j] for i in range(2) for j in range(2)}
    half = {"PIX2A11": RXJ_MATRIX[0][0], "PIX2A12": RXJ_MATRIX[0][1]}
    for extra, how in ((full, "PIX2A11..PIX2A22"), (half, "sky parity")):
        ob = read_observation(ObservationSpec(filter="F150W", image=write_cutout(
            tmp_path / "m.fits", sci, np.ones_like(sci), extra={"PIXSCALE": 0.04999, **extra})))
        assert how in ob.frame_how
        fr = fit_frame([ob.frame], ["F150W"])
        # θ1 = −East, θ2 = North: one pixel step along x is (−0.02066, 0.04553)″ in θ
        th = fr.theta(np.array([ob.frame.pixel_arcsec, 0.0]))
        assert th == pytest.approx([-RXJ_MATRIX[0][0], RXJ_MATRIX[1][0]], rel=2e-4)
        assert fr.phi_of_theta(th) == pytest.approx([ob.frame.pixel_arcsec, 0.0], abs=1e-9)
        # a position angle turns with the pixels: x axis (pa_φ = 0) → atan2(θ2, θ1)
        assert float(fr.pa_theta(np.zeros(2), 0.0)[0]) == pytest.approx(math.atan2(th[1], th[0]))
    # the scene's matrix wins; without one, x is West and y North
    ob = read_observation(ObservationSpec(filter="F150W", image=write_cutout(
        tmp_path / "n.fits", sci, np.ones_like(sci), extra={"PIXSCALE": 0.05}),
        pixel_matrix_arcsec=[[-0.05, 0.0], [0.0, 0.05]]))
    assert fit_frame([ob.frame], ["F150W"]).theta(np.array([1.0, 2.0])) == pytest.approx([1.0, 2.0])


def test_bands_of_two_pixel_matrices_are_concentric_and_turned_by_their_difference():
    """Without a WCS, a band whose pixel matrix is RXJ1131's (turned against North-up) beside
    a North-up band: concentric, its pixels turned by the matrices' relative angle, and θ of
    its pixels the same through either band."""
    from clumpylen_jax.observations.frame import BandFrame
    from clumpylen_jax.pixels import RotatedGrid
    north_up = ((-0.05, 0.0), (0.0, 0.05))
    fr = fit_frame([BandFrame((16, 16), 0.05, None, north_up),
                    BandFrame((20, 20), 0.05, None, tuple(map(tuple, RXJ_MATRIX)))], ["A", "B"])
    g = fr.grids[1]
    assert isinstance(g, RotatedGrid)
    m = np.asarray(RXJ_MATRIX, float)
    want = math.atan2(m[1, 0], -m[0, 0])       # pixel x's direction in θ (West, North)
    assert math.remainder(g.angle_rad - want, 2 * math.pi) == pytest.approx(0.0, abs=1e-9)
    assert g.position_of(np.array([9.5, 9.5])) == pytest.approx([0.0, 0.0], abs=1e-12)
    # θ = (West, North) of pixel steps from the centre, the matrix taken at the band's pixel side
    to_theta = np.diag([-1.0, 1.0]) @ m * (0.05 / math.sqrt(abs(np.linalg.det(m))))
    xy = np.array([[0.0, 0.0], [19.0, 3.0]])
    theta = fr.theta(fr.phi_of_pixel(xy, 1))
    assert theta == pytest.approx((xy - 9.5) @ to_theta.T, abs=1e-9)


@pytest.mark.parametrize("case", ["mirror", "scale", "partial", "psf_is_image", "psf_nan"])
def test_bad_matrix_or_psf_hdu_is_one_line_and_exit_2(tmp_path, capsys, case):
    sci = np.random.default_rng(3).normal(size=(16, 16))
    extra = {"PIXSCALE": 0.05}
    obs = {"filter": "F150W"}
    needles = ["observations[F150W]"]
    tables = [obs]
    if case == "mirror":
        obs["pixel_matrix_arcsec"] = [[0.05, 0.0], [0.0, 0.05]]
        needles += ["pixel_matrix_arcsec", "sky parity"]
    elif case == "scale":
        obs["pixel_matrix_arcsec"] = [[-0.03, 0.0], [0.0, 0.03]]
        needles += ["pixel_matrix_arcsec", "pixel scale"]
    elif case == "partial":
        extra.update(PIX2A11=0.05, PIX2A21=0.0)
        needles += ["pixel_matrix_arcsec", "PIX2A22", "x.fits"]
    elif case == "psf_is_image":
        obs["psf"] = "x.fits"
        needles += ["psf_hdu", "x.fits"]
    elif case == "psf_nan":
        bad = gaussian()
        bad[3, 3] = np.nan
        obs["psf"] = write_cutout(tmp_path / "p.fits", bad, extra={"PIXSCALE": 0.05}, bunit=None)
        needles += ["psf", "p.fits"]
    obs["image"] = write_cutout(tmp_path / "x.fits", sci, np.ones_like(sci), extra=extra)
    text = "[scene]\nname = \"t\"\n"
    for t in tables:
        text += "\n[[observations]]\n" + "".join(
            f"{k} = {json.dumps(v)}\n" for k, v in t.items())
    (tmp_path / "s.toml").write_text(text + "\n[fit]\nclumps = \"none\"\n")
    rc = main(["fit", str(tmp_path / "s.toml"), "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err.strip()
    assert rc == 2, err
    assert len(err.splitlines()) == 1 and "Traceback" not in err, err
    for n in needles:
        assert n in err, err
    assert not (tmp_path / "out").exists()


def test_psf_extension_of_the_image_file_is_found_by_name(tmp_path):
    sci = np.random.default_rng(4).normal(size=(16, 16))
    path = write_cutout(tmp_path / "q.fits", sci, np.ones_like(sci), psf=gaussian() * 7.0)
    fits.setval(path, "PIXSCALE", value=0.05, ext=0)    # as in the rxj1131 file: primary header
    ob = read_observation(ObservationSpec(filter="F814W", image=path, psf=path))
    assert ob.psf.array.shape == (11, 11) and ob.psf.array.sum() == pytest.approx(1.0)
    assert ob.psf.pixel_arcsec == pytest.approx(0.05)     # PIXSCALE of the primary header


# ----------------------------------------------------------------------------- the real scenes


@pytest.mark.skipif(not (REAL / "rxj1131").is_dir(), reason="../shared/data/real absent")
def test_rxj1131_scene_reads_the_header_noise_pix2a_psf_extension_and_quasar_mask():
    from clumpylen_jax.observations.run import read_scene_data
    obs, fr = read_scene_data(load_observation_scene(str(SCENES / "rxj1131_f814w.toml")))
    ob = obs[0]
    assert ob.noise_exptime_s == 1980.0 and ob.variance[0, 0] == pytest.approx(0.0075095**2)
    assert np.asarray(ob.frame.pixel_matrix_arcsec) == pytest.approx(np.asarray(RXJ_MATRIX))
    assert ob.psf.array.shape == (77, 77) and ob.psf.effective and "[2]" in ob.psf.source
    # four quasar circles of 8 px: ~4 × π 8² pixels, none of the lens galaxy's centre
    assert 4 * 180 < (~ob.mask).sum() < 4 * 220 and ob.mask[65, 73]
    for x, y in ((101, 98), (78, 107), (54, 106), (69, 43)):     # the four brightest peaks
        assert not ob.mask[y, x]


@pytest.mark.skipif(not (REAL / "abell_s1063_sys4_im1").is_dir(), reason="../shared/data/real absent")
def test_s1063_scene_reads_three_bands_on_one_grid():
    from clumpylen_jax.observations.run import read_scene_data
    obs, fr = read_scene_data(load_observation_scene(str(SCENES / "s1063_sys4_im1.toml")))
    assert [o.name for o in obs] == ["F115W", "F150W", "F200W"]
    assert all(o.mask.all() and "ERR" in o.noise_how for o in obs)
    assert all(g == fr.grids[0] for g in fr.grids)


# ----------------------------------------------------------------------------- the whole command


def _mock_arc_with_flagged_pixels(tmp_path):
    """A 40² MJy/sr cutout with only PIXSCALE: an elliptical exponential host and two compact
    knots, Gaussian PSF, noise of known σ, and a flagged stripe (σ = 1e30, data 1e5) — the
    three formats of the issue's outside checks in one file. Returns (scene path, knots)."""
    rng = np.random.default_rng(11)
    n, pix, sig = 40, 0.03, 0.02
    y, x = np.mgrid[:n, :n].astype(float)
    xr, yr = (x - 20) * 0.8 + (y - 19) * 0.6, -(x - 20) * 0.6 + (y - 19) * 0.8
    img = 0.25 * np.exp(-np.hypot(xr / 7.0, yr / 3.0))
    knots = [(16.0, 17.0), (25.0, 23.0)]
    for (kx, ky), amp in zip(knots, (1.0, 0.6)):
        img += amp * np.exp(-((x - kx) ** 2 + (y - ky) ** 2) / (2 * 0.8**2))
    psf = gaussian(15, 1.2)
    from scipy.signal import fftconvolve
    img = fftconvolve(img, psf / psf.sum(), mode="same")
    sci = img + rng.normal(0.0, sig, img.shape)
    err = np.full(img.shape, sig)
    sci[:, 36:38], err[:, 36:38] = 1e5, 1e30
    write_cutout(tmp_path / "arc.fits", sci, err, extra={"PIXSCALE": pix})
    p = tmp_path / "psf.fits"
    fits.PrimaryHDU(psf.astype(np.float32), fits.Header({"PIXSCALE": pix})).writeto(p)
    (tmp_path / "arc.toml").write_text(
        '[scene]\nname = "mock-arc"\n\n[[observations]]\nfilter = "F150W"\n'
        'image = "arc.fits"\npsf = "psf.fits"\n\n[fit]\nclumps = "auto"\nmax_clumps = 4\n')
    return str(tmp_path / "arc.toml"), knots


@pytest.mark.slow
def test_auto_fit_of_a_mock_cutout_with_huge_sigma_pixels_through_the_command(tmp_path, capsys):
    """`clumpylen fit` with clumps = "auto" (never a catalogue): χ²/dof near 1 with the flagged
    stripe left out, no |χ| > 5 at the clumps, and a component (clump, or the host's centre)
    on each knot. Measured (load 14 on 2 cores): 514 s wall, χ²/dof 1.02; the host Sérsic
    (n 5.4) took the brighter knot and two clumps its smooth light — the host/clump
    degeneracy this test pins down until the host's n range is narrowed."""
    scene, knots = _mock_arc_with_flagged_pixels(tmp_path)
    assert main(["fit", scene, "--out", str(tmp_path / "out"), "--quiet"]) == 0
    out = tmp_path / "out"
    check_mock_fit(out, knots)


def test_auto_stage_of_the_command_runs_at_the_looser_tolerance(tmp_path, monkeypatch):
    """`auto_starts` asks the automatic stage for AUTO_RTOL (the joint fit refits from its
    optimum), no errors and no moves; every other caller keeps AutoOptions' rtol."""
    from clumpylen_jax.inference import auto
    from clumpylen_jax.observations import run
    seen = {}

    def capture(*args, options, **kwargs):
        seen["options"] = options
        raise RuntimeError("captured")
    monkeypatch.setattr(auto, "fit_without_truth", capture)
    scene = load_observation_scene(_mock_arc_with_flagged_pixels(tmp_path)[0])
    obs, frame = run.read_scene_data(scene)
    with pytest.raises(RuntimeError, match="captured"):
        run.auto_starts(obs, frame, scene)
    opts = seen["options"]
    assert opts.rtol == run.AUTO_RTOL > auto.AutoOptions().rtol
    assert not opts.errors and not opts.merge
    # no clump found: no starts, and the counting's steps still come back (summary.json's
    # "counting")
    import types
    steps = [dict(step=0, action="host"), dict(step=1, action="stop")]
    monkeypatch.setattr(auto, "fit_without_truth", lambda *a, **k: types.SimpleNamespace(
        state=types.SimpleNamespace(source=types.SimpleNamespace(clumps=None)), steps=steps))
    assert run.auto_starts(obs, frame, scene) == (None, steps)


def check_mock_fit(out, knots):
    from astropy.table import Table
    summary = json.loads((out / "summary.json").read_text())
    # the counting's steps: the host first, then clumps added, and the final refit
    actions = [st["action"] for st in summary["counting"]]
    assert actions[0] == "host" and "add" in actions and actions[-1] == "final", actions
    assert summary["bands"]["F150W"]["n_pixels_masked"] == 80
    assert 0.85 < summary["chi2_per_dof"]["F150W"] < 1.2, summary["chi2_per_dof"]
    t = Table.read(out / "fit.ecsv")
    xy = np.c_[t["x_pix"], t["y_pix"]]
    centres = np.vstack([xy, [[summary["host"]["x_pix"], summary["host"]["y_pix"]]]])
    for k in knots:
        assert np.min(np.hypot(*(centres - np.asarray(k)).T)) < 1.0, (k, centres)
    chi = fits.getdata(out / "residuals_F150W.fits", "CHI")
    yy, xx = np.indices(chi.shape)
    near = np.zeros(chi.shape, bool)
    for cx, cy in xy:
        near |= np.hypot(xx - cx, yy - cy) <= 2
    assert np.nanmax(np.abs(chi[near])) < 5
    assert np.all(np.isnan(chi[:, 36:38]))
