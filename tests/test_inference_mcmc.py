"""emcee and NUTS agree on a small (3-parameter) posterior, and their diagnostics are sane."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from clumpylen_jax.inference import fisher_uncertainty, fit_map, make_data, make_state, parametrize
from clumpylen_jax.inference.mcmc import run_emcee, run_nuts
from clumpylen_jax.inference.mock import toy_bands, toy_model
from clumpylen_jax.source import Clumps, Source


def test_emcee_and_nuts_agree():
    src = Source(clumps=Clumps(jnp.array([[-0.2, 0.1], [0.2, -0.1]]), jnp.array([[0.6], [0.3]]),
                               jnp.array([0.08, 0.06]), jnp.full(2, 0.5), jnp.array([0.8, 0.9]),
                               jnp.array([0.3, 1.0])))
    model = toy_model(src, toy_bands(1, pixel_arcsec=0.04), npix=21)
    noisy, _, var = eqx.filter_jit(model.observe)(src, jax.random.key(1))
    data = make_data(model, noisy, var)
    param = parametrize(make_state(src, 1), {"clumps.flux": True, "clumps.re_arcsec": [0]})
    # the samplers start where an astronomer would: at the MAP reached from a start away
    # from the truth (the truth only makes the mock)
    u0 = fit_map(model, data, param, param.initial() + jnp.array([0.3, -0.3, 0.2])).u
    em = run_emcee(model, data, param, u0, n_walkers=16, n_steps=600, init_scale=0.01, seed=3)
    nu = run_nuts(model, data, param, u0, jax.random.key(4), n_chains=2, n_warmup=200, n_samples=300)
    m_e, s_e = em.mean_std()
    m_n, s_n = nu.mean_std()
    assert np.all(np.abs(m_e - m_n) < 0.5 * np.maximum(s_e, s_n)), (m_e, m_n, s_e)
    np.testing.assert_allclose(s_e, s_n, rtol=0.3)
    # both near the Fisher (Cramér–Rao) width at the truth
    fe = np.asarray(fisher_uncertainty(model, param, data=data).err)
    np.testing.assert_allclose(s_n, fe, rtol=0.3)
    assert 0.2 < em.acceptance < 0.9 and 0.6 < nu.acceptance <= 1.0
    assert np.all(np.isfinite(em.autocorr_time)) and np.all(em.autocorr_time > 1)
    assert np.all(nu.rhat < 1.05) and np.all(nu.ess > 100) and nu.n_divergent == 0
    assert em.samples_x.shape == (16, 450, 3) and nu.samples_x.shape == (2, 300, 3)
