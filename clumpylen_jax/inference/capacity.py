"""A fixed capacity of clumps with an active mask: the compiled pieces of `auto.py`.

The scene model is built once with `capacity` clump slots, every slot at the largest
R_e of the prior (so unlensed stamps hold any clump the fit can reach: a clump grown
beyond its build-time R_e would otherwise be cut by a square stamp). A fit varies a
Parametrization over every slot; the light of slot i is multiplied by active[i]
(0 or 1, a traced array), so adding, removing or moving a clump changes arrays only,
never shapes or static fields: `solve_batch`, `predict` and `masked_fisher` compile once
per (model, data layout, capacity, batch size) and are reused at every counting step.
An inactive slot has zero Jacobian columns, and gets a zero step.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..convolve import fft_shape
from .likelihood import predicted_images, whitened_residuals
from .params import FitState, Parametrization


def masked(state: FitState, active) -> FitState:
    """The state with clump k's fluxes multiplied by active[k]."""
    flux = state.source.clumps.flux
    return eqx.tree_at(lambda s: s.source.clumps.flux, state,
                       flux * jnp.asarray(active, flux.dtype)[:, None])


def _residuals(model, data, param: Parametrization, u, active):
    return whitened_residuals(predicted_images(model, masked(param.state(u), active)), data)


def levenberg_marquardt(resid, v0, rtol, max_steps):
    """Minimise |resid(v)|² by Levenberg–Marquardt (Marquardt's diagonal scaling).

    One Jacobian (forward mode) and one trial residual per iteration: optimistix's
    LevenbergMarquardt traces the model several times per step, and compiling this loop
    is what a counting step waits for (bench_fit_auto.py). A parameter with a zero
    Jacobian column (an inactive slot) gets a zero step. Converged: an accepted step
    lowered χ² by less than rtol·χ², or no step lowers it (damping above 1e10).
    Returns (v, χ², converged, iterations).
    """
    r0 = resid(v0)

    def cond(c):
        return (c[4] < max_steps) & ~c[5]

    def body(c):
        v, r, chi2, lam, k, _ = c
        jac = jax.jacfwd(resid)(v)
        h = jac.T @ jac
        d = jnp.diag(h)
        a = h + lam * jnp.diag(jnp.where(d > 0, d, 1.0))
        step = -jnp.linalg.solve(a, jac.T @ r)
        r_new = resid(v + step)
        chi2_new = jnp.sum(r_new * r_new)
        ok = jnp.isfinite(chi2_new) & (chi2_new < chi2)
        small = ok & (chi2 - chi2_new <= rtol * chi2_new)
        lam_new = jnp.where(ok, lam * 0.3, lam * 10.0)
        done = small | (lam_new > 1e10)
        return (jnp.where(ok, v + step, v), jnp.where(ok, r_new, r), jnp.where(ok, chi2_new, chi2),
                lam_new, k + 1, done)

    init = (v0, r0, jnp.sum(r0 * r0), jnp.asarray(1e-3, r0.dtype), jnp.asarray(0), jnp.asarray(False))
    v, _, chi2, _, k, done = jax.lax.while_loop(cond, body, init)
    return v, chi2, done, k


def _solve(model, data, param, u0, active, rtol, atol, max_steps):
    v, chi2, ok, k = levenberg_marquardt(lambda u: _residuals(model, data, param, u, active), u0,
                                         rtol, max_steps)
    return v, -0.5 * chi2, ok, k


@eqx.filter_jit
def solve_batch(model, data, param, u0s, actives, rtol, atol, max_steps):
    """Levenberg–Marquardt from each start u0s[s] with mask actives[s], vmapped:
    (u [S, P], ln L [S], converged [S], steps [S])."""
    return jax.vmap(lambda u0, a: _solve(model, data, param, u0, a, rtol, atol, max_steps))(
        u0s, actives)


def _solve_local(model, data, param, u, idx, active, rtol, atol, max_steps):
    """LM over the entries idx of u only (the rest held): a fixed number of columns."""
    v, chi2, ok, k = levenberg_marquardt(
        lambda v: _residuals(model, data, param, u.at[idx].set(v), active), u[idx], rtol, max_steps)
    return u.at[idx].set(v), -0.5 * chi2, ok, k


@eqx.filter_jit
def solve_local_batch(model, data, param, us, idxs, actives, rtol, atol, max_steps):
    """`solve_batch` over the entries idxs[s] (int [S, K]) of each start only: the cost of a
    step is K Jacobian columns (host, background and a few clumps), not the capacity's."""
    return jax.vmap(lambda u, i, a: _solve_local(model, data, param, u, i, a, rtol, atol,
                                                 max_steps))(us, idxs, actives)


@eqx.filter_jit
def predict(model, param, u, active):
    """Model images (with sky and fitted background) at u with the mask applied."""
    return predicted_images(model, masked(param.state(u), active))


@eqx.filter_jit
def log_likelihoods(model, data, param, u, actives):
    """ln L at one u under each mask of actives [M, N] (no refit): [M]."""
    def one(a):
        r = _residuals(model, data, param, u, a)
        return -0.5 * jnp.sum(r * r)
    return jax.lax.map(one, actives)


@eqx.filter_jit
def masked_fisher(model, data, param, x, active):
    """Fisher matrix Jᵀ W J of the physical free parameters at x with the mask applied
    (fixed-variance Gaussian data: W = mask/σ²); inactive slots give zero rows."""
    def vec(xx):
        imgs = predicted_images(model, masked(param.state_from_physical(xx), active))
        return jnp.concatenate([i.ravel() for i in imgs])
    jac = jax.jacfwd(vec)(x)
    w = jnp.concatenate([(m / v).ravel() for m, v in zip(data.masks, data.variances)])
    return (jac * w[:, None]).T @ jac


def psf_sigma_pixels(model) -> np.ndarray:
    """Per band, the Gaussian-equivalent σ of the PSF ⊗ pixel, in detector pixels (from the
    kernel the model convolves with; √(1/12) for a band without PSF)."""
    out = []
    for k, lay in enumerate(model.layouts):
        if lay.psf_shape is None:
            out.append(np.sqrt(1 / 12))
            continue
        sub = lay.grid.subdivided(lay.oversampling)
        ky, kx = lay.psf_shape
        ker = np.fft.irfft2(np.asarray(lay.psf_ft), s=fft_shape(sub.shape, (ky, kx)))[:ky, :kx]
        ker = np.clip(ker, 0.0, None)
        yy, xx = np.mgrid[:ky, :kx]
        tot = ker.sum()
        mx, my = (ker * xx).sum() / tot, (ker * yy).sum() / tot
        var = 0.5 * (ker * ((xx - mx) ** 2 + (yy - my) ** 2)).sum() / tot
        pix = 0.0 if lay.psf_effective else 1 / 12
        out.append(float(np.sqrt(var / lay.oversampling**2 + pix)))
    return np.asarray(out)
