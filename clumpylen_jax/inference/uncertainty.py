"""Uncertainties at an optimum: Fisher matrix, Laplace approximation, delta method.

- `fisher_matrix`: F = Jᵀ W J with J = ∂μ/∂x, the model images' Jacobian in the
  *physical* free parameters x, and W = mask/σ² — the data's variances for
  fixed-variance Gaussian data, else the expected Poisson variance μ/t (the
  Fisher matrix of the Poisson/Cash likelihood; for the model-variance Gaussian
  the term from ∂σ²/∂x is left out, negligible when counts are large). Needs no
  data at all for forecasts (`data=None`).
- `laplace`: the Hessian of −ln posterior in the unconstrained space at the
  optimum, inverted, then mapped to x by the delta method
  Cov_x = D Cov_u Dᵀ, D = diag(dx/du).

Physical-space Fisher errors stay meaningful at the edge of a transform's domain
(a clump at zero flux: dx/du = x → 0 would make delta-method errors vanish), so
they are what `fit_table` and detectability use by default.

Degenerate directions (blended clumps, a clump with zero flux whose position
the data cannot tell) make F singular. `safe_inverse` floors eigenvalues at
`rcond`·max so the covariance stays finite and reports those directions with
very large variances instead of NaN.
"""

from __future__ import annotations

from typing import Optional

import equinox as eqx
import jax
import jax.numpy as jnp

from .likelihood import ImageData, make_log_posterior, predicted_images, whitened_residuals
from .params import Parametrization, masked_clumps


class Uncertainty(eqx.Module):
    """Parameter estimates with a covariance: labels, x (physical), cov, err = √diag(cov)."""

    labels: tuple = eqx.field(static=True)
    x: jnp.ndarray
    cov: jnp.ndarray

    @property
    def err(self):
        return jnp.sqrt(jnp.diag(self.cov))

    @property
    def corr(self):
        e = self.err
        return self.cov / jnp.outer(e, e)


def safe_inverse(matrix, rcond: float = 1e-12):
    """Inverse of a symmetric positive semi-definite matrix with eigenvalues floored at rcond·max,
    after Jacobi scaling (F → D⁻¹ F D⁻¹, D² = diag F).

    The scaling matters for Fisher matrices in physical units, whose diagonals span many decades
    (a background in MJy/sr beside a flux in counts): floored unscaled, rcond·max exceeded the
    genuine eigenvalues of the less informative parameters and shrank their errors (100× in
    the test), and round-off in the eigenvectors of the null directions spread their huge
    variance into well-measured ones. Entries with no information (diag below rcond·max diag)
    keep D = 1. Null directions come back with variance ~1/rcond: huge but finite.
    """
    m = 0.5 * (matrix + matrix.T)
    diag = jnp.abs(jnp.diag(m))
    d = jnp.where(diag > rcond * jnp.max(diag), jnp.sqrt(diag), 1.0)
    ms = m / jnp.outer(d, d)
    w, v = jnp.linalg.eigh(ms)
    floor = rcond * jnp.maximum(jnp.max(jnp.abs(w)), jnp.finfo(m.dtype).tiny / rcond)
    w = jnp.maximum(w, floor)
    return ((v / w[None, :]) @ v.T) / jnp.outer(d, d)


@jax.jit
def covariance_from_fisher_u(fisher_u, dxdu):
    """Covariance of the physical x from the Fisher matrix in the unconstrained u (JᵀJ of the
    whitened residuals' Jacobian in u) and the transforms' slopes dx/du, all elementwise:
    F_x = D⁻¹ F_u D⁻¹ with D = diag(dx/du), inverted by `safe_inverse`. A zero slope (a
    transform's saturated end) is taken as the smallest float, divided by once per side:
    that entry's row of F_u is 0 there, which stays 0 (no information, a huge variance),
    where dividing by d² (which underflows to 0) made 0/0 and a NaN in every entry. One
    program (op by op, a dozen one-op compiles)."""
    d = jnp.where(dxdu != 0, dxdu, jnp.finfo(dxdu.dtype).tiny)
    return safe_inverse(fisher_u / d[:, None] / d[None, :])


def _model_vector(scene_model, param, x, active=None):
    state = param.state_from_physical(x)
    if active is not None:
        state = masked_clumps(state, active)
    return jnp.concatenate([img.ravel() for img in predicted_images(scene_model, state)])


def pixel_weights(scene_model, data: Optional[ImageData], mu):
    """1/σ² per pixel, flattened over bands, with the mask applied."""
    parts, start = [], 0
    for k, lay in enumerate(scene_model.layouts):
        size = lay.grid.shape[0] * lay.grid.shape[1]
        mu_k = mu[start:start + size]
        start += size
        mask = 1.0 if data is None else data.masks[k].ravel()
        if data is not None and data.kind == "gaussian":
            w = 1.0 / data.variances[k].ravel()
        else:
            w = lay.exptime_s / jnp.maximum(mu_k, 1e-12)
        parts.append(mask * w * jnp.ones_like(mu_k))
    return jnp.concatenate(parts)


def fisher_of(model_vector, x, weights):
    """Jᵀ W J with J = ∂model_vector/∂x at x (forward mode: one pass per parameter) and
    W = weights(model_vector(x)) per pixel (`pixel_weights`)."""
    mu = model_vector(x)
    jac = jax.jacfwd(model_vector)(x)
    return (jac * weights(mu)[:, None]).T @ jac


def fisher_of_residuals(residuals, x):
    """JᵀJ with J = ∂residuals/∂x: the Fisher matrix where the whitened residual vector is the
    likelihood's (with a diffuse light profiled out: the marginal Fisher matrix of x)."""
    jac = jax.jacfwd(residuals)(x)
    return jac.T @ jac


def _images_of_vector(scene_model, vector):
    out, start = [], 0
    for lay in scene_model.layouts:
        size = lay.grid.shape[0] * lay.grid.shape[1]
        out.append(vector[start:start + size].reshape(lay.grid.shape))
        start += size
    return tuple(out)


def fisher_for_data(scene_model, model_vector, x, data: Optional[ImageData]):
    """Fisher matrix of model_vector's parameters x for `data`: Jᵀ W J per pixel, or through
    the profiled residuals where `data` has a diffuse light."""
    if data is not None and data.diffuse is not None:
        return fisher_of_residuals(lambda xx: whitened_residuals(
            _images_of_vector(scene_model, model_vector(xx)), data), x)
    return fisher_of(model_vector, x, lambda mu: pixel_weights(scene_model, data, mu))


@eqx.filter_jit
def _fisher(scene_model, data, param, x, active):
    return fisher_for_data(scene_model, lambda xx: _model_vector(scene_model, param, xx, active),
                           x, data)


def fisher_matrix(scene_model, param: Parametrization, x=None, data: Optional[ImageData] = None,
                  active=None):
    """Fisher matrix of the physical free parameters at x (default: the template's values).

    active: None, or [N] 0/1 per clump slot (`params.masked_clumps`): inactive slots give
    zero rows and columns (the fixed-capacity fits of `capacity.py`)."""
    x = param.physical_of_state() if x is None else jnp.asarray(x)
    return _fisher(scene_model, data, param, x, None if active is None else jnp.asarray(active))


def fisher_uncertainty(scene_model, param: Parametrization, x=None,
                       data: Optional[ImageData] = None, rcond: float = 1e-12) -> Uncertainty:
    """Marginal (Cramér–Rao) covariance of the physical free parameters: F⁻¹."""
    x = param.physical_of_state() if x is None else jnp.asarray(x)
    return Uncertainty(param.labels, x, safe_inverse(fisher_matrix(scene_model, param, x, data), rcond))


@eqx.filter_jit
def _neg_log_post_hessian(scene_model, data, param, u, log_prior):
    lp = make_log_posterior(scene_model, data, param, log_prior=log_prior, jacobian=False)
    return jax.hessian(lambda v: -lp(v))(u)


def laplace(scene_model, data: ImageData, param: Parametrization, u, *, log_prior=None,
            rcond: float = 1e-12) -> Uncertainty:
    """Laplace approximation at the optimum u, mapped to physical parameters (delta method)."""
    u = jnp.asarray(u)
    cov_u = safe_inverse(_neg_log_post_hessian(scene_model, data, param, u, log_prior), rcond)
    x, d = param.physical_and_slope(u)
    return Uncertainty(param.labels, x, d[:, None] * cov_u * d[None, :])
