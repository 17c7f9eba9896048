"""run_fit writes fit.ecsv, chains.npz and residual FITS; vmapped multi-start agrees with LM."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from astropy.io import fits
from astropy.table import Table

from clumpylen_jax.inference import fit_map, fit_map_multistart, make_data, make_state, parametrize
from clumpylen_jax.inference.mock import toy_bands, toy_model
from clumpylen_jax.inference.run import run_fit
from clumpylen_jax.source import Clumps, Source

SRC = Source(clumps=Clumps(jnp.array([[-0.15, 0.05], [0.15, -0.05]]), jnp.array([[3.0], [2.0]]),
                           jnp.array([0.07, 0.06]), jnp.full(2, 0.5), jnp.array([0.8, 0.9]),
                           jnp.array([0.3, 1.0])))
# every fit here starts away from the truth (fluxes × 0.7, centres moved by ~0.04"): the
# truth makes the mock only
START = eqx.tree_at(lambda s: (s.clumps.flux, s.clumps.center_arcsec), SRC,
                    (SRC.clumps.flux * 0.7, SRC.clumps.center_arcsec + jnp.array([[0.03, -0.02],
                                                                                  [-0.02, 0.03]])))


@pytest.mark.slow  # 19 s; test_cli_fit's emcee run covers the files written (keeps make test < 10 min)
def test_run_fit_emcee_writes_outputs(tmp_path):
    model = toy_model(SRC, toy_bands(1), npix=21)
    noisy, _, var = eqx.filter_jit(model.observe)(SRC, jax.random.key(0))
    out = run_fit(model, START, {"B0": np.asarray(noisy[0])}, {"B0": np.asarray(var[0])},
                  free={"clumps.flux": True, "clumps.center_arcsec": True}, method="emcee",
                  zeropoints_ab={"B0": 27.0}, out_dir=tmp_path, mcmc=dict(n_walkers=16, n_steps=200))
    names = sorted(p.name for p in tmp_path.iterdir())
    assert names == ["chains.npz", "fit.ecsv", "residuals_B0.fits"]
    t = Table.read(tmp_path / "fit.ecsv")
    assert len(t) == 2 and "mag_B0_err" in t.colnames and "beta2_arcsec_err" in t.colnames
    assert np.all(np.abs(t["flux_B0"] - [3.0, 2.0]) < 4 * t["flux_B0_err"])
    chains = np.load(tmp_path / "chains.npz")
    assert chains["samples_x"].shape[-1] == 6 and chains["labels"].size == 6
    with fits.open(tmp_path / "residuals_B0.fits") as h:
        chi = h["CHI"].data
        assert 0.5 < np.std(chi) < 1.5
    assert out.chains is not None and out.chains.method == "emcee"


@pytest.mark.slow
def test_multistart_matches_lm():
    """fit_map_multistart reaches fit_map's optimum. Slow: 26 s on 2 cores, two compiled
    fits of the whole model (`make test` took 10 min 18 s with it)."""
    model = toy_model(SRC, toy_bands(1), npix=21)
    noisy, _, var = eqx.filter_jit(model.observe)(SRC, jax.random.key(1))
    data = make_data(model, noisy, var)
    param = parametrize(make_state(START, 1), {"clumps.flux": True, "clumps.center_arcsec": True})
    lm = fit_map(model, data, param)
    ms = fit_map_multistart(model, data, param, jax.random.key(2), n_starts=3, scale=0.05)
    assert ms.starts_log_posterior.shape == (3,)
    np.testing.assert_allclose(ms.log_posterior, lm.log_posterior, atol=1e-4)
