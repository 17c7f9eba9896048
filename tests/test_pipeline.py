"""`simulate` end to end on the smallest built-in scene: outputs, headers, determinism."""

import json

import numpy as np
import pytest
from astropy.io import fits
from astropy.wcs import WCS

from clumpylen_jax import pipeline


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    a = tmp_path_factory.mktemp("a")
    b = tmp_path_factory.mktemp("b")
    c = tmp_path_factory.mktemp("c")
    pipeline.simulate("single-sersic", a, progress=False)
    pipeline.simulate("single-sersic", b, progress=False)
    pipeline.simulate("single-sersic", c, seed=99, progress=False)
    return a, b, c


def test_same_seed_gives_identical_files_and_another_seed_other_noise(runs):
    a, b, c = runs
    with fits.open(a / "bands" / "F200W.fits") as fa, fits.open(b / "bands" / "F200W.fits") as fb, \
            fits.open(c / "bands" / "F200W.fits") as fc:
        for name in ("PRIMARY", "NOISELESS", "VARIANCE"):
            assert np.array_equal(fa[name].data, fb[name].data)
        assert np.array_equal(fa["NOISELESS"].data, fc["NOISELESS"].data)
        assert not np.array_equal(fa[0].data, fc[0].data)
        assert fc[0].header["SEED"] == 99


def test_band_file_contract(runs):
    a, _, _ = runs
    with fits.open(a / "bands" / "F200W.fits") as f:
        h = f[0].header
        for key in ("BUNIT", "TELESCOP", "INSTRUME", "FILTER", "EXPTIME", "ZP_AB", "PIXSCALE",
                    "SKYLEVEL", "SEED"):
            assert key in h, key
        assert h["FILTER"] == "F200W" and h["TELESCOP"] == "JWST"
        assert WCS(h).has_celestial
        data, clean, var = f[0].data, f["NOISELESS"].data, f["VARIANCE"].data
        assert data.dtype.kind == "f" and data.dtype.itemsize == 4
        assert np.all(np.isfinite(data)) and np.all(var > 0)
        # the noiseless image holds the sky plus the source of F200W = 24 AB
        source = clean.sum() - h["SKYLEVEL"] * clean.size
        expected = 10 ** (-0.4 * (24.0 - h["ZP_AB"]))
        assert abs(source / expected - 1) < 0.02   # the 3" field holds ~all of an n = 2, 0.2" profile
        # photon noise: (image − noiseless)/σ is standard normal
        pulls = (data - clean) / np.sqrt(var)
        assert abs(pulls.std() - 1) < 0.05
    summary = json.loads((a / "summary.json").read_text())
    for key in ("scene", "seed", "version", "band_total_counts", "timings_s", "stages",
                "timings_split_s"):
        assert key in summary
    for stage, t in summary["timings_split_s"].items():    # compile + run = the stage's time
        assert 0 <= t["compile"] <= t["total"] and abs(t["compile"] + t["run"] - t["total"]) < 2e-3
    assert summary["timings_split_s"]["render (compile + run)"]["compile"] > 0
    assert summary["scene"]["scene"]["name"] == "single-sersic"


THIN_DISK = """
[scene]
name = "thin-disk"
seed = 3
z_source = 1.5

[source]
center_arcsec = [0.0, 0.0]

[source.disk]
magnitudes = { F200W = 22.0 }
re_arcsec = 0.05
n = 0.5
q = 1.0
pa_rad = 0.0
inclination_rad = 1.52

[render]
field_arcsec = { x = [-0.6, 0.6], y = [-0.6, 0.6] }

[[bands]]
instrument = "JWST/NIRCam"
filter = "F200W"
exptime_s = 1000.0
sky_counts_per_s = 0.16
psf = "none"

[output]
noise = false
unlensed = false
"""


def _midpoint_sersic(theta1, theta2, pixel, *, re, n, q, pa, sub=64):
    """Independent reference: unit-flux Sérsic (exact b(n)) averaged over sub × sub midpoints
    of each pixel centred at (theta1, theta2) (arcsec), times the pixel area."""
    from scipy.special import gamma, gammaincinv
    b = gammaincinv(2 * n, 0.5)
    norm = 2 * np.pi * q * re**2 * n * np.exp(b) * b ** (-2 * n) * gamma(2 * n)
    o = (np.arange(sub) + 0.5) / sub - 0.5
    out = np.zeros(theta1.shape)
    for oy in o:
        x = theta1[..., None] + o * pixel
        y = (theta2 + oy * pixel)[..., None]
        u = x * np.cos(pa) + y * np.sin(pa)
        v = -x * np.sin(pa) + y * np.cos(pa)
        r = np.hypot(u, v / q)
        out += np.exp(-b * ((r / re) ** (1 / n) - 1)).sum(-1)
    return out / sub**2 * pixel**2 / norm


def test_thin_edge_on_disk_through_simulate_matches_an_independent_renderer(tmp_path):
    """An edge-on disk (projected minor-axis R_e 0.08 pixel, along a pixel row), unlensed, no
    PSF or noise, through `simulate`: pixel by pixel against midpoint sampling in numpy (a
    reference for n ≤ 2 only: at n = 4 the cusp needs far more samples), placed by the FITS
    WCS. Sampled pixels missed 4.9 % of this disk's light (8.9 % of the peak in a pixel)
    before thin profiles had their major-axis pixels integrated exactly."""
    path = tmp_path / "thin.toml"
    path.write_text(THIN_DISK)
    pipeline.simulate(path, tmp_path / "out", progress=False)
    with fits.open(tmp_path / "out" / "bands" / "F200W.fits") as f:
        h = f[0].header
        img = f["NOISELESS"].data.astype(float) - h["SKYLEVEL"]
        wcs = WCS(h)
    y, x = np.mgrid[:img.shape[0], :img.shape[1]]
    ra, dec = wcs.pixel_to_world_values(x, y)
    ra0, dec0 = wcs.wcs.crval
    theta1 = -((ra - ra0 + 180.0) % 360.0 - 180.0) * np.cos(np.radians(dec0)) * 3600.0
    theta2 = (dec - dec0) * 3600.0
    ref = _midpoint_sersic(theta1, theta2, h["PIXSCALE"], re=0.05, n=0.5, q=np.cos(1.52), pa=0.0)
    ref *= 10 ** (-0.4 * (22.0 - h["ZP_AB"]))
    assert img.sum() == pytest.approx(ref.sum(), rel=1e-3)
    assert np.max(np.abs(img - ref)) <= 3e-3 * ref.max()


def test_no_high_resolution_output_costs_nothing(tmp_path, monkeypatch):
    """output.hr = false: no high-resolution photometry, program or thread work at all."""
    import dataclasses

    from clumpylen_jax import scene as sc

    def refuse(*a, **k):
        raise AssertionError("high-resolution work for a scene that drops it")

    for name in ("_hr_source", "_launch_hr", "_write_hr_lensed", "_write_hr_unlensed",
                 "_monochromatic_source", "_source_plane_images", "_source_plane_host_light"):
        monkeypatch.setattr(pipeline, name, refuse)
    s = sc.load_scene("single-sersic")
    s = dataclasses.replace(s, output=dataclasses.replace(s.output, hr=False))
    summary = pipeline.simulate(s, tmp_path / "run", progress=False)
    assert not (tmp_path / "run" / "hr").exists() and summary["hr"] is None
    assert not any("high-resolution" in stage for stage in summary["timings_split_s"])


def test_programs_without_lens_are_launched_before_the_lens_is_traced(tmp_path, monkeypatch):
    """The unlensed and high-resolution source-plane programs need no lens: `simulate`
    launches them (`_launch_early`) from `prepare` before it builds the lens and traces it,
    so that a first run compiles them while the rays are traced."""
    order = []
    for name, tag in (("_launch_early", "launch"), ("build_lens", "lens")):
        fun = getattr(pipeline, name)

        def recorded(*a, _fun=fun, _tag=tag, **k):
            order.append(_tag)
            return _fun(*a, **k)

        monkeypatch.setattr(pipeline, name, recorded)
    pipeline.simulate("single-sersic", tmp_path / "run", progress=False)
    assert order == ["launch", "lens"]


def test_noise_program_draws_what_observe_draws():
    """The photon noise is drawn by a program of its own (`_noise_program`, compiled beside
    the band render) from the band render's noiseless images: the same images, to the bit,
    as `SceneModel.observe` draws in one program."""
    import equinox as eqx
    import jax

    from clumpylen_jax import scene as sc

    prep = pipeline.prepare(sc.load_scene("single-sersic"))
    key = jax.random.key(prep.scene.seed)
    noisy, clean, _ = eqx.filter_jit(lambda m, s, k: m.observe(s, k))(prep.model, prep.source, key)
    drawn = pipeline._noise_program(prep, pipeline._Progress(False, 1))(key, clean)
    assert len(drawn) == len(noisy)
    for a, b in zip(noisy, drawn):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_unlensed_programs_make_the_high_resolution_source_plane():
    """With unlensed and high-resolution outputs both asked for, the unlensed bands'
    programs also make the high-resolution source plane (host light and clump stamps on
    one more grid: two programs fewer): the images of the source plane's own programs."""
    import dataclasses

    import jax.numpy as jnp

    from clumpylen_jax import scene as sc
    from clumpylen_jax.model.clumps import UnlensedClumps
    from clumpylen_jax.source import Clumps, Source

    prep = pipeline.prepare(sc.load_scene("single-sersic"))
    # the bulge with three clumps (two stamp sizes) around it
    nb = prep.source.bulge.flux.shape[0]
    clumps = Clumps(jnp.asarray([[0.05, -0.02], [-0.1, 0.07], [0.0, 0.12]]),
                    jnp.full((3, nb), 0.3) * jnp.asarray([[1.0], [2.0], [0.5]]),
                    jnp.asarray([0.01, 0.03, 0.005]), jnp.asarray([1.0, 1.5, 0.8]),
                    jnp.asarray([0.7, 0.9, 0.5]), jnp.asarray([0.3, 1.0, 2.0]))
    prep = dataclasses.replace(prep, source=Source(prep.source.bulge, None, clumps))
    mono = pipeline._hr_source(prep)[0]
    sgrid = pipeline._hr_grid(prep, mono)
    assert len(pipeline._hr_groups(prep, mono, sgrid)) >= 1
    unl, bands, plane = pipeline._launch_unlensed(prep, pipeline._Progress(False, 1),
                                                  (mono, sgrid))
    assert isinstance(unl.clumps, UnlensedClumps)       # the one-stamp-call path
    _, alone = pipeline._hr_source_plane(prep, mono, sgrid)
    _, bands_alone, none = pipeline._launch_unlensed(prep, pipeline._Progress(False, 1))
    assert none is None and plane.shape == alone.shape
    np.testing.assert_allclose(np.asarray(plane), np.asarray(alone), rtol=1e-12,
                               atol=1e-14 * float(np.max(np.abs(alone))))
    for a, b in zip(bands, bands_alone):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-12,
                                   atol=1e-14 * float(np.max(np.abs(b))))
