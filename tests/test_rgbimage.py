"""Colour composites people look at: colour kept where the light is bright, figures large and decorated."""

from __future__ import annotations

import numpy as np
import pytest
from astropy.wcs import WCS

from clumpylen_jax import rgbimage as ri
from clumpylen_jax.pixels import Grid

PNG = b"\x89PNG\r\n\x1a\n"


def _scene_images(n=80):
    """A red exponential host with a blue clump off-centre (flux per pixel in r, g, b)."""
    y, x = np.mgrid[0:n, 0:n] - n / 2 + 0.5
    r = np.hypot(x, y)
    host = np.exp(-r / 6.0)
    clump = 40.0 * np.exp(-((x - 12) ** 2 + (y - 5) ** 2) / 2.0)
    sed_host, sed_clump = (1.0, 0.6, 0.3), (0.3, 0.6, 1.0)
    return [h * host + c * clump for h, c in zip(sed_host, sed_clump)], (n // 2 + 5, n // 2 + 12)


def test_colours_differ_where_the_light_is_bright():
    chans, (cy, cx) = _scene_images()
    rgb = ri.rgb_array(*chans)
    n = rgb.shape[0]
    assert rgb.shape == (n, n, 3) and rgb.min() >= 0 and rgb.max() <= 1
    centre, clump = rgb[n // 2, n // 2], rgb[cy, cx]
    # The host centre is redder than the clump, the clump bluer than the host: colour survives at the
    # brightest pixels (the old composite clipped every channel there to one flat colour).
    assert centre[0] / centre[2] > 1.5 * clump[0] / clump[2]
    assert clump[2] > clump[0]
    # The host keeps its gradient: brightness falls from the centre outwards, not a saturated plateau.
    ring = [rgb[n // 2, n // 2 + k].sum() for k in (0, 4, 8, 16)]
    assert all(a > b for a, b in zip(ring, ring[1:]))


def test_noise_reference_keeps_sky_dark():
    chans, _ = _scene_images()
    rng = np.random.default_rng(1)
    noisy = [c + 0.05 * rng.normal(size=c.shape) for c in chans]
    rgb = ri.rgb_array(*noisy, reference=chans)
    corner = rgb[:10, :10].mean()
    assert corner < 0.1 * rgb[40, 40].mean()  # empty sky stays dark, the host stays bright


def test_extents_and_scale_bar():
    g = Grid(-1.0, 2.0, 0.5, 4, 3)
    assert ri.extent_of_grid(g) == (-1.25, 0.75, 1.75, 3.25)
    assert ri.nice_length(5.0) == 1.0 and ri.nice_length(0.9) == 0.1 and ri.nice_length(30) == 5.0


def test_compass_follows_the_wcs():
    def wcs(rot_deg):
        w = WCS(naxis=2)
        w.wcs.ctype = ["RA---TAN", "DEC--TAN"]
        w.wcs.crval = [64.0, -24.0]
        w.wcs.crpix = [50, 50]
        t = np.deg2rad(rot_deg)
        d = 0.05 / 3600
        w.wcs.cd = [[-d * np.cos(t), d * np.sin(t)], [d * np.sin(t), d * np.cos(t)]]
        w.pixel_shape = (100, 100)
        return w

    north, east = ri.compass_directions(wcs(0.0))
    np.testing.assert_allclose(north, [0, 1], atol=1e-4)
    np.testing.assert_allclose(east, [-1, 0], atol=1e-4)  # east left
    north, east = ri.compass_directions(wcs(30.0))
    assert abs(np.degrees(np.arctan2(north[0], north[1]))) == pytest.approx(30.0, abs=0.01)
    assert abs(np.dot(north, east)) < 1e-4  # still perpendicular
    assert north[0] * east[1] - north[1] * east[0] > 0  # E is 90° counter-clockwise from N: not mirrored


def test_crop_to_light_zooms_on_the_source():
    img = np.zeros((200, 200))
    img[90:110, 120:130] = 1.0
    (sy, sx), ext = ri.crop_to_light([img], (0.0, 200.0, 0.0, 200.0))
    assert sy.start <= 90 and sy.stop >= 110 and sx.start <= 120 and sx.stop >= 130
    assert sy.stop - sy.start < 60 and ext[0] == sx.start


def test_composite_png_is_large_and_written_atomically(tmp_path):
    chans, _ = _scene_images(n=40)
    path = ri.save_composite(tmp_path / "rgb.png", chans, (-1.0, 1.0, -1.0, 1.0), title="t",
                             circles=[(0.3, 0.1, 0.1, "r")])
    assert path.read_bytes()[:8] == PNG
    import matplotlib.image as mpimg

    h, w = mpimg.imread(path).shape[:2]
    assert w >= 600 and h >= 600  # a 40-pixel image drawn at least 600 px across, blocks not smoothed
    assert [p.name for p in tmp_path.iterdir()] == ["rgb.png"]  # no temporary file left


def test_paper_figure_from_a_run_with_hr_images(tmp_path):
    """plot_paper_rgb on a synthetic run: HR lensed panel + the detector composite; the brightest lensed
    clump away from the host's centre is the one circled."""
    import json

    import matplotlib.image as mpimg
    from _fake_run import make_fake_run

    from clumpylen_jax import io, paperfig
    from clumpylen_jax.analysis import _read_catalog, band_data

    run = make_fake_run(tmp_path / "run")
    summary = json.loads((run / "summary.json").read_text())
    summary["scene"]["output"]["rgb"] = [["F200W", "F150W", "F150W"]]
    summary["scene"]["output"]["hr_rgb_um"] = [5.0, 3.0, 2.0]
    summary["hr"] = {"names": ["5um", "3um", "2um"]}
    wcs = io.make_wcs((64.0, -24.0), 0.01, (300, 300), (-1.495, -1.495))
    y, x = (np.mgrid[0:300, 0:300] - 149.5) * 0.01
    for k, name in enumerate(summary["hr"]["names"]):
        io.write_fits_image(run / "hr" / f"lensed_{name}.fits", np.exp(-np.hypot(x, y) / (0.2 + 0.1 * k)), wcs=wcs)
    bands = {b["filter"]: b for b in (band_data(p) for p in (run / "bands").glob("*.fits"))}
    catalog = _read_catalog(run)
    # unlensed fake run: clump 0 (mag 27.2) at β = (0.4, 0.3) is the brightest
    assert paperfig._clump_of_interest(catalog, None, summary["field_arcsec"], "F200W") == pytest.approx((0.4, 0.3))
    assert paperfig._clump_of_interest(catalog, None, summary["field_arcsec"], "F200W",
                                       avoid=(0.4, 0.3, 0.1)) == pytest.approx((-0.5, -0.4))
    path = paperfig.plot_paper_rgb(run, tmp_path / "paper.png", summary=summary, bands=bands, catalog=catalog)
    h, w = mpimg.imread(path).shape[:2]
    assert w >= 1200 and h >= 600  # two panels side by side, each over 600 px


def test_lupton_stretch_is_astropys_bit_for_bit():
    """`_lupton_rgb` (a few in-place passes) gives astropy's make_lupton_rgb array exactly:
    NaN, zero and negative pixels, intensities ≤ 0, saturated pixels and tiny Q included."""
    from astropy.visualization import make_lupton_rgb

    rng = np.random.default_rng(5)
    chans = [rng.normal(0.2, 1.0, (64, 48)) ** 3 for _ in range(3)]
    chans[0][0, 0] = np.nan
    chans[1][3, 4] = -0.0
    for c in chans:
        c[10:12] = 0.0
    for stretch, Q in [(0.3, 7.0), (1e-3, 2.5), (5.0, 1e-9), (2.0, 8.0)]:
        with np.errstate(invalid="ignore", divide="ignore"):
            want = make_lupton_rgb(*chans, minimum=[0.0, 0.0, 0.0], stretch=stretch, Q=Q,
                                   output_dtype=np.float64)
        got = ri._lupton_rgb(chans, stretch, Q)
        assert got.shape == want.shape
        assert np.array_equal(got, want, equal_nan=True)
        assert np.array_equal(np.signbit(got), np.signbit(want))


def test_large_frames_are_coloured_on_block_means_with_the_full_frames_stretch(monkeypatch, tmp_path):
    """A frame f ≥ 2 times wider than drawn: block means shown, balance and stretch from its
    every f-th pixel (so a clump's light does not set the top of the stretch f² times
    over); shown=images is the plain call bit for bit."""
    rng = np.random.default_rng(4)
    yy, xx = np.mgrid[:1900, :1900]
    host = np.exp(-np.hypot(xx - 950, yy - 950) / 200.0)
    clumps = np.zeros_like(host)
    clumps[rng.integers(0, 1900, 3600), rng.integers(0, 1900, 3600)] = 1e3   # 0.1 % of pixels
    chans = [host + clumps, 0.8 * host + 2 * clumps, 0.5 * host + 4 * clumps]
    assert np.array_equal(ri.rgb_array(*chans[:3], shown=chans), ri.rgb_array(*chans))

    means, extent = ri._block_means(chans, (0.0, 19.0, -1.0, 18.0), 3)
    assert means[0].shape == (633, 633) and np.allclose(extent, (0.0, 18.99, -1.0, 17.99))
    assert np.isclose(means[1][10, 20], chans[1][30:33, 60:63].mean())

    seen = {}
    monkeypatch.setattr(ri, "save_sky_figure", lambda path, rgb, extent, **kw: seen.update(
        rgb=rgb, extent=extent))
    ri.save_composite(tmp_path / "x.png", chans, (0.0, 19.0, -1.0, 18.0))
    assert seen["rgb"].shape == (633, 633, 3) and np.allclose(seen["extent"], extent)
    # the host, away from clumps, as bright as in the full frame's colouring
    full = ri.rgb_array(*chans)
    assert np.allclose(seen["rgb"][300, 100], full[901, 301], rtol=0.05)
    block_stretch = ri.rgb_array(*means)
    assert block_stretch[300, 100].sum() < 0.7 * seen["rgb"][300, 100].sum()
