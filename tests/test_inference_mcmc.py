"""emcee and NUTS agree on a small (3-parameter) posterior, their diagnostics are sane, and
NUTS whitened by the Laplace metric samples the Fisher widths."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from clumpylen_jax.inference import fisher_uncertainty, fit_map, make_data, make_state, parametrize
from clumpylen_jax.inference.mcmc import run_emcee, run_nuts
from clumpylen_jax.inference.mock import toy_bands, toy_model
from clumpylen_jax.source import Clumps, Source


def _toy_problem():
    src = Source(clumps=Clumps(jnp.array([[-0.2, 0.1], [0.2, -0.1]]), jnp.array([[0.6], [0.3]]),
                               jnp.array([0.08, 0.06]), jnp.full(2, 0.5), jnp.array([0.8, 0.9]),
                               jnp.array([0.3, 1.0])))
    model = toy_model(src, toy_bands(1, pixel_arcsec=0.04), npix=21)
    noisy, _, var = eqx.filter_jit(model.observe)(src, jax.random.key(1))
    data = make_data(model, noisy, var)
    param = parametrize(make_state(src, 1), {"clumps.flux": True, "clumps.re_arcsec": [0]})
    return model, data, param


def test_emcee_and_nuts_agree():
    model, data, param = _toy_problem()
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


def test_whitening_scale_is_the_covariance_in_u_and_caps_parameters_at_a_bound():
    """L Lᵀ = D⁻¹ C D⁻¹ (D = dx/du) where the σ in u is modest; a transformed parameter at its
    bound (σ_u ≫ 1: the Fisher width over a vanishing dx/du) gets σ_u = cap and no
    correlation; an identity (flux) parameter is never capped, whatever its width."""
    from clumpylen_jax.inference.mcmc import whitening_scale
    from clumpylen_jax.inference.transforms import Transform
    from clumpylen_jax.inference.params import Free
    src = Source(clumps=Clumps(jnp.array([[0.0, 0.0]]), jnp.array([[0.5]]), jnp.array([0.1]),
                               jnp.full(1, 0.5), jnp.ones(1), jnp.zeros(1)))
    param = parametrize(make_state(src, 1), {
        "clumps.flux": Free(True, Transform("identity")),
        "clumps.re_arcsec": Free(True, Transform("log_bounded", 0.01, 0.3)),
        "clumps.center_arcsec": Free(True, Transform("bounded", -0.5, 0.5))})
    cov = np.array([[4.0, 0.005, 0.0, 0.0], [0.005, 1e-4, 0.0, 0.0],
                    [0.0, 0.0, 1e-4, 5e-5], [0.0, 0.0, 5e-5, 1e-4]])
    u = param.initial()
    L = np.asarray(whitening_scale(param, u, cov))
    _, dxdu = jax.jvp(param.physical_vector, (u,), (jnp.ones_like(u),))
    d = 1 / np.asarray(dxdu)
    np.testing.assert_allclose(L @ L.T, d[:, None] * cov * d[None, :], rtol=1e-9, atol=1e-15)
    # R_e pushed to its lower bound: dx/du → 0 there, the Fisher σ in u explodes
    u_edge = u.at[1].set(-30.0)
    L = np.asarray(whitening_scale(param, u_edge, cov, cap=1.0))
    C = L @ L.T
    assert abs(C[1, 1] - 1.0) < 1e-6 and abs(C[0, 1]) < 1e-12 and abs(C[1, 2]) < 1e-12
    assert abs(C[0, 0] - 4.0) < 1e-9   # identity: σ = 2 flux units kept, not capped
    assert np.all(np.isfinite(L))


def test_whitened_nuts_matches_fisher_on_a_small_posterior():
    """NUTS in whitened coordinates (scale = the Laplace factor, step size tuned alone) samples
    the same posterior as the plain run: widths within 20 % of the Fisher ones, R̂ < 1.05,
    no divergence; the same seed gives the same draws, bit for bit."""
    from clumpylen_jax.inference.mcmc import whitening_scale
    model, data, param = _toy_problem()
    u0 = fit_map(model, data, param, param.initial() + jnp.array([0.3, -0.3, 0.2])).u
    x0 = param.physical_vector(u0)
    fe = fisher_uncertainty(model, param, x0, data)
    L = whitening_scale(param, u0, fe.cov)
    # the metric check: ~1 for the right metric; ≳ 100 for one 10× too wide (Δln p ∝ scale²
    # for a Gaussian; more where 10σ reaches the transforms' curvature)
    from clumpylen_jax.inference.mcmc import laplace_mismatch
    ok, wide = (laplace_mismatch(model, data, param, u0, k * L, seed=1) for k in (1.0, 10.0))
    assert 0.5 < ok < 2.0 and wide > 50, (ok, wide)
    run = lambda: run_nuts(model, data, param, u0, jax.random.key(5), n_chains=2,  # noqa: E731
                           n_warmup=150, n_samples=300, init_scale=0.1, scale=L)
    nu = run()
    _, s_n = nu.mean_std()
    np.testing.assert_allclose(s_n, np.asarray(fe.err), rtol=0.2)
    assert np.all(nu.rhat < 1.05) and nu.n_divergent == 0 and 0.6 < nu.acceptance <= 1.0
    np.testing.assert_array_equal(run().samples_x, nu.samples_x)


def test_hessian_scale_matches_the_laplace_metric_and_bounds_a_flat_direction():
    """On the small posterior, H⁻¹ of the sampled density agrees with the Fisher whitening
    (widths within 15 %, metric check ~1). A third clump of zero flux leaves its R_e free of
    the data: its Fisher variance is singular, and the Hessian metric gives it at most the
    cap (σ_u ≤ 1), while the others keep their widths."""
    from clumpylen_jax.inference.mcmc import hessian_scale, laplace_mismatch, whitening_scale
    model, data, param = _toy_problem()
    u0 = fit_map(model, data, param, param.initial() + jnp.array([0.3, -0.3, 0.2])).u
    fe = fisher_uncertainty(model, param, param.physical_vector(u0), data)
    L_f = whitening_scale(param, u0, fe.cov)
    L_h = hessian_scale(model, data, param, u0, fe.cov)
    sd_f, sd_h = (np.sqrt(np.diag(L @ L.T)) for L in (L_f, L_h))
    np.testing.assert_allclose(sd_h, sd_f, rtol=0.15)
    assert 0.5 < laplace_mismatch(model, data, param, u0, L_h, seed=1) < 2.0

    src = Source(clumps=Clumps(jnp.array([[-0.2, 0.1], [0.2, -0.1], [0.0, 0.25]]),
                               jnp.array([[0.6], [0.3], [0.0]]), jnp.array([0.08, 0.06, 0.05]),
                               jnp.full(3, 0.5), jnp.array([0.8, 0.9, 1.0]),
                               jnp.array([0.3, 1.0, 0.0])))
    flat = parametrize(make_state(src, 1), {"clumps.flux": [0, 1], "clumps.re_arcsec": [0, 2]})
    model3 = toy_model(src, toy_bands(1, pixel_arcsec=0.04), npix=21)
    data3 = make_data(model3, data.images, data.variances)
    u3 = fit_map(model3, data3, flat, flat.initial() + jnp.array([0.2, -0.2, 0.1, 0.0])).u
    fe3 = fisher_uncertainty(model3, flat, flat.physical_vector(u3), data3)
    L3 = hessian_scale(model3, data3, flat, u3, fe3.cov)
    sd3 = np.sqrt(np.diag(L3 @ L3.T))
    assert np.all(np.isfinite(L3)) and sd3[3] <= 1.0 + 1e-9, sd3
    np.testing.assert_allclose(sd3[:3], sd_h, rtol=0.15)


def test_observed_fit_sampling_keeps_the_better_checked_metric(monkeypatch):
    """`observations.sample.sample_observed_fit` computes the Hessian metric when the Fisher
    metric's check is above MISMATCH_WARN (forced here: 0) and samples with whichever check
    is nearer 1 (a unit Gaussian); summary.json's fields say which, and with both checks."""
    from clumpylen_jax.observations import FitOptions, sample
    from clumpylen_jax.observations.fit import ObservedFit
    monkeypatch.setattr(sample, "MISMATCH_WARN", 0.0)
    model, data, param = _toy_problem()
    u0 = fit_map(model, data, param, param.initial() + jnp.array([0.3, -0.3, 0.2])).u
    unc = fisher_uncertainty(model, param, param.physical_vector(u0), data)
    fit = ObservedFit(model, data, param, param.state(u0), unc, (), True, [], {}, 2)
    messages = []
    out = sample.sample_observed_fit(fit, "nuts", FitOptions(sampler_chains=1, sampler_warmup=30,
                                                             sampler_samples=30), 0,
                                     messages.append)
    s = out.summary
    assert s["metric"] in ("fisher", "hessian")
    near = lambda v: abs(np.log(v))  # noqa: E731  (nearer 1 wins)
    assert near(s["laplace_mismatch"]) <= near(s["laplace_mismatch_fisher"])
    assert any("Hessian" in m for m in messages)
    assert out.chains.samples_x.shape == (1, 30, 3) and np.all(np.isfinite(out.chains.samples_x))
