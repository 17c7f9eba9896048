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
    for key in ("scene", "seed", "version", "band_total_counts", "timings_s", "stages"):
        assert key in summary
    assert summary["scene"]["scene"]["name"] == "single-sersic"
