"""A fixed capacity of clumps with an active mask: the compiled pieces of `auto.py`.

The scene model is built once with `capacity` clump slots, every slot at the largest
R_e of the prior (so unlensed stamps hold any clump the fit can reach: a clump grown
beyond its build-time R_e would otherwise be cut by a square stamp). A fit varies a
Parametrization over every slot; the light of slot i is multiplied by active[i]
(0 or 1, a traced array), so adding, removing or moving a clump changes arrays only,
never shapes or static fields: `solve_batch`, `solve_local_batch` and the rendering of a
state (`likelihood.chi2_and_images`) compile once per (model, data layout, capacity, batch
size) and are reused at every counting step (the errors come from the final local
solve's JᵀJ: no Fisher program); `solve_local_batch` takes any number of rows moved up to the
capacity (padded, `_local_normal`), so the counting steps and the final refit of every
kept clump share one program. An inactive slot has zero Jacobian columns, and gets a
zero step.

A model whose clump renderer draws any number of clumps (`Renderer.any_count`: analytic
clumps at every ray of a lensed scene, round Gaussians of an unlensed one) renders in a
local solve only the rows it moves, the other clumps' light made once per solve
(`held_light`): an LM step of a counting fit with 20 slots draws 3 clumps, not 20.
Round Gaussians add linearly, so this is the full model to rounding (tested). A lensed
model's rebinning from the lens plane to the sub-grids shares split pixels with a
minmod-limited slope, which is not linear: the held light plus the moved clumps (each
chunk of rows of `_local_normal` drawn apart) differs from every clump drawn at once by
2e-5 of the clump image's peak (SIS recovery scene, 103² px: at most 0.002 σ in a
residual, 5e-4 of the largest Jacobian entry), far below that rebinning's own error
against the exact pixel integral (`pixels.rebin_sparse`).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..convolve import fft_shape
from ..psf import PSF, fwhm_arcsec
from ..source import Source
from .likelihood import whitened_residuals
from .lm import (band_of_residuals, blockwise, columns_by_kind, held_residuals, linear_groups,
                 levenberg_marquardt)
from .params import clump_rows, masked_clumps, only_gradient, part_blocks

FWHM_PER_SIGMA = 2.0 * np.sqrt(2.0 * np.log(2.0))


def _solve(model, data, param, u0, active, rtol, max_steps):
    resid_held = held_residuals(model, data, param, active=active)
    r = levenberg_marquardt(lambda u: resid_held(u, 0), u0, max_steps, rtol,
                            blockwise(resid_held, part_blocks(param)), u_limits=param.u_limits())
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
    """Band images (counts/s, no sky) of the active clumps outside the rows `slots` (entries
    equal to the capacity are padding): what a fit that moves only those rows holds fixed
    (rendered once per solve, not per step). The host is left out of the source, not drawn
    at zero flux."""
    others = masked_clumps(state, active.at[slots].set(0.0, mode="drop")).render_source()
    return jax.lax.stop_gradient(model.band_images(Source(clumps=others.clumps)))


def _rows_source(model, state, rows, keep):
    """The clumps of the rows `rows` (int [W]) alone, rows where keep (bool [W]) is False
    dark: the light one chunk of a local solve moves. A model that draws any number of
    clumps draws just these rows; another draws every slot, the others dark."""
    if model.clumps.any_count:
        cl = clump_rows(state, jnp.where(keep, rows, 0)).source.clumps
        return Source(clumps=eqx.tree_at(lambda c: c.flux, cl, cl.flux * keep[:, None]))
    zero = jnp.zeros_like(state.source.clumps.re_arcsec)
    on = zero.at[rows].max(keep.astype(zero.dtype), mode="drop")
    return Source(clumps=masked_clumps(state, on).source.clumps)


def _host_images(model, source, like):
    """Band images with sky of the host alone (of the sky alone for a source without one)."""
    if source.bulge is None and source.disk is None:
        return tuple(lay.with_sky(jnp.zeros_like(x)) for lay, x in zip(model.layouts, like))
    return model.noiseless(Source(bulge=source.bulge, disk=source.disk))


def _tangents(f, v, first, width):
    """f(v) and its derivatives along the entries first … first + width − 1 of v (first
    traced): (primal, tangents with a leading axis of width)."""
    basis = jax.nn.one_hot(first + jnp.arange(width), v.size, dtype=v.dtype)
    return jax.vmap(lambda t: jax.jvp(f, (v,), (t,)), out_axes=(None, 0))(basis)


def _normal_by_blocks(r, T_host, T_chunks, n_chunks):
    """(JᵀJ, Jᵀr) of Jᵀ = [T_host; T_chunks[0]; T_chunks[1]; …] (rows: a column's derivative)
    from its blocks, the chunks from n_chunks on (zero columns) skipped: [K, K], [K] with
    K = h + C·w."""
    h, (n_c, w, _) = T_host.shape[0], T_chunks.shape
    put = jax.lax.dynamic_update_slice
    H = jnp.zeros((h + n_c * w,) * 2, r.dtype).at[:h, :h].set(T_host @ T_host.T)
    g = jnp.zeros(h + n_c * w, r.dtype).at[:h].set(T_host @ r)

    def row(c, Hg):
        H, g = Hg
        T_c, o = T_chunks[c], h + c * w
        hc = T_host @ T_c.T
        H = put(put(H, hc, (0, o)), hc.T, (o, 0))

        def col(c2, H):
            b = T_c @ T_chunks[c2].T
            return put(put(H, b, (o, h + c2 * w)), b.T, (h + c2 * w, o))
        return jax.lax.fori_loop(0, c + 1, col, H), put(g, T_c @ r, (o,))
    return jax.lax.fori_loop(0, n_chunks, row, (H, g))


def _local_normal(model, data, param, u, idx, slots, active, fixed, n_host: int, chunk: int,
                  kinds=None):
    """(v ↦ (residuals, JᵀJ, Jᵀr), v ↦ residuals) of the fit over the entries idx of u (the
    rest held).

    Layout (`auto._solve_layout`): idx = n_host host and background entries, then per row
    of slots (int [C·chunk]) its clump entries, as many per row; the entry u.size (a
    column that moves nothing) and the row `capacity` pad. The clump rows are drawn
    `chunk` at a time, only the chunks holding a row (a fori_loop with a traced count),
    each with the derivatives along its own columns, the host's and the other chunks'
    light held; then the host with its columns, every clump's light held. So the program
    is the same for a counting step (one chunk) and the final refit of every kept clump
    (C chunks at most: compiled once), and a step costs the chunks it uses: padding
    columns are never pushed through the model, and their blocks of JᵀJ never formed.
    fixed: the light of the active clumps outside slots (`held_light`).
    kinds: None, or (host kinds [n_host], kinds of a row's entries [width / chunk]) as
    `params.entry_kinds` gives them: the per-band linear entries' columns (fluxes,
    background) are then made by groups (`lm.columns_by_kind`; a row's fluxes one group)."""
    cap = active.shape[0]
    n_c = slots.size // chunk
    width = (idx.size - n_host) // n_c
    n_chunks = (jnp.sum(slots < cap) + chunk - 1) // chunk

    def state_of(v, only=None):
        st = masked_clumps(param.state(u.at[idx].set(v, mode="drop")), active)
        return st if only is None else only_gradient(st, only)

    def chunk_residuals(c):
        """The chunk's light and its residuals alone (whose derivatives are the residuals')."""
        rows = jax.lax.dynamic_slice(slots, (c * chunk,), (chunk,))

        def f(w, only=None):
            light = model.band_images(_rows_source(model, state_of(w, only), rows, rows < cap))
            return whitened_residuals(light, data), light
        return f

    def host_residuals(light):
        def f(w, only=None):
            st = state_of(w, only)
            mu = _host_images(model, st.source, light)
            return whitened_residuals(tuple(m + b + l for m, b, l in zip(
                mu, st.background_counts_per_s, light)), data)
        return f

    if kinds is not None:
        host_kinds, row_kinds = kinds
        chunk_kinds = tuple(row_kinds) * chunk
        bands = band_of_residuals(data)
        host_groups = linear_groups(host_kinds)
        chunk_groups = linear_groups(chunk_kinds, len(row_kinds))

        def chunk_tangents(c, v):
            (_, l_c), t_c = columns_by_kind(chunk_residuals(c), v,
                                            n_host + c * width + jnp.arange(width), chunk_kinds,
                                            chunk_groups, bands)
            return l_c, t_c

        def host_tangents(light, v):
            f = host_residuals(light)
            (r, _), t = columns_by_kind(lambda w, only: (f(w, only), ()), v, np.arange(n_host),
                                        host_kinds, host_groups, bands)
            return r, t
    else:
        def chunk_tangents(c, v):
            (_, l_c), (t_c, _) = _tangents(chunk_residuals(c), v, n_host + c * width, width)
            return l_c, t_c

        def host_tangents(light, v):
            return _tangents(host_residuals(light), v, 0, n_host)

    def residual(v):
        """The residuals alone (what decides a trial), the light summed as `normal` sums it."""
        def add_rows(c, light):
            rows = jax.lax.dynamic_slice(slots, (c * chunk,), (chunk,))
            l_c = model.band_images(_rows_source(model, state_of(v), rows, rows < cap))
            return tuple(a + b for a, b in zip(light, l_c))
        return host_residuals(jax.lax.fori_loop(0, n_chunks, add_rows, tuple(fixed)))(v)

    def normal(v):
        def add_chunk(c, carry):
            light, T_chunks = carry
            l_c, t_c = chunk_tangents(c, v)
            return tuple(a + b for a, b in zip(light, l_c)), T_chunks.at[c].set(t_c)
        n_r = sum(f.size for f in fixed) + sum(data.n_diffuse)   # whitened_residuals' length
        T0 = jnp.zeros((n_c, width, n_r), v.dtype)
        light, T_chunks = jax.lax.fori_loop(0, n_chunks, add_chunk, (tuple(fixed), T0))
        r, T_host = host_tangents(light, v)
        H, g = _normal_by_blocks(r, T_host, T_chunks, n_chunks)
        return r, H, g
    return normal, residual


def _solve_local(model, data, param, u, idx, slots, active, rtol, max_steps, n_host, chunk,
                 kinds=None):
    """LM over the entries idx of u only (`_local_normal`)."""
    normal, residual = _local_normal(model, data, param, u, idx, slots, active,
                                     held_light(model, param.state(u), slots, active), n_host,
                                     chunk, kinds)
    v0 = u.at[idx].get(mode="fill", fill_value=0.0)
    lo, hi = (jnp.asarray(a).at[idx].get(mode="fill", fill_value=f)
              for a, f in zip(param.u_limits(), (-jnp.inf, jnp.inf)))
    r = levenberg_marquardt(residual, v0, max_steps, rtol, normal=normal, u_limits=(lo, hi))
    return u.at[idx].set(r.u, mode="drop"), -0.5 * r.chi2, r.success, r.n_steps, r.jtj


@eqx.filter_jit
def solve_local_batch(model, data, param, us, idxs, slots, actives, rtol, max_steps,
                      n_host: int, chunk: int, kinds=None):
    """`solve_batch` over the entries idxs[s] (int [S, K]) of each start only: the cost of a
    step is that of the columns used (host, background and the clumps of the rows slots[s],
    int [S, C·chunk]), not the capacity's. Layout and padding: `_local_normal`; one compiled
    program for any number of rows up to C·chunk. max_steps as in solve_batch. kinds
    (static): the layout's per-band linear entries, `_local_normal`. Returns solve_batch's
    four and JᵀJ [S, K, K] at each optimum in idxs' order (the Fisher matrix in u of those
    entries: zero rows and columns at padding), so that errors need no program of their own."""
    return jax.lax.map(lambda a: _solve_local(model, data, param, *a[:4], rtol, a[4], n_host,
                                              chunk, kinds),
                       (us, idxs, slots, actives, _per_start(max_steps, us.shape[0])))  # see solve_batch


def psf_sigma_pixels(model) -> np.ndarray:
    """Per band, the Gaussian-equivalent σ of the PSF core ⊗ pixel, in detector pixels:
    FWHM / 2.3548 from the area above half maximum of the kernel the model convolves with
    (`psf.fwhm_arcsec`), pixel variance 1/12 added unless the PSF is effective; √(1/12) for a
    band without PSF. Not the second moments: a real PSF's wings dominate those (S1063's
    WebbPSF F150W: 5.3 px against a core of 0.9 px), and the seeding's matched filter and
    size deconvolution are for the core. For a Gaussian the two are the same."""
    out = []
    for lay in model.layouts:
        if lay.psf_shape is None:
            out.append(np.sqrt(1 / 12))
            continue
        sub = lay.sub_grid
        ky, kx = lay.psf_shape
        ker = np.fft.irfft2(np.asarray(lay.psf_ft), s=fft_shape(sub.shape, (ky, kx)))[:ky, :kx]
        ker = np.clip(ker, 0.0, None)
        sigma_sub = fwhm_arcsec(PSF(ker / ker.sum(), 1.0, False)) / FWHM_PER_SIGMA
        pix = 0.0 if lay.psf_effective else 1 / 12
        out.append(float(np.sqrt((sigma_sub / lay.oversampling) ** 2 + pix)))
    return np.asarray(out)
