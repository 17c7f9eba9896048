"""Levenberg–Marquardt with one forward-mode Jacobian per step: the one solver of the
observation fits (`observations/fit.py`) and of the clump counting (`capacity.py`, `auto.py`).

Why not optimistix's LevenbergMarquardt (used elsewhere in inference/): its compiled
program holds the scene model several times (residual, linearisation, trial step), and
for a three-band model with exact pixel integrals XLA spends minutes compiling it; the
Fisher matrix then needs one more compile. Here each step evaluates the residuals at a
trial point, accepts it if χ² dropped (λ ← λ/3) or keeps the previous point (λ ← 4λ),
makes the Jacobian only at an accepted point (`jax.jacfwd(..., has_aux=True)`: one trace
of the model; a rejected trial costs one model evaluation), and proposes the next trial
from (JᵀJ + λ diag JᵀJ) δ = −Jᵀr. The Jacobian at the optimum and JᵀJ are returned, so errors
need no further compile. benchmarks/bench_optimizers.py measures both.

Converged (`success`) means one of two things, never "ran out of steps" nor "damping
maxed out while a Gauss–Newton step would still gain": an accepted step close to
Gauss–Newton (λ ≤ 1) that lowered χ² by less than rtol·χ², or damping above LAMBDA_MAX
at a point where the full Gauss–Newton step predicts a χ² gain below DECREMENT_TOL (the
minimum within rounding). A parameter with a zero Jacobian column (an inactive clump slot
of `capacity.py`) gets a zero step.

Marquardt's damping λ diag JᵀJ scales with each entry's own information, so an entry whose
column all but vanishes is not damped at all: its step −Jᵢ·r / (λ Jᵢ²) grows without bound
as Jᵢ → 0 whatever λ is. That happens in the fits: a clump whose R_e collapsed far below a
PSF sub-pixel puts all its light in one sub-pixel, and its position along one axis then moves
nothing (column ~1e-144); every trial threw that coordinate to the box edge (Δχ² +2.7e4 at
λ up to 1e55), the fit sat at LAMBDA_MAX with a Gauss–Newton gain of 15 left in the other
entries and was flagged not converged (unlensed recovery seeds 1 and 2, issue 18). So each
entry is damped by at least DAMPING_FLOOR, one unit of Fisher information in u (the
residuals are whitened, so JᵀJ is the Fisher matrix; an entry with less has σ(u) > 1, the
data hardly constrain it): such an entry takes a vanishing step, a constrained one
(Jᵢ² ≫ 1) is damped as before, and the steps near the minimum (λ → 0) are unchanged.

An entry of u that ends beyond its transform's range (`Transform.u_range`, the u its
inverse gives; u_limits) is brought back to it by one more step, whose linearisation
(made in the loop: a second copy of the Jacobian after it took S1063's compile from 31.6
to 43.5 s on one host) is what the errors come from; `success` is the fit's before that step.
A bounded parameter pushed to its bound runs on in u (an unresolved clump's R_e reached
u = −446, dx/du 1e-196) until JᵀJ underflows, and the errors of every parameter of that
clump came out wrong (`uncertainty.covariance_from_fisher_u`). Holding such entries during
the steps instead (a projected step, or the trial clipped) changed which clumps the
counting kept: the pulls mocks' jwst seed 0 lost a S/N > 10 clump
(`results/pulls_ulim_clip.md`, `pulls_ulim_held.md`).
"""

from __future__ import annotations

from typing import Optional

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .likelihood import predicted_images, whitened_residuals
from .params import CLUMP_PART, HOST_PART, entry_kinds, held, masked_clumps, only_gradient, part_blocks

LAMBDA0 = 1e-3
LAMBDA_MAX = 1e12
LAMBDA_GN = 1e-12         # damping of the "Gauss–Newton" step of the stuck test (zero columns)
DECREMENT_TOL = 1e-2      # χ² a Gauss–Newton step may still gain at a converged point
DAMPING_FLOOR = 1.0       # least diagonal the damping scales with (module doc)
RTOL = 1e-7               # default convergence: an accepted step gaining < RTOL·χ²


class LMResult(eqx.Module):
    u: jnp.ndarray
    chi2: jnp.ndarray
    jacobian: Optional[jnp.ndarray]   # d(whitened residuals)/du at u (None: `normal` given)
    jtj: jnp.ndarray                  # JᵀJ at u: the Fisher matrix in u (whitened residuals)
    n_steps: jnp.ndarray
    success: jnp.ndarray


def _propose(u, H, g, lam):
    d = jnp.maximum(jnp.diag(H), DAMPING_FLOOR)
    delta = jnp.linalg.solve(H + lam * jnp.diag(d), -g)
    delta = jnp.where(jnp.isfinite(delta), delta, 0.0)
    return u + delta, delta


def _normal_of_jacobian(r_and_j):
    """u ↦ (r, JᵀJ, Jᵀr, J): the linearisation `levenberg_marquardt` steps from, J kept."""
    def lin(u):
        r, J = r_and_j(u)
        return r, J.T @ J, J.T @ r, J
    return lin


def _jacfwd(resid):
    def r_and_j(u):
        def f(v):
            r = resid(v)
            return r, r
        J, r = jax.jacfwd(f, has_aux=True)(u)
        return r, J
    return r_and_j


def band_of_residuals(data) -> np.ndarray:
    """Band of each entry of `whitened_residuals` (its pixels, then its diffuse coefficients'
    entries, band after band): static."""
    sizes = [int(np.prod(d.shape)) + k for d, k in zip(data.images, data.n_diffuse)]
    return np.repeat(np.arange(len(sizes)), sizes)


def linear_groups(kinds, per_row: int = 0) -> tuple:
    """The per-band linear entries of `kinds` (`params.entry_kinds`) in groups, each one
    component's fluxes, one clump's fluxes or the background levels: ((path, (positions of
    a group, ...)), ...) by path. A group's row: the position // per_row where per_row > 0
    (a layout of rows alike), else the kind's own. One entry per band in a group (else its
    derivative would mix two columns of one band)."""
    out = {}
    for p, (path, _, row) in enumerate(kinds):
        if path is not None:
            out.setdefault((path, p // per_row if per_row else row), []).append(p)
    by_path = {}
    for (path, _), ps in out.items():
        assert len({kinds[p][1] for p in ps}) == len(ps), "one entry per band in a group"
        by_path.setdefault(path, []).append(tuple(ps))
    return tuple((path, tuple(gs)) for path, gs in by_path.items())


def columns_by_kind(f, v, entries, kinds, groups, bands):
    """((residuals, aux) = f(v, None), the residuals' derivatives [len(kinds), n_r] along the
    entries `entries` of v). kinds[p] = (path, band, row) marks entry p per-band linear
    (`params.entry_kinds`; path None: any other); groups: `linear_groups(kinds)`; bands:
    `band_of_residuals`. f(w, only): (residuals, aux) with every leaf of the state but
    `only` behind stop_gradient when only is a path (`params.only_gradient`).

    The other entries are pushed through the model one unit tangent each. A per-band linear
    entry (a flux, a background level) moves one band's image by its own unit image:
    pushed like the others it costs a tangent through the profile and every band's PSF
    convolution, zeros but in one band. Instead each group is one derivative along the
    sum of its entries with every other leaf held (no profile tangent; one convolution per
    band), split by band into its entries' columns: the same columns to rounding, far
    fewer pushed through the model (a S1063 counting step: 15 instead of 30 for host and
    clumps; the joint fit: 6 + 45 + 17 instead of 102)."""
    if not kinds:       # no entries (e.g. no host and no background): no columns
        out = f(v, None)
        return out, jnp.zeros((0, out[0].size), v.dtype)
    entries = jnp.asarray(entries)
    geo = [p for p, k in enumerate(kinds) if k[0] is None]
    cols = [None] * len(kinds)
    primal = None

    def push(tangents, only):
        return jax.vmap(lambda t: jax.jvp(lambda w: f(w, only), (v,), (t,)),
                        out_axes=(None, 0))(tangents)
    if geo:
        primal, (t, _) = push(jax.nn.one_hot(entries[np.asarray(geo)], v.size, dtype=v.dtype),
                              None)
        for k, p in enumerate(geo):
            cols[p] = t[k]
    bands = jnp.asarray(bands)
    for path, gs in groups:
        sums = jnp.stack([jnp.sum(jax.nn.one_hot(entries[np.asarray(g)], v.size, dtype=v.dtype), 0)
                          for g in gs])
        out, (t, _) = push(sums, path)
        primal = out if primal is None else primal
        for k, g in enumerate(gs):
            for p in g:
                cols[p] = jnp.where(bands == kinds[p][1], t[k], 0.0)
    return primal, jnp.stack(cols)


def blockwise(resid_held, blocks, kinds=None, bands=None):
    """u ↦ (resid(u), its Jacobian) by one forward-mode pass per block of entries of u.

    blocks: static int arrays partitioning u's entries (empty ones are skipped);
    resid_held(u, b): the residual with the parts of the model that block b does not move
    behind stop_gradient (`params.held`). A tangent of block b then skips the other parts'
    rendering: the host's pixels (its exact strip is ~64 incomplete gammas per pixel) are
    pushed through its own few columns, not through every clump's. The Jacobian is the same
    as one jacfwd over u (tests/test_inference_auto.py).

    Every block pushes its unit tangents from the same primal point u (not from a u
    rebuilt around the block's entries): the blocks' primal computations are then the same
    operations on the same operands, which XLA merges (common subexpressions), so the model
    is evaluated once per call, not once per block.

    kinds (per entry of u, `params.entry_kinds`) and bands (`band_of_residuals`): the
    per-band linear entries' columns are made by groups (`columns_by_kind`); resid_held
    then takes (u, b, only).
    """
    blocks = [(b, np.asarray(idx, int)) for b, idx in enumerate(blocks) if np.size(idx)]
    inverse = np.argsort(np.concatenate([idx for _, idx in blocks]))

    def r_and_j(u):
        cols = []
        for b, idx in blocks:
            if kinds is not None:
                k_b = tuple(kinds[i] for i in idx)
                (r, _), T = columns_by_kind(
                    lambda v, only, b=b: (resid_held(v, b, only), ()), u, idx, k_b,
                    linear_groups(k_b), bands)
                cols.append(T.T)
                continue
            basis = jnp.eye(u.size, dtype=u.dtype)[idx]     # the block's unit tangents
            push = lambda t, b=b: jax.jvp(lambda v: resid_held(v, b), (u,), (t,))  # noqa: E731
            r, J = jax.vmap(push, out_axes=(None, 1))(basis)
            cols.append(J)
        return r, jnp.concatenate(cols, axis=1)[:, inverse]
    return r_and_j


def held_residuals(scene_model, data, param, active=None):
    """resid_held(v, b) for `blockwise`: the whitened residuals at u = v with the clumps held
    for block 0 (host and background entries) and the host held for block 1 (clump entries:
    `params.part_blocks`); active: a clump mask or None."""
    other = (CLUMP_PART, HOST_PART)

    def resid_held(u, b, only=None):
        state = param.state(u)
        if active is not None:
            state = masked_clumps(state, active)
        if only is not None:    # one per-band linear leaf's derivative (`columns_by_kind`)
            state = only_gradient(state, only)
        return whitened_residuals(predicted_images(scene_model, held(state, other[b])), data)
    return resid_held


def levenberg_marquardt(resid, u0, max_steps: int = 200, rtol: float = RTOL,
                        r_and_j=None, normal=None, u_limits=None) -> LMResult:
    """Minimise |resid(u)|² over u from u0 (module doc). Traceable (under vmap its branch on
    acceptance runs both sides: `capacity.solve_batch` maps starts one after the other).
    resid decides each trial (it should cost one model evaluation); the linearisation is
    made at accepted trials only.
    max_steps: an int or a traced integer (0: no step, u0 returned with χ² = inf).
    r_and_j: u ↦ (resid(u), Jacobian) when given (`blockwise`), else one jacfwd of resid.
    normal: u ↦ (resid(u), JᵀJ, Jᵀr) instead of r_and_j, for a caller that builds the normal
    equations by blocks without one J (`capacity.solve_local_batch`); the result's
    jacobian is then None. u_limits: (lo, hi) [n] the result is brought back within
    (`Parametrization.u_limits`: where JᵀJ in u keeps the Fisher matrix in x), or None;
    that step counts in n_steps, which can then be max_steps + 1."""
    lo, hi = (jnp.asarray(a, u0.dtype) for a in
              ((-jnp.inf, jnp.inf) if u_limits is None else u_limits))
    lin = (lambda u: (*normal(u), None)) if normal is not None else \
        _normal_of_jacobian(r_and_j or _jacfwd(resid))

    n = u0.size
    r_shape = jax.eval_shape(resid, u0)
    zero_j = None if normal is not None else jnp.zeros((int(np.prod(r_shape.shape)), n), u0.dtype)
    init = dict(u=u0, H=jnp.zeros((n, n), u0.dtype), g=jnp.zeros(n, u0.dtype), J=zero_j,
                chi2=jnp.asarray(jnp.inf, u0.dtype), trial=u0, lam=jnp.asarray(LAMBDA0, u0.dtype),
                step=jnp.asarray(0), done=jnp.asarray(False), ok=jnp.asarray(False),
                back=jnp.asarray(False))

    def cond(s):
        return ((s["step"] < max_steps) | s["back"]) & ~s["done"]

    def body(s):
        # the residuals alone decide the trial; the Jacobian is made only where it is
        # accepted (a rejected trial costs one model evaluation, not its derivatives).
        # A trial that brings u back within its limits ("back", module doc) is taken
        # whatever its χ², for its linearisation: the one the errors are made from
        c_t = jnp.sum(resid(s["trial"]) ** 2)
        accept = jnp.isfinite(c_t) & ((c_t <= s["chi2"]) | s["back"])
        # converged: a step close to Gauss–Newton (not one shrunk by a large λ after
        # rejections, which gains little anywhere) that gained almost nothing
        small = accept & ~s["back"] & (s["chi2"] - c_t <= rtol * c_t) & (s["lam"] <= 1.0)
        u, chi2 = jnp.where(accept, s["trial"], s["u"]), jnp.where(accept, c_t, s["chi2"])
        H, g, J = jax.lax.cond(accept, lambda: lin(s["trial"])[1:],
                               lambda: (s["H"], s["g"], s["J"]))
        lam = jnp.where(accept, s["lam"] / 3.0, s["lam"] * 4.0)
        trial, _ = _propose(u, H, g, lam)
        stuck = lam > LAMBDA_MAX
        # stuck at the largest damping: converged only if a full Gauss–Newton step would
        # gain < DECREMENT_TOL in χ² (at the minimum within rounding), else a failure
        _, gn = _propose(u, H, g, LAMBDA_GN)
        at_min = -2.0 * jnp.dot(g, gn) < DECREMENT_TOL
        end = small | stuck | s["back"] | (s["step"] + 1 >= max_steps)
        u_in = jnp.clip(u, lo, hi)
        back = end & ~s["back"] & jnp.any((u < lo) | (u > hi))
        return dict(u=u, H=H, g=g, J=J, chi2=chi2, trial=jnp.where(back, u_in, trial), lam=lam,
                    step=s["step"] + 1, done=end & ~back,
                    ok=jnp.where(s["back"], s["ok"], small | (stuck & at_min)), back=back)

    s = jax.lax.while_loop(cond, body, init)
    return LMResult(s["u"], s["chi2"], s["J"], s["H"], s["step"], s["ok"])


@eqx.filter_jit
def lm_fit(scene_model, data, param, u0, max_steps: int = 200, rtol: float = RTOL) -> LMResult:
    """`levenberg_marquardt` of the whitened residuals of `data` over param's u from u0,
    the Jacobian by blocks (host and background; clumps: `blockwise`)."""
    resid_held = held_residuals(scene_model, data, param)
    # fluxes and background levels by groups (`columns_by_kind`): the same Jacobian
    kinds = entry_kinds(param, np.arange(param.size))
    return levenberg_marquardt(lambda u: resid_held(u, 0), u0, max_steps, rtol,
                               blockwise(resid_held, part_blocks(param), kinds,
                                         band_of_residuals(data)), u_limits=param.u_limits())
