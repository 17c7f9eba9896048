"""Deflection maps from FITS: placement in the θ frame, scaling, errors, real HFF maps."""

import os
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from astropy.io import fits

from clumpylen_jax.errors import ConfigError
from clumpylen_jax.lensing import SIE, DeflectionGrid, find_images, grid_lensing_quantities, trace
from clumpylen_jax.lensing._distances import dls_ds
from clumpylen_jax.lensing.fits import check_finite, load_deflection_maps

RA0, DEC0 = 64.038142, -24.067472  # the paper's MACS J0416 lens centre


def _shared_data():
    env = os.environ.get("CLUMPYLEN_SHARED_DATA")
    return Path(env) if env else Path(__file__).resolve().parents[2] / "shared" / "data"


def _hff(cluster):
    d = _shared_data() / "lens" / "hff_williams_v4" / cluster
    x = d / f"hlsp_frontier_model_{cluster}_williams_v4_x-arcsec-deflect.fits"
    if not x.is_file():
        pytest.skip(f"HFF Williams v4 maps for {cluster} not found under {d}")
    return d, x, d / f"hlsp_frontier_model_{cluster}_williams_v4_y-arcsec-deflect.fits"


def _header(n, pix_arcsec, crval, cd1=None, cd12=0.0):
    h = fits.Header()
    h["CTYPE1"], h["CTYPE2"] = "RA---TAN", "DEC--TAN"
    h["CRPIX1"] = h["CRPIX2"] = (n + 1) / 2
    h["CRVAL1"], h["CRVAL2"] = crval
    h["CD1_1"] = -pix_arcsec / 3600 if cd1 is None else cd1
    h["CD2_2"] = pix_arcsec / 3600
    h["CD1_2"] = cd12
    h["CD2_1"] = -cd12
    return h


LENS = SIE(6.0, 0.7, 0.5, jnp.array([3.0, -2.0]))


def _write_synthetic(tmp_path, *, n=101, pix=0.5, crval=(RA0 + 0.004, DEC0 - 0.005), east_right=False,
                     nan_at=None, cd12=0.0, suffix=""):
    """x/y maps of LENS on a TAN grid whose tangent point is offset from the lens centre."""
    from astropy.wcs import WCS

    cd1 = pix / 3600 if east_right else None
    h = _header(n, pix, crval, cd1=cd1, cd12=cd12)
    jj, ii = np.mgrid[0:n, 0:n]
    ra, dec = WCS(h).all_pix2world(ii, jj, 0)
    t1 = -(ra - RA0) * np.cos(np.deg2rad(DEC0)) * 3600  # DESIGN.md's θ, independent of fits.py
    t2 = (dec - DEC0) * 3600
    a1, a2 = (np.asarray(a) for a in LENS.deflection(jnp.asarray(t1), jnp.asarray(t2)))
    ax = -a1 if east_right else a1  # component along +x pixel
    if nan_at is not None:
        ax = ax.copy()
        ax[nan_at] = np.nan
    px, py = tmp_path / f"x{suffix}.fits", tmp_path / f"y{suffix}.fits"
    fits.PrimaryHDU(ax.astype(">f4"), h).writeto(px, overwrite=True)
    fits.PrimaryHDU(a2.astype(">f4"), h).writeto(py, overwrite=True)
    return px, py


def _load(px, py, **kw):
    kw.setdefault("z_lens", 0.396)
    kw.setdefault("z_source", 6.145)
    return load_deflection_maps(px, py, lens_center_radec_deg=(RA0, DEC0), **kw)


@pytest.mark.parametrize("east_right", [False, True])
def test_synthetic_map_is_placed_in_theta_frame(tmp_path, east_right):
    px, py = _write_synthetic(tmp_path, east_right=east_right)
    grid = _load(px, py, normalization={"z_source": 6.145})
    assert grid.scale == pytest.approx(1.0)
    assert grid.alpha1_arcsec.dtype == jnp.float64 and grid.alpha1_arcsec.dtype.isnative
    # the map spans θ1 ∈ [−38, 12]″, θ2 ∈ [−43, 7]″ (tangent point offset from the lens centre)
    assert bool(jnp.all(grid.contains(jnp.array([-37.0, 11.0]), jnp.array([-42.0, 6.0]))))
    assert not bool(grid.contains(jnp.array(13.0), jnp.array(0.0)))
    t1 = jnp.array([-10.0, 0.5, -25.0, 8.0, -30.0])
    t2 = jnp.array([-7.0, -30.0, -20.0, 3.0, 5.0])
    got = np.asarray(grid.deflection(t1, t2))
    want = np.asarray(LENS.deflection(t1, t2))
    np.testing.assert_allclose(got, want, atol=0.01)  # bilinear on 0.5″ pixels of a smooth field


def test_redshift_scaling(tmp_path):
    px, py = _write_synthetic(tmp_path)
    g = _load(px, py)
    assert g.scale == pytest.approx(dls_ds(0.396, 6.145))
    g2 = _load(px, py, normalization={"z_source": 2.0})
    assert g2.scale == pytest.approx(dls_ds(0.396, 6.145) / dls_ds(0.396, 2.0))
    assert 0.8 < g.scale < 0.83  # astropy flat ΛCDM, H0 = 70, Ωm = 0.3
    with pytest.raises(ConfigError):
        _load(px, py, normalization="per_pixel")


def test_errors(tmp_path):
    px, py = _write_synthetic(tmp_path)
    qx, qy = _write_synthetic(tmp_path, n=99, suffix="small")
    with pytest.raises(ConfigError, match="shape"):
        _load(px, qy)
    rx, ry = _write_synthetic(tmp_path, crval=(RA0, DEC0), suffix="moved")
    with pytest.raises(ConfigError, match="WCS"):
        _load(px, ry)
    tx, ty = _write_synthetic(tmp_path, cd12=0.5 / 3600 * 0.1, suffix="rot")
    with pytest.raises(ConfigError, match="rotated"):
        _load(tx, ty)
    nx_ = tmp_path / "nowcs.fits"
    fits.PrimaryHDU(np.zeros((10, 10), ">f4")).writeto(nx_)
    with pytest.raises(ConfigError, match="celestial"):
        _load(nx_, nx_)
    with pytest.raises(ConfigError, match="existing"):
        _load(tmp_path / "missing.fits", py)


def test_nan_only_matters_where_traced(tmp_path):
    px, py = _write_synthetic(tmp_path, nan_at=(3, 4), suffix="nan")
    grid = _load(px, py)
    check_finite(grid, (-10.0, 10.0), (-10.0, 10.0))  # far from the bad pixel: fine
    o1, o2 = (float(v) for v in grid.origin_arcsec)
    with pytest.raises(ConfigError, match=r"pixel \[y=3, x=4\]"):
        check_finite(grid, (o1, o1 + 5), (o2, o2 + 5))


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_rays_outside_map_are_finite(dtype):
    a = jnp.asarray(np.random.default_rng(0).normal(size=(2, 8, 9)), dtype)
    grid = DeflectionGrid(a[0], a[1], jnp.asarray([-4.0, -3.5], dtype), 1.0, 0.9)
    for theta in ([100.0, -200.0], [-4.0, -3.5], [0.0, 0.0], [4.0, 0.5], [1e30, -1e30]):
        th = jnp.asarray(theta, dtype)
        f = lambda t: jnp.sum(jnp.stack(trace(grid, t[0], t[1])))  # noqa: E731
        v, g = jax.value_and_grad(f)(th)
        assert np.isfinite(v) and np.all(np.isfinite(g)) and v.dtype == dtype


def test_abell2744_kappa_is_half_divergence():
    d, x, y = _hff("abell2744")
    grid = load_deflection_maps(x, y, lens_center_radec_deg=(3.586257, -30.400172), z_lens=0.308,
                                z_source=3.98)
    grid = DeflectionGrid(grid.alpha1_arcsec, grid.alpha2_arcsec, grid.origin_arcsec, grid.pixel_arcsec, 1.0)
    _, _, m = grid_lensing_quantities(grid)
    k = fits.getdata(d / "hlsp_frontier_model_abell2744_williams_v4_kappa.fits").astype(np.float64)
    k_cells = 0.25 * (k[1:, 1:] + k[:-1, 1:] + k[1:, :-1] + k[:-1, :-1])
    sel = k_cells > 0.2
    ratio = np.asarray(m.kappa)[sel] / k_cells[sel]
    assert np.median(ratio) == pytest.approx(1.0, abs=1e-3)
    assert np.percentile(np.abs(ratio - 1), 90) < 1e-3


PAPER_IMAGES = np.array([(-35.57, 18.85), (-42.66, 8.46), (-20.16, 31.53)])
PAPER_BETA = (-13.72, 3.62)


def test_macs0416_paper_images_trace_to_one_source_and_are_found():
    _, x, y = _hff("macs0416")
    grid = load_deflection_maps(x, y, lens_center_radec_deg=(RA0, DEC0), z_lens=0.396, z_source=6.145)
    b1, b2 = trace(grid, jnp.asarray(PAPER_IMAGES[:, 0]), jnp.asarray(PAPER_IMAGES[:, 1]))
    beta = np.stack([b1, b2], 1)
    # The Williams (GRALE) model is not the paper's Lenstool model: the three images
    # trace back to within ~0.7″ of each other and of the paper's β.
    assert np.max(np.hypot(*(beta - beta.mean(0)).T)) < 0.8
    assert np.hypot(*(beta.mean(0) - PAPER_BETA)) < 0.8
    im = find_images(grid, float(beta[:, 0].mean()), float(beta[:, 1].mean()),
                     field=((-60.0, 10.0), (-20.0, 50.0)), pixel_arcsec=0.25, max_images=6)
    th = np.stack([im.theta1, im.theta2], 1)[np.asarray(im.valid)]
    assert len(th) == 3
    for p in PAPER_IMAGES:  # each paper image has a found image within a few arcsec
        assert np.min(np.hypot(*(th - p).T)) < 3.0
    assert np.all(np.isfinite(im.magnification))
