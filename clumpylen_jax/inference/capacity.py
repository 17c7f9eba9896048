"""A fixed capacity of clumps with an active mask: the compiled pieces of `auto.py`.

The scene model is built once with `capacity` clump slots, every slot at the largest
R_e of the prior (so unlensed stamps hold any clump the fit can reach: a clump grown
beyond its build-time R_e would otherwise be cut by a square stamp). A fit varies a
Parametrization over every slot; the light of slot i is multiplied by active[i]
(0 or 1, a traced array), so adding, removing or moving a clump changes arrays only,
never shapes or static fields: `solve_batch`, `predict` and the Fisher matrix
(`uncertainty.fisher_matrix(..., active=)`) compile once
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
from .lm import blockwise, held_residuals, levenberg_marquardt
from .params import Parametrization, masked_clumps, part_blocks


def _residuals(model, data, param: Parametrization, u, active):
    return whitened_residuals(predicted_images(model, masked_clumps(param.state(u), active)), data)


def _solve(model, data, param, u0, active, rtol, max_steps):
    resid_held = held_residuals(model, data, param, active=active)
    r = levenberg_marquardt(lambda u: resid_held(u, 0), u0, max_steps, rtol,
                            blockwise(resid_held, part_blocks(param)))
    return r.u, -0.5 * r.chi2, r.success, r.n_steps


@eqx.filter_jit
def solve_batch(model, data, param, u0s, actives, rtol, max_steps):
    """Levenberg–Marquardt (`lm.py`) from each start u0s[s] with mask actives[s], one start
    after the other (lax.map): (u [S, P], ln L [S], converged [S], steps [S]). The Jacobian
    by blocks (`lm.blockwise`): the host's columns, then the clumps' with the host held.

    Not vmapped: a vmapped solve holds every start's Jacobian intermediates at once (a
    3-band 120² fit with 20 slots and 4 starts reached 10.8 GB and was killed) and runs
    every start for as many steps as the slowest; on a CPU the batch bought no speed.

    max_steps: LM steps per start, an int or ints [S] (0 for a start that only pads the
    batch to its compiled size: it costs no step and returns ln L = −inf)."""
    return jax.lax.map(lambda uas: _solve(model, data, param, *uas[:2], rtol, uas[2]),
                       (u0s, actives, _per_start(max_steps, u0s.shape[0])))


def _per_start(max_steps, n):
    return jnp.broadcast_to(jnp.asarray(max_steps, jnp.int32), (n,))


def _solve_local(model, data, param, u, idx, active, rtol, max_steps, n_host):
    """LM over the entries idx of u only (the rest held): a fixed number of columns."""
    resid_held = held_residuals(model, data, param, to_u=lambda v: u.at[idx].set(v),
                                active=active)
    blocks = (np.arange(n_host), np.arange(n_host, idx.shape[0]))
    r = levenberg_marquardt(lambda v: resid_held(v, 0), u[idx], max_steps, rtol,
                            blockwise(resid_held, blocks))
    return u.at[idx].set(r.u), -0.5 * r.chi2, r.success, r.n_steps


@eqx.filter_jit
def solve_local_batch(model, data, param, us, idxs, actives, rtol, max_steps, n_host: int):
    """`solve_batch` over the entries idxs[s] (int [S, K]) of each start only: the cost of a
    step is K Jacobian columns (host, background and a few clumps), not the capacity's.
    Each idxs[s] lists every host and background entry first (n_host of them, static), then
    clump entries: the Jacobian's two blocks (`lm.blockwise`). max_steps as in solve_batch."""
    return jax.lax.map(lambda uias: _solve_local(model, data, param, *uias[:3], rtol, uias[3],
                                                 n_host),
                       (us, idxs, actives, _per_start(max_steps, us.shape[0])))  # see solve_batch


@eqx.filter_jit
def predict(model, param, u, active):
    """Model images (with sky and fitted background) at u with the mask applied."""
    return predicted_images(model, masked_clumps(param.state(u), active))


@eqx.filter_jit
def log_likelihoods(model, data, param, u, actives):
    """ln L at one u under each mask of actives [M, N] (no refit): [M]."""
    def one(a):
        r = _residuals(model, data, param, u, a)
        return -0.5 * jnp.sum(r * r)
    return jax.lax.map(one, actives)


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
