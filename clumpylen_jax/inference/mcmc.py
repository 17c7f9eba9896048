"""Posterior sampling: emcee (ensemble, vectorised over walkers) and NUTS (blackjax).

Both sample the unconstrained vector u with density
    ln p(u) = ln L(state(u)) + ln prior(state(u)) + ln |dx/du|,
i.e. a prior flat in the physical parameters x (or the one given), and report
samples in x too.

emcee: the log density is `jax.jit(jax.vmap(...))` over walkers and handed to
`emcee.EnsembleSampler(..., vectorize=True)`, so each ensemble update is one
batched model evaluation. NUTS: blackjax's window adaptation (step size and
diagonal mass matrix) then NUTS steps in a `lax.scan`, chains under `jax.vmap`,
compiled once per problem structure. Given `scale` (L, e.g. the Cholesky factor of
the Laplace covariance in u), NUTS moves in z = L⁻¹(u − u0) instead: a posterior near
its Laplace approximation is a unit Gaussian there, so the adaptation starts from the
right (dense) metric rather than the identity in u, where fluxes, positions and sizes
differ in scale by orders of magnitude. L comes from the Fisher / Laplace covariance
(`whitening_scale`) or, where that covariance is near-singular, from the Hessian of the
sampled density itself (`hessian_scale`); `laplace_mismatch` checks either.
"""

from __future__ import annotations

from typing import Callable, Optional

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..errors import require
from .diagnostics import effective_sample_size, split_rhat
from .likelihood import ImageData, make_log_posterior
from .params import Parametrization


class ChainResult(eqx.Module):
    """Samples and diagnostics.

    samples_u, samples_x: [n_chains, n_draws, n_params] in unconstrained / physical space
        (emcee: one chain per walker).  log_posterior: [n_chains, n_draws].
    acceptance: mean acceptance fraction (emcee) or mean acceptance probability (NUTS).
    autocorr_time: emcee's integrated autocorrelation time per parameter (quiet=True),
        NaN for NUTS.  ess, rhat: per parameter (diagnostics.py).
    n_divergent: NUTS divergent transitions (0 for emcee).  labels: parameter labels.
    """

    samples_u: np.ndarray
    samples_x: np.ndarray
    log_posterior: np.ndarray
    acceptance: float
    autocorr_time: np.ndarray
    ess: np.ndarray
    rhat: np.ndarray
    n_divergent: int
    labels: tuple = eqx.field(static=True)
    method: str = eqx.field(static=True)

    def flat_x(self):
        """All physical samples as [n_samples, n_params]."""
        return self.samples_x.reshape(-1, self.samples_x.shape[-1])

    def mean_std(self):
        """(mean, std) of the physical samples per parameter."""
        f = self.flat_x()
        return f.mean(axis=0), f.std(axis=0, ddof=1)


def posterior_median(chains: ChainResult, param: Parametrization):
    """(the state at the samples' median, the samples' median and covariance as an
    `Uncertainty`): what a sampled fit reports."""
    from .uncertainty import Uncertainty
    flat = chains.flat_x()
    med = np.median(flat, axis=0)
    return (param.state_from_physical(jnp.asarray(med)),
            Uncertainty(param.labels, jnp.asarray(med), jnp.asarray(np.atleast_2d(np.cov(flat.T)))))


def _logdensity(scene_model, data, param, log_prior) -> Callable:
    return make_log_posterior(scene_model, data, param, log_prior=log_prior, jacobian=True)


@eqx.filter_jit
def _batched_logdensity(scene_model, data, param, log_prior, us):
    lp = jax.vmap(_logdensity(scene_model, data, param, log_prior))(us)
    return jnp.where(jnp.isfinite(lp), lp, -jnp.inf)


@eqx.filter_jit
def _batched_physical(param, us):
    return jax.vmap(param.physical_vector)(us)


# the widest σ in u that a transformed (non-identity) parameter is given by `whitening_scale`:
# a bounded or log transform spans its whole range in a few units of u, and at a bound the
# Fisher σ in u is ~1/|dx/du| (3e4 for a clump R_e at its lower bound in the S1063 fit),
# which would throw the chains across the interval in one step
U_SIGMA_CAP = 1.0


def _identity_entries(param: Parametrization) -> np.ndarray:
    """[size] True for the entries of u whose transform is the identity (fluxes)."""
    return np.array([leaf.transform.kind == "identity" for leaf in param.leaves
                     for _ in leaf.index], bool)


def whitening_scale(param: Parametrization, u, cov_x, cap: float = U_SIGMA_CAP) -> np.ndarray:
    """L with L Lᵀ = the covariance in u of the Laplace / Fisher covariance `cov_x` of the
    physical parameters at u (cov_u = D⁻¹ cov_x D⁻¹, D = dx/du, diagonal), for `run_nuts`'
    `scale`. A transformed parameter whose σ in u exceeds `cap` (one at or near a bound) gets σ
    = cap and no correlations: there the posterior in u is no Gaussian (flat likelihood times
    the transform's Jacobian). Non-finite or non-positive variances get σ = cap too."""
    _, dxdu = param.physical_and_slope(jnp.asarray(u))
    dinv = 1.0 / np.asarray(dxdu, float)
    cov_u = dinv[:, None] * np.asarray(cov_x, float) * dinv[None, :]
    var = np.diag(cov_u)
    bad = ~np.isfinite(var) | (var <= 0) | (~_identity_entries(param) & (var > cap ** 2))
    sd = np.where(bad, cap, np.sqrt(np.where(bad, 1.0, var)))
    corr = cov_u / np.outer(sd, sd)
    corr[bad, :] = 0.0
    corr[:, bad] = 0.0
    np.fill_diagonal(corr, 1.0)
    corr = np.where(np.isfinite(corr), corr, 0.0)
    w, v = np.linalg.eigh(0.5 * (corr + corr.T))   # nearest positive-definite correlation
    corr = (v * np.maximum(w, 1e-10)) @ v.T
    return sd[:, None] * np.linalg.cholesky(corr)


@eqx.filter_jit
def _neg_log_density_hessian(scene_model, data, param, u):
    # the model and data are arguments, not closed over: one program per problem structure,
    # their arrays not baked into it as constants
    return -jax.hessian(_logdensity(scene_model, data, param, None))(u)


def hessian_scale(scene_model, data: ImageData, param: Parametrization, u, cov_x,
                  cap: float = U_SIGMA_CAP) -> np.ndarray:
    """L with L Lᵀ = H⁻¹, H = −∇² ln p(u) of the density NUTS samples (likelihood times the
    transforms' Jacobian, flat in the physical parameters), its eigenvalues floored so
    that no direction is wider than `cap` (in u; for identity parameters, `cap` × their
    Fisher σ).

    Where the Fisher matrix is near-singular (a clump's R_e unresolved, centres degenerate
    with the diffuse light: RXJ1131, marginal σ_u up to 1.6e5), `whitening_scale` caps each
    parameter alone and keeps the near-singular rest; here the Jacobian's own curvature
    bounds the flat directions, and the floor is per direction. Units: identity parameters
    (fluxes, in data units) are measured in their Fisher σ from `cov_x` before the floor,
    transformed ones in u, whose range a bounded or log transform spans in a few units.
    One Hessian: ~ parameters × a gradient's cost, compiled once."""
    u = jnp.asarray(u)
    h = np.asarray(_neg_log_density_hessian(scene_model, data, param, u), float)
    _, dxdu = param.physical_and_slope(u)
    sd = np.sqrt(np.abs(np.diag(np.asarray(cov_x, float)))) / np.abs(np.asarray(dxdu, float))
    d = np.where(_identity_entries(param) & np.isfinite(sd) & (sd > 0), sd, 1.0)
    hs = d[:, None] * np.where(np.isfinite(h), h, 0.0) * d[None, :]
    w, v = np.linalg.eigh(0.5 * (hs + hs.T))
    return d[:, None] * (v / np.sqrt(np.maximum(w, 1.0 / cap**2)))


def laplace_mismatch(scene_model, data: ImageData, param: Parametrization, u0, scale,
                     seed: int = 0) -> float:
    """−Δln p / (½|z|²) between u0 and u0 + L z for one z ~ N(0, I) (L = `scale`): ~1 where
    the posterior in whitened coordinates is the unit Gaussian the metric assumes (S1063:
    1.3), ≫ 1 where the optimum's covariance misdescribes it (RXJ1131 with its diffuse
    light: ~400), and NUTS then takes tiny steps. NaN where a density is not finite."""
    u0 = np.asarray(u0, float)
    z = np.random.default_rng(seed).standard_normal(u0.size)
    us = jnp.asarray(np.stack([u0, u0 + np.asarray(scale, float) @ z]))
    lp = np.asarray(_batched_logdensity(scene_model, data, param, None, us))
    ratio = -(lp[1] - lp[0]) / (0.5 * float(z @ z))
    return float(ratio) if np.isfinite(ratio) else float("nan")


def run_emcee(scene_model, data: ImageData, param: Parametrization, u0, *, n_walkers=None,
              n_steps=1000, burn=None, init_scale=1e-3, seed=0,
              log_prior: Optional[Callable] = None) -> ChainResult:
    """emcee ensemble around u0 (usually the MAP), vectorised over walkers.

    init_scale: scalar or per-parameter σ (in u) of the initial Gaussian ball
        (the Laplace errors in u are a good choice).
    burn: draws dropped from the start (default: n_steps // 4).
    """
    import emcee

    u0 = np.asarray(u0, float)
    d = u0.size
    n_walkers = int(n_walkers or max(4 * d, 16))
    n_walkers += n_walkers % 2
    require(n_walkers >= 2 * d, "n_walkers", n_walkers, f"at least 2 × {d} parameters")
    burn = n_steps // 4 if burn is None else int(burn)
    rng = np.random.default_rng(seed)
    p0 = u0[None, :] + rng.standard_normal((n_walkers, d)) * np.asarray(init_scale)

    def logp(us):
        return np.asarray(_batched_logdensity(scene_model, data, param, log_prior, jnp.asarray(us)))

    sampler = emcee.EnsembleSampler(n_walkers, d, logp, vectorize=True)
    # emcee draws from its own RandomState: seed it so that runs are reproducible
    sampler.random_state = np.random.RandomState(int(rng.integers(2**31))).get_state()
    sampler.run_mcmc(p0, n_steps, progress=False)
    chain = sampler.get_chain(discard=burn)           # [draws, walkers, d]
    lp = sampler.get_log_prob(discard=burn)
    su = np.transpose(chain, (1, 0, 2))
    sx = np.asarray(_batched_physical(param, jnp.asarray(su.reshape(-1, d)))).reshape(su.shape)
    tau = np.asarray(sampler.get_autocorr_time(quiet=True, discard=burn))
    return ChainResult(su, sx, lp.T, float(np.mean(sampler.acceptance_fraction)), tau,
                       effective_sample_size(sx), split_rhat(sx), 0, param.labels, "emcee")


def _step_size_warmup(logdensity, z0, key, n_steps, target=0.8):
    """NUTS warm-up in whitened coordinates: the metric stays the identity and only the step
    size is tuned (dual averaging, Hoffman & Gelman 2014 §3.2). blackjax's window adaptation
    also estimates a mass matrix from the warm-up draws; from a few hundred draws in ~100
    dimensions that estimate is noisier than the Laplace metric the whitening already holds
    (on the two-band mock: R̂ 2.8 after 100 warm-up steps)."""
    import blackjax
    from blackjax.adaptation.step_size import dual_averaging_adaptation

    da_init, da_update, da_final = dual_averaging_adaptation(target)
    kernel = blackjax.nuts.build_kernel()
    metric = jnp.ones_like(z0)
    # ε ≈ 1.7 d^(-1/4) for leapfrog on a unit Gaussian in d dimensions; a start below it
    first = 1.0 / z0.size ** 0.25

    def step(carry, k):
        st, da = carry
        st, info = kernel(k, st, logdensity, jnp.exp(da.log_step_size), metric)
        return (st, da_update(da, info.acceptance_rate)), None

    (state, da), _ = jax.lax.scan(step, (blackjax.nuts.init(z0, logdensity), da_init(first)),
                                  jax.random.split(key, n_steps))
    return state, {"step_size": da_final(da), "inverse_mass_matrix": metric}


@eqx.filter_jit
def _nuts_chains(scene_model, data, param, log_prior, z0s, keys, n_warmup, n_samples,
                 center=None, scale=None):
    """Chains in z (u = center + scale @ z; z = u without a scale); positions returned in u."""
    import blackjax

    logdensity = _logdensity(scene_model, data, param, log_prior)
    if scale is not None:
        logdensity_u = logdensity

        def logdensity(z):   # u = center + L z has a constant Jacobian: nothing to add
            return logdensity_u(center + scale @ z)

    def one_chain(u0, key):
        k_warm, k_run = jax.random.split(key)
        if scale is None:
            warmup = blackjax.window_adaptation(blackjax.nuts, logdensity)
            (state, params), _ = warmup.run(k_warm, u0, num_steps=n_warmup)
        else:
            state, params = _step_size_warmup(logdensity, u0, k_warm, n_warmup)
        kernel = blackjax.nuts(logdensity, **params).step

        def step(st, k):
            st, info = kernel(k, st)
            return st, (st.position, st.logdensity, info.acceptance_rate, info.is_divergent)

        _, out = jax.lax.scan(step, state, jax.random.split(k_run, n_samples))
        return out

    pos, lp, acc, div = jax.vmap(one_chain)(z0s, keys)
    if scale is not None:
        pos = center + pos @ scale.T
    return pos, lp, acc, div


def run_nuts(scene_model, data: ImageData, param: Parametrization, u0, key, *, n_chains=2,
             n_warmup=300, n_samples=500, init_scale=1e-3, scale=None,
             log_prior: Optional[Callable] = None) -> ChainResult:
    """NUTS (blackjax) with window adaptation; `n_chains` chains from u0 + init_scale·N(0, 1).

    scale: [d, d] matrix L or None. With L the chains move in z = L⁻¹(u − u0) (module doc),
        start at z = init_scale·N(0, 1), i.e. u0 + init_scale·L·N(0, 1), and the warm-up
        tunes the step size only (`_step_size_warmup`).
    """
    require(int(n_chains) >= 1, "n_chains", n_chains, "an integer ≥ 1")
    u0 = jnp.asarray(u0)
    k_init, k_run = jax.random.split(key)
    dz = jax.random.normal(k_init, (n_chains, u0.size), u0.dtype) * jnp.asarray(init_scale)
    if scale is None:
        z0s, center = u0[None] + dz, None
    else:
        scale = jnp.asarray(scale, u0.dtype)
        require(scale.shape == (u0.size, u0.size) and bool(jnp.all(jnp.isfinite(scale))),
                "scale", f"shape {scale.shape}", f"a finite [{u0.size}, {u0.size}] matrix")
        z0s, center = dz, u0
    pos, lp, acc, div = _nuts_chains(scene_model, data, param, log_prior, z0s,
                                     jax.random.split(k_run, n_chains), int(n_warmup),
                                     int(n_samples), center, scale)
    su = np.asarray(pos)
    sx = np.asarray(_batched_physical(param, pos.reshape(-1, u0.size))).reshape(su.shape)
    return ChainResult(su, sx, np.asarray(lp), float(np.mean(acc)),
                       np.full(u0.size, np.nan), effective_sample_size(sx), split_rhat(sx),
                       int(np.sum(div)), param.labels, "nuts")


START_BALL = 0.1   # chains start within this fraction of the optimum's whitened widths


def sample_from_optimum(method: str, scene_model, data: ImageData, param: Parametrization, u0,
                        scale, *, seed: int = 0, **options) -> ChainResult:
    """emcee or NUTS ("emcee" / "nuts") started at an optimum u0, with `scale` its whitening
    (`whitening_scale` of its Fisher or Laplace covariance): NUTS in coordinates whitened by
    it, emcee's walkers in a ball of START_BALL × its widths. options: `run_emcee` /
    `run_nuts` keywords (given ones win). The NUTS key is fold_in(key(seed), 1)."""
    require(method in ("emcee", "nuts"), "method", method, '"emcee" or "nuts"')
    if method == "emcee":
        options.setdefault("init_scale", START_BALL * np.sqrt(np.sum(np.asarray(scale) ** 2,
                                                                     axis=1)))
        return run_emcee(scene_model, data, param, u0, seed=seed, **options)
    options.setdefault("scale", scale)
    options.setdefault("init_scale", START_BALL)
    return run_nuts(scene_model, data, param, u0, jax.random.fold_in(jax.random.key(seed), 1),
                    **options)
