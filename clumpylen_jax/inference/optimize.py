"""Maximum a posteriori fits with optimistix, from one start or many (vmapped).

Two solvers, both in the unconstrained space of a `Parametrization`:
- "lm": Levenberg–Marquardt on the whitened residuals (Gaussian likelihood with
  fixed variances and no prior): uses the least-squares structure, converges in
  a handful of steps near the optimum;
- "bfgs": BFGS on −ln posterior (any likelihood, optional prior).

The solve is compiled once per (scene model, data layout, free set, solver)
structure with `eqx.filter_jit`; arrays (data, template, start) are traced, so
fits to new noise realisations or from new starts reuse the compiled code.
"""

from __future__ import annotations

from typing import Callable, Optional

import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx

from ..errors import require
from .likelihood import ImageData, make_log_posterior, make_residuals
from .params import FitState, Parametrization


class MapResult(eqx.Module):
    """Outcome of a MAP fit.

    u: optimum in unconstrained space.  x: physical free parameters at u.
    state: the FitState at u.  log_posterior: ln L (+ ln prior) at u (no Jacobian term).
    success: solver converged.  n_steps: solver steps.  method: solver used.
    starts_log_posterior: per-start values for multi-start fits (else None).
    """

    u: jnp.ndarray
    x: jnp.ndarray
    state: FitState
    log_posterior: jnp.ndarray
    success: jnp.ndarray
    n_steps: jnp.ndarray
    method: str = eqx.field(static=True)
    starts_log_posterior: Optional[jnp.ndarray] = None


def _solve(scene_model, data, param, u0, method, log_prior, rtol, atol, max_steps):
    logpost = make_log_posterior(scene_model, data, param, log_prior=log_prior, jacobian=False)
    if method == "lm":
        resid = make_residuals(scene_model, data, param)
        sol = optx.least_squares(lambda u, _: resid(u), optx.LevenbergMarquardt(rtol, atol), u0,
                                 max_steps=max_steps, throw=False)
    else:
        sol = optx.minimise(lambda u, _: -logpost(u), optx.BFGS(rtol, atol), u0,
                            max_steps=max_steps, throw=False)
    u = sol.value
    return u, logpost(u), sol.result == optx.RESULTS.successful, sol.stats["num_steps"]


@eqx.filter_jit
def _solve_one(scene_model, data, param, u0, method, log_prior, rtol, atol, max_steps):
    return _solve(scene_model, data, param, u0, method, log_prior, rtol, atol, max_steps)


@eqx.filter_jit
def _solve_many(scene_model, data, param, u0s, method, log_prior, rtol, atol, max_steps):
    return jax.vmap(lambda u0: _solve(scene_model, data, param, u0, method, log_prior, rtol, atol,
                                      max_steps))(u0s)


def _method(data: ImageData, method: str, log_prior) -> str:
    require(method in ("auto", "lm", "bfgs"), "method", method, '"auto", "lm" or "bfgs"')
    if method == "auto":
        return "lm" if data.kind == "gaussian" and log_prior is None else "bfgs"
    if method == "lm":
        require(data.kind == "gaussian" and log_prior is None, "method", "lm",
                'a Gaussian likelihood with fixed variances and no prior (use "bfgs")')
    return method


def fit_map(scene_model, data: ImageData, param: Parametrization, u0=None, *, method="auto",
            log_prior: Optional[Callable] = None, rtol=1e-8, atol=1e-8,
            max_steps=200) -> MapResult:
    """MAP (or maximum-likelihood) fit from `u0` (default: the template's values).

    method: "lm", "bfgs" or "auto" (LM for fixed-variance Gaussian data without prior).
    log_prior: callable(FitState) → ln prior in physical parameters, or None (flat).
    """
    method = _method(data, method, log_prior)
    u0 = param.initial() if u0 is None else jnp.asarray(u0)
    u, lp, ok, steps = _solve_one(scene_model, data, param, u0, method, log_prior,
                                  float(rtol), float(atol), int(max_steps))
    return MapResult(u, param.physical_vector(u), param.state(u), lp, ok, steps, method)


def perturbed_starts(param: Parametrization, key, n_starts: int, scale=0.1, u0=None):
    """n_starts starts: u0 (first, unperturbed) and u0 + scale·N(0, 1) in unconstrained space.

    scale: scalar or per-parameter array (in u units: 0.1 is ±10 % on log quantities).
    """
    u0 = param.initial() if u0 is None else jnp.asarray(u0)
    eps = jax.random.normal(key, (n_starts - 1, u0.size), u0.dtype) * jnp.asarray(scale)
    return jnp.concatenate([u0[None], u0[None] + eps], axis=0)


def fit_map_multistart(scene_model, data: ImageData, param: Parametrization, key, *,
                       n_starts=8, scale=0.1, u0=None, method="auto",
                       log_prior: Optional[Callable] = None, rtol=1e-8, atol=1e-8,
                       max_steps=200) -> MapResult:
    """Fits from `perturbed_starts`, solved together under `jax.vmap`; returns the best.

    The per-start optima's ln posterior is kept in `starts_log_posterior` (a spread
    there flags multiple modes, e.g. swapped blended clumps).
    """
    require(int(n_starts) >= 1, "n_starts", n_starts, "an integer ≥ 1")
    method = _method(data, method, log_prior)
    starts = perturbed_starts(param, key, int(n_starts), scale, u0)
    us, lps, oks, steps = _solve_many(scene_model, data, param, starts, method, log_prior,
                                      float(rtol), float(atol), int(max_steps))
    score = jnp.where(jnp.isfinite(lps), lps, -jnp.inf)
    best = jnp.argmax(score)
    u = us[best]
    return MapResult(u, param.physical_vector(u), param.state(u), lps[best], oks[best],
                     steps[best], method, lps)
