"""A fixed capacity of clumps with an active mask: the compiled pieces of `auto.py`.

The scene model is built once with `capacity` clump slots, every slot at the largest
R_e of the prior (so unlensed stamps hold any clump the fit can reach: a clump grown
beyond its build-time R_e would otherwise be cut by a square stamp). A fit varies a
Parametrization over every slot; the light of slot i is multiplied by active[i]
(0 or 1, a traced array), so adding, removing or moving a clump changes arrays only,
never shapes or static fields: `solve_batch`, `solve_local_batch`, `predict` and the
Fisher matrix compile once per (model, data layout, capacity, batch size, number of rows
moved) and are reused at every counting step. An inactive slot has zero Jacobian columns,
and gets a zero step.

A model whose clump renderer draws any number of clumps (`Renderer.any_count`: analytic
clumps at every ray of a lensed scene, round Gaussians of an unlensed one) renders in a
local solve only the rows it moves, the other clumps' light made once per solve
(`held_light`): an LM step of a counting fit with 20 slots draws 3 clumps, not 20.
Round Gaussians add linearly, so this is the full model to rounding (tested). A lensed
model's rebinning from the lens plane to the sub-grids shares split pixels with a
minmod-limited slope, which is not linear: the held light plus the moved clumps differs
from every clump drawn at once by 2e-5 of the clump image's peak (SIS recovery scene,
103² px: at most 0.002 σ in a residual, 5e-4 of the largest Jacobian entry), far below
that rebinning's own error against the exact pixel integral (`pixels.rebin_sparse`).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..convolve import fft_shape
from ..source import Source
from .likelihood import predicted_images, whitened_residuals
from .lm import blockwise, held_residuals, levenberg_marquardt
from .params import Parametrization, clump_rows, masked_clumps, part_blocks
from .uncertainty import fisher_of, pixel_weights


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


def held_light(model, state, slots, active):
    """Band images (counts/s, no sky) of the active clumps outside the rows `slots`: what a
    fit that moves only those rows holds fixed (rendered once per solve, not per step). The
    host is left out of the source, not drawn at zero flux."""
    others = masked_clumps(state, active.at[slots].set(0.0)).render_source()
    return jax.lax.stop_gradient(model.band_images(Source(clumps=others.clumps)))


def _solve_local(model, data, param, u, idx, slots, active, rtol, max_steps, n_host):
    """LM over the entries idx of u only (the rest held): a fixed number of columns. The
    clump entries of idx belong to the rows `slots`; with a model that renders any number
    of clumps only those rows are drawn at each step, plus the held light of the others."""
    subset = model.clumps.any_count
    resid_held = held_residuals(model, data, param, to_u=lambda v: u.at[idx].set(v),
                                active=active, slots=slots if subset else None,
                                fixed=held_light(model, param.state(u), slots, active)
                                if subset else None)
    blocks = (np.arange(n_host), np.arange(n_host, idx.shape[0]))
    r = levenberg_marquardt(lambda v: resid_held(v, 0), u[idx], max_steps, rtol,
                            blockwise(resid_held, blocks))
    return u.at[idx].set(r.u), -0.5 * r.chi2, r.success, r.n_steps


@eqx.filter_jit
def solve_local_batch(model, data, param, us, idxs, slots, actives, rtol, max_steps,
                      n_host: int):
    """`solve_batch` over the entries idxs[s] (int [S, K]) of each start only: the cost of a
    step is K Jacobian columns (host, background and a few clumps), not the capacity's.
    Each idxs[s] lists every host and background entry first (n_host of them, static), then
    the entries of the clump rows slots[s] (int [S, L]): the Jacobian's two blocks
    (`lm.blockwise`). max_steps as in solve_batch."""
    return jax.lax.map(lambda a: _solve_local(model, data, param, *a[:4], rtol, a[4], n_host),
                       (us, idxs, slots, actives, _per_start(max_steps, us.shape[0])))  # see solve_batch


@eqx.filter_jit
def fisher_of_rows(model, data, param, u, entries, slots, active):
    """Fisher matrix [K, K] of the physical entries `entries` (int [K]: host, background and
    the entries of the clump rows `slots`, int [L]) at u, the other entries held: only those
    rows are rendered when the model draws any number of clumps (else every slot, masked by
    active), so its cost is that of the kept clumps, not of the capacity."""
    x = param.physical_vector(u)

    def model_vector(xs):
        state = masked_clumps(param.state_from_physical(x.at[entries].set(xs)), active)
        if model.clumps.any_count:
            state = clump_rows(state, slots)
        return jnp.concatenate([img.ravel() for img in predicted_images(model, state)])

    return fisher_of(model_vector, x[entries], lambda mu: pixel_weights(model, data, mu))


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
