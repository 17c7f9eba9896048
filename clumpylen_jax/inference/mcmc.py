"""Posterior sampling: emcee (ensemble, vectorised over walkers) and NUTS (blackjax).

Both sample the unconstrained vector u with density
    ln p(u) = ln L(state(u)) + ln prior(state(u)) + ln |dx/du|,
i.e. a prior flat in the physical parameters x (or the one given), and report
samples in x too.

emcee: the log density is `jax.jit(jax.vmap(...))` over walkers and handed to
`emcee.EnsembleSampler(..., vectorize=True)`, so each ensemble update is one
batched model evaluation. NUTS: blackjax's window adaptation (step size and
diagonal mass matrix) then NUTS steps in a `lax.scan`, chains under `jax.vmap`,
compiled once per problem structure.
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


def _logdensity(scene_model, data, param, log_prior) -> Callable:
    return make_log_posterior(scene_model, data, param, log_prior=log_prior, jacobian=True)


@eqx.filter_jit
def _batched_logdensity(scene_model, data, param, log_prior, us):
    lp = jax.vmap(_logdensity(scene_model, data, param, log_prior))(us)
    return jnp.where(jnp.isfinite(lp), lp, -jnp.inf)


@eqx.filter_jit
def _batched_physical(param, us):
    return jax.vmap(param.physical_vector)(us)


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


@eqx.filter_jit
def _nuts_chains(scene_model, data, param, log_prior, u0s, keys, n_warmup, n_samples):
    import blackjax

    logdensity = _logdensity(scene_model, data, param, log_prior)

    def one_chain(u0, key):
        k_warm, k_run = jax.random.split(key)
        warmup = blackjax.window_adaptation(blackjax.nuts, logdensity)
        (state, params), _ = warmup.run(k_warm, u0, num_steps=n_warmup)
        kernel = blackjax.nuts(logdensity, **params).step

        def step(st, k):
            st, info = kernel(k, st)
            return st, (st.position, st.logdensity, info.acceptance_rate, info.is_divergent)

        _, out = jax.lax.scan(step, state, jax.random.split(k_run, n_samples))
        return out

    return jax.vmap(one_chain)(u0s, keys)


def run_nuts(scene_model, data: ImageData, param: Parametrization, u0, key, *, n_chains=2,
             n_warmup=300, n_samples=500, init_scale=1e-3,
             log_prior: Optional[Callable] = None) -> ChainResult:
    """NUTS (blackjax) with window adaptation; `n_chains` chains from u0 + init_scale·N(0, 1)."""
    require(int(n_chains) >= 1, "n_chains", n_chains, "an integer ≥ 1")
    u0 = jnp.asarray(u0)
    k_init, k_run = jax.random.split(key)
    u0s = u0[None] + jax.random.normal(k_init, (n_chains, u0.size), u0.dtype) * jnp.asarray(init_scale)
    pos, lp, acc, div = _nuts_chains(scene_model, data, param, log_prior, u0s,
                                     jax.random.split(k_run, n_chains), int(n_warmup), int(n_samples))
    su = np.asarray(pos)
    sx = np.asarray(_batched_physical(param, pos.reshape(-1, u0.size))).reshape(su.shape)
    return ChainResult(su, sx, np.asarray(lp), float(np.mean(acc)),
                       np.full(u0.size, np.nan), effective_sample_size(sx), split_rhat(sx),
                       int(np.sum(div)), param.labels, "nuts")
