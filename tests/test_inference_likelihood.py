"""Likelihood gradients against central finite differences (float64), unlensed, lensed, photometric."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import clumpylen_jax
from clumpylen_jax.errors import ConfigError
from clumpylen_jax.inference import make_data, make_log_likelihood, make_state, parametrize
from clumpylen_jax.inference.mock import toy_bands, toy_model
from clumpylen_jax.source import Clumps, Source

FREE = {"clumps.flux": True, "clumps.center_arcsec": True, "clumps.re_arcsec": True,
        "clumps.q": [0], "clumps.pa_rad": [0], "background": True}


@pytest.fixture(scope="module")
def scene():
    src = Source(clumps=Clumps(jnp.array([[-0.3, 0.1], [0.25, -0.2], [0.05, 0.33]]),
                               jnp.array([[5.0], [3.0], [2.0]]), jnp.array([0.08, 0.06, 0.1]),
                               jnp.full(3, 0.5), jnp.array([0.8, 0.9, 0.7]), jnp.array([0.3, 1.0, -0.5])))
    model = toy_model(src, toy_bands(1))
    noisy, _, var = eqx.filter_jit(model.observe)(src, jax.random.key(0))
    return src, model, noisy, var


def _check_gradient(f, u, n_dirs=3, h=1e-6, rtol=1e-4):
    fj = jax.jit(f)
    g = np.asarray(jax.jit(jax.grad(f))(u))
    assert np.all(np.isfinite(g))
    rng = np.random.default_rng(0)
    dirs = [rng.standard_normal(u.size) for _ in range(n_dirs)]
    dirs += [np.eye(u.size)[i] for i in np.argsort(-np.abs(g))[:3]]
    for v in dirs:
        v = jnp.asarray(v)
        fd = (float(fj(u + h * v)) - float(fj(u - h * v))) / (2 * h)
        an = float(g @ np.asarray(v))
        assert abs(fd - an) <= rtol * max(abs(an), 1e-3 * np.linalg.norm(g)), (fd, an)


@pytest.mark.parametrize("kind", ["gaussian", "poisson", "gaussian_model_variance"])
def test_gradient_matches_finite_differences(scene, kind):
    src, model, noisy, var = scene
    data = make_data(model, {"B0": noisy[0]}, {"B0": var[0]} if kind == "gaussian" else None, kind=kind)
    param = parametrize(make_state(src, 1), FREE)
    u = param.initial() + 0.01  # off the truth: gradients are not ~0
    _check_gradient(make_log_likelihood(model, data, param), u)


@pytest.mark.slow  # 40-80 s: the thorough profile (pytest -m slow); keeps make test under 10 min
def test_lensed_sis_gradient(scene):
    from clumpylen_jax.lensing.analytic import SIS
    src = Source(clumps=Clumps(jnp.array([[0.05, 0.02], [0.0, -0.03]]), jnp.array([[3.0], [2.0]]),
                               jnp.array([0.02, 0.03]), jnp.full(2, 0.5), jnp.array([0.8, 1.0]),
                               jnp.array([0.3, 0.0])))
    model = toy_model(src, toy_bands(1, pixel_arcsec=0.06), npix=40,
                      lens=SIS(jnp.asarray(1.0), jnp.zeros(2)), lens_pixel_arcsec=0.015,
                      source_pixel_arcsec=0.004)
    # data need not be a realisation of the model for a gradient check: skip compiling observe
    shape = model.layouts[0].grid.shape
    data = make_data(model, np.full(shape, 0.05), np.full(shape, 1e-3))
    param = parametrize(make_state(src, 1), {"clumps.flux": True, "clumps.center_arcsec": True,
                                             "clumps.re_arcsec": True})
    _check_gradient(make_log_likelihood(model, data, param), param.initial() + 0.005, n_dirs=2)


def test_photometric_multiband_gradient_finite():
    from clumpylen_jax.inference.photometric import ClumpPhotometry
    src = Source(clumps=Clumps(jnp.array([[-0.15, 0.0], [0.15, 0.05]]), jnp.ones((2, 2)),
                               jnp.array([0.06, 0.08]), jnp.full(2, 0.5), jnp.ones(2), jnp.zeros(2)))
    phot = ClumpPhotometry(("F150W", "F200W"), (28.0, 28.0), 2.0)
    state = make_state(src, 2, mass_msun=[3e7, 1e7], age_myr=[10.0, 50.0], photometry=phot)
    flux = np.asarray(state.render_source().clumps.flux)
    assert flux.shape == (2, 2) and np.all(flux > 0)
    model = toy_model(state.render_source(), toy_bands(2), npix=21)
    shape = model.layouts[0].grid.shape
    data = make_data(model, {"B0": np.zeros(shape), "B1": np.zeros(shape)}, [np.ones(shape)] * 2)
    param = parametrize(state, {"mass_msun": True, "age_myr": True, "clumps.center_arcsec": True})
    f = make_log_likelihood(model, data, param)
    g = jax.jit(jax.grad(f))(param.initial())
    assert np.all(np.isfinite(np.asarray(g))) and np.any(np.asarray(g) != 0)
    with pytest.raises(ConfigError):
        parametrize(state, {"clumps.flux": True})


def test_make_data_checks(scene, tmp_path):
    from astropy.io import fits
    src, model, noisy, var = scene
    with pytest.raises(ConfigError):
        make_data(model, noisy, None, kind="gaussian")
    with pytest.raises(ConfigError):
        make_data(model, np.zeros((5, 5)), np.ones((5, 5)))
    path = tmp_path / "img.fits"
    fits.PrimaryHDU(np.asarray(noisy[0])).writeto(path)
    d = make_data(model, {"B0": str(path)}, {"B0": np.asarray(var[0])}, mask=np.ones((41, 41)))
    np.testing.assert_allclose(np.asarray(d.images[0]), np.asarray(noisy[0]), rtol=1e-6)
