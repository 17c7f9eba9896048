"""Upper limits on the sizes of unresolved clumps, from a profile of χ² in R_e.

A clump much smaller than the PSF fits an R_e at or near the prior's lower bound, and its
Fisher error there says nothing (σ(R_e) > R_e: flag `size_unresolved`): the data bound its
size from above only. The limit is where χ², minimised over the clump's flux in every band
with everything else held at the optimum, has risen by `DELTA_CHI2_UL` above its value at
the fitted R_e. The flux enters the images linearly (also through a profiled diffuse light,
itself a linear solve), so its minimum is exact (the diffuse light's ridge term aside,
1e-6 of its normal matrix's mean diagonal; and the flux may go negative) and needs two
images per trial R_e: the clump dark and at unit flux. Holding the position and the host makes the limit a little
tight: refitting them too moved χ² at the limit by 2.54–2.59 rather than 2.71 on S/N 6–18
point sources (tests/test_observations.py). R_e is bisected in log between the fitted value
and the prior's upper bound, each trial one call of the program that renders a state
outside a fit (`likelihood.chi2_and_images`, compiled already): no compile.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from .likelihood import chi2_and_images

DELTA_CHI2_UL = 2.706   # one-sided 95 % upper limit: the 90 % point of χ² with 1 dof
RTOL = 0.02             # relative precision of the limit in R_e


def flux_profiled_gain(unit_images, dark_images, data_images, weights) -> float:
    """χ² of the clump dark less χ² with its best flux in every band: Σ_b (Σ w c r)² / Σ w c²,
    c the clump's light at unit flux and r the data less the dark model, per band (arrays of
    one shape each; weights 1/σ² times the mask); NaN where an image is not finite."""
    gain = 0.0
    for u, m, d, w in zip(unit_images, dark_images, data_images, weights):
        c, r = u - m, d - m
        norm = float(np.sum(w * c * c))
        if not np.isfinite(norm):
            return float("nan")
        if norm > 0:
            gain += float(np.sum(w * c * r)) ** 2 / norm
    return gain


def re_upper_limit(model, data, state, slot: int, re_max_arcsec: float, *,
                   delta_chi2: float = DELTA_CHI2_UL, rtol: float = RTOL) -> float:
    """Upper limit on the R_e [arcsec] of clump row `slot` of `state` (a FitState that
    `model` renders, gaussian `data` of `likelihood.make_data`): the R_e above its fitted one
    where χ² profiled over the clump's fluxes rises by delta_chi2 (module doc), to rtol;
    re_max_arcsec (the fit's upper bound) where it never does below that, or where R_e
    is there already; NaN where a render is not finite (no limit rather than a tight one)."""
    clumps = state.source.clumps
    re_fit = float(clumps.re_arcsec[slot])
    d = [np.asarray(x) for x in data.images]
    with np.errstate(divide="ignore", invalid="ignore"):   # masked pixels: weight 0 whatever σ²
        w = [np.where(np.asarray(m) > 0, np.asarray(m) / np.asarray(v), 0.0)
             for m, v in zip(data.masks, data.variances)]

    def images(re_arcsec, flux):
        st = eqx.tree_at(lambda s: (s.source.clumps.re_arcsec, s.source.clumps.flux), state,
                         (clumps.re_arcsec.at[slot].set(re_arcsec),
                          clumps.flux.at[slot].set(jnp.full(clumps.flux.shape[1:], flux))))
        return [np.asarray(m) for m in chi2_and_images(model, data, st)[1]]

    if re_fit >= re_max_arcsec:
        return float(re_max_arcsec)
    dark = images(re_fit, 0.0)

    def gain(log_re):
        return flux_profiled_gain(images(float(np.exp(log_re)), 1.0), dark, d, w)

    lo, hi = np.log(re_fit), np.log(re_max_arcsec)
    best, g = gain(lo), gain(hi)
    if not np.isfinite(best + g):
        return float("nan")
    best = max(best, g)      # a trial better than the fitted R_e becomes the reference
    if best - g < delta_chi2:
        return float(re_max_arcsec)
    while hi - lo > np.log1p(rtol):
        mid = 0.5 * (lo + hi)
        g = gain(mid)
        if not np.isfinite(g):
            return float("nan")
        best = max(best, g)
        if best - g < delta_chi2:
            lo = mid
        else:
            hi = mid
    return float(np.exp(hi))


def re_upper_limits(model, data, state, slots, re_max_arcsec) -> np.ndarray:
    """[len(slots)] `re_upper_limit` of each clump row in `slots` (ints; −1: none, NaN)."""
    return np.array([re_upper_limit(model, data, state, int(i), re_max_arcsec) if i >= 0
                     else np.nan for i in np.asarray(slots, int)], float)
