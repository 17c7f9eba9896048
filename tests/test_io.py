"""io: atomic writes, the θ-frame TAN WCS, band FITS files, catalogues, JSON, RGB PNGs."""

import json
import math
import os

import numpy as np
import pytest
from astropy.io import fits
from astropy.table import Table
from astropy.wcs import WCS

from clumpylen_jax import io

RA0, DEC0 = 64.038142, -24.067472  # MACS J0416 (the paper's lens centre)


def test_atomic_write_leaves_nothing_on_error(tmp_path):
    target = tmp_path / "sub" / "out.txt"
    with pytest.raises(RuntimeError):
        with io.atomic_write(target, "w") as fh:
            fh.write("half")
            raise RuntimeError("boom")
    assert not target.exists()
    assert os.listdir(tmp_path / "sub") == []  # no temporary file left behind


def test_atomic_write_keeps_old_file_on_error_and_replaces_on_success(tmp_path):
    target = tmp_path / "out.txt"
    target.write_text("old")
    with pytest.raises(ValueError):
        with io.atomic_write(target) as tmp:
            with open(tmp, "w") as fh:
                fh.write("new")
            raise ValueError
    assert target.read_text() == "old"
    with io.atomic_write(target, "w") as fh:
        fh.write("new")
    assert target.read_text() == "new"
    umask = os.umask(0)
    os.umask(umask)
    assert target.stat().st_mode & 0o777 == 0o666 & ~umask  # not mkstemp's private 0600


def test_theta_convention_round_trip():
    # +θ1 is West: RA decreases; +θ2 is North: Dec increases.
    ra, dec = io.theta_to_radec(10.0, 0.0, (RA0, DEC0))
    assert ra < RA0
    assert -(ra - RA0) * math.cos(math.radians(DEC0)) * 3600 == pytest.approx(10.0, abs=1e-6)
    ra, dec = io.theta_to_radec(0.0, 5.0, (RA0, DEC0))
    assert (dec - DEC0) * 3600 == pytest.approx(5.0, abs=1e-9) and ra == pytest.approx(RA0)
    t1, t2 = io.radec_to_theta(*io.theta_to_radec(-35.57, 18.85, (RA0, DEC0)), (RA0, DEC0))
    assert (float(t1), float(t2)) == pytest.approx((-35.57, 18.85), abs=1e-9)


def test_make_wcs_pixel_centres_in_theta():
    pix = 0.031
    w = io.make_wcs((RA0, DEC0), pix, (100, 120), (-38.0, 16.5))
    assert w.has_celestial and w.wcs.crval[0] == RA0
    assert w.wcs.cdelt[0] == pytest.approx(-pix / 3600) and w.wcs.cdelt[1] == pytest.approx(pix / 3600)
    for x, y in [(0, 0), (119, 99), (40, 7)]:
        ra, dec = w.pixel_to_world_values(x, y)
        t1, t2 = io.radec_to_theta(ra, dec, (RA0, DEC0))
        assert (float(t1), float(t2)) == pytest.approx((-38.0 + x * pix, 16.5 + y * pix), abs=1e-8)
        # and the linear θ formula of DESIGN.md agrees to a few mas this far out
        lin1 = -(ra - RA0) * math.cos(math.radians(DEC0)) * 3600
        lin2 = (dec - DEC0) * 3600
        assert abs(lin1 - (-38.0 + x * pix)) < 5e-3 and abs(lin2 - (16.5 + y * pix)) < 5e-3
    # a pixel to the West (larger x) has a smaller RA
    assert w.pixel_to_world_values(10, 0)[0] < w.pixel_to_world_values(0, 0)[0]


def test_band_fits_read_back(tmp_path):
    shape = (20, 30)
    w = io.make_wcs((RA0, DEC0), 0.063, shape, (-36.0, 17.0))
    wu = io.make_wcs((RA0, DEC0), 0.063, (10, 10), (-14.0, 3.3))
    img = np.arange(600, dtype=np.float64).reshape(shape)
    header = {"TELESCOP": "JWST", "INSTRUME": "NIRCAM", "FILTER": "F277W", "EXPTIME": 2920.4,
              "ZP_AB": (28.0, "AB mag for 1 count/s"), "PIXSCALE": 0.063, "SKYLEVEL": np.float32(0.0948),
              "SEED": np.int64(7)}
    path = tmp_path / "bands" / "F277W.fits"
    io.write_band_fits(path, img, noiseless=img * 0.5, variance=img + 1, unlensed=np.ones((10, 10)),
                       header=header, wcs=w, unlensed_wcs=wu)
    with fits.open(path) as hdul:
        assert [h.name for h in hdul] == ["PRIMARY", "NOISELESS", "VARIANCE", "UNLENSED"]
        h = hdul[0].header
        assert hdul[0].data.dtype == np.dtype(">f4") and np.array_equal(hdul[0].data, img.astype(np.float32))
        assert h["BUNIT"] == "counts/s" and h["FILTER"] == "F277W" and h["SEED"] == 7
        assert h["ZP_AB"] == 28.0 and h["EXPTIME"] == 2920.4
        wr = WCS(h)
        assert wr.has_celestial
        assert np.allclose(wr.pixel_to_world_values(3, 4), w.pixel_to_world_values(3, 4), atol=1e-12)
        assert np.allclose(hdul["NOISELESS"].data, img * 0.5)
        wu_r = WCS(hdul["UNLENSED"].header)
        assert np.allclose(wu_r.pixel_to_world_values(0, 0), wu.pixel_to_world_values(0, 0), atol=1e-12)
    assert [p.name for p in path.parent.iterdir()] == ["F277W.fits"]


def test_fits_image_catalog_json(tmp_path):
    io.write_fits_image(tmp_path / "a.fits", np.zeros((4, 5)), header={"OBJECT": "hr"})
    assert fits.getheader(tmp_path / "a.fits")["OBJECT"] == "hr"
    io.write_catalog(tmp_path / "c.ecsv", {"id": np.arange(3), "mass_msun": np.array([1e4, 2e4, 3e5])})
    t = Table.read(tmp_path / "c.ecsv")
    assert list(t.colnames) == ["id", "mass_msun"] and t["mass_msun"][2] == 3e5
    obj = {"a": np.float32(1.5), "b": np.arange(3), "c": (np.bool_(True), None), "d": float("nan"),
           "e": tmp_path, 3: np.int64(4)}
    io.write_json(tmp_path / "s.json", obj)
    back = json.loads((tmp_path / "s.json").read_text())
    assert back == {"a": 1.5, "b": [0, 1, 2], "c": [True, None], "d": None, "e": str(tmp_path), "3": 4}
