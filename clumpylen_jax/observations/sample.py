"""Posterior sampling of a fit of observations (`[fit] method = "nuts" | "emcee"`, or `--method`).

    sample_observed_fit(fit, method, options, seed) -> SampledFit

The chains start at the joint fit's optimum (found from the data alone, never from any
truth) and sample every parameter that fit moved (host, clumps, background) under the same
bounded transforms, with a prior flat in the physical parameters (`inference.mcmc`): a
clump's position box and its R_e range are the prior's support. A diffuse light
(`fit.diffuse_spacing_arcsec`) stays profiled out: each draw sees its best diffuse light,
so the errors are conditional on it, as the Fisher errors are marginalised over it linearly.

- Position angles, free and unbounded in the MAP fit, are bounded to ±π/2 around the
  optimum here (`_angles_bounded`): an ellipse at PA and PA + π is the same, so with a flat
  prior on the whole line the posterior is improper, and where the host's shape is poorly
  measured the chains walked over several periods (R̂ 1.8 on the two-band mock).
- NUTS (blackjax) moves in coordinates whitened by the optimum's covariance
  (`mcmc.whitening_scale`, capped in u where a parameter sits at a bound); without that the
  S1063 fit (102 parameters) diverged at every step, with it ~15 leapfrog steps a draw.
  Where that covariance misdescribes the posterior (`mcmc.laplace_mismatch`, one density
  evaluation 1σ away: 1.3 on S1063, ~400 on RXJ1131 with its diffuse light, against 1 for
  a Gaussian; above MISMATCH_WARN), the metric is the inverse Hessian of the sampled
  density instead (`mcmc.hessian_scale`), when its check is nearer 1; the command warns
  when the chosen one is still above MISMATCH_WARN. summary.json: "metric", both checks.
- emcee's walkers (2 × parameters + 2) start in a ball of a tenth of those widths
  (`mcmc.sample_from_optimum`, shared with the fits of mock images).

Reported: the posterior median of every parameter (the state drawn in `residuals_*.fits`)
and the samples' covariance, which the answers propagate as they do the Fisher one
(magnitudes, sizes, positions, β; masses through the SED grid with the posterior's flux
errors). `chains.npz` holds the draws; summary.json's "sampler" the diagnostics.
"""

from __future__ import annotations

import dataclasses
import re
import time

import numpy as np

from ..inference.mcmc import (ChainResult, hessian_scale, laplace_mismatch, posterior_median,
                              sample_from_optimum, whitening_scale)
from ..inference.params import FreeLeaf, Parametrization, _getter
from ..inference.transforms import Transform
from .fit import ObservedFit, _chi2

MISMATCH_WARN = 10.0   # `laplace_mismatch` above this: the progress output warns
RHAT_MAX = 1.1     # split R̂ above this for one of a clump's parameters: flag 1 (not converged)


@dataclasses.dataclass
class SampledFit:
    """The fit re-centred on the posterior (median state, sample covariance), its chains, and
    the diagnostics summary.json reports under "sampler"."""

    fit: ObservedFit
    chains: ChainResult
    summary: dict

    def describe(self) -> str:
        """One line for the command's progress output."""
        d = self.summary
        num = lambda v, f: "n/a" if v is None else format(v, f)  # noqa: E731
        line = (f"{d['method']}: {d['seconds']:.0f} s, acceptance {d['acceptance']:.2f}, "
                f"R̂ ≤ {num(d['rhat_max'], '.3f')} ({d['rhat_max_parameter']}), "
                f"ESS ≥ {num(d['ess_min'], '.0f')} ({d['ess_min_parameter']})")
        if not d["converged"]:
            line += (f"; chains NOT mixed (R̂ > {d['rhat_limit']}): flag 1 on the clumps "
                     "concerned; run longer (fit.sampler_warmup, fit.sampler_samples)")
        return line


def sample_observed_fit(fit: ObservedFit, method: str, options, seed: int,
                        progress=None) -> SampledFit:
    """Sample the posterior of `fit` (`fit_observations`' result) with "nuts" or "emcee";
    options: the scene's FitOptions (sampler_chains, sampler_warmup, sampler_samples);
    progress: a callable for a warning before a run that the metric check expects to be
    slow (`mcmc.laplace_mismatch` above MISMATCH_WARN), or None."""
    t0, c0 = time.perf_counter(), time.process_time()
    param = _angles_bounded(fit.param, fit.state)
    u0 = param.unconstrained_vector(param.physical_of_state(fit.state))
    if method == "nuts":
        sizes = dict(n_chains=options.sampler_chains, n_warmup=options.sampler_warmup,
                     n_samples=options.sampler_samples)
    else:
        sizes = dict(n_walkers=2 * u0.size + 2, burn=options.sampler_warmup,
                     n_steps=options.sampler_warmup + options.sampler_samples)
    scale = whitening_scale(param, u0, fit.uncertainty.cov)
    mismatch = fisher_mismatch = laplace_mismatch(fit.model, fit.data, param, u0, scale, seed)
    metric = "fisher"
    if not mismatch <= MISMATCH_WARN:   # the Hessian of the sampled density instead
        if progress:
            progress(f"the Fisher metric misdescribes the posterior (check {mismatch:.0f}, 1 "
                     "for a Gaussian): computing the Hessian of the sampled density")
        h_scale = hessian_scale(fit.model, fit.data, param, u0, fit.uncertainty.cov)
        h_mismatch = laplace_mismatch(fit.model, fit.data, param, u0, h_scale, seed)
        if _closer_to_gaussian(h_mismatch, mismatch):
            scale, mismatch, metric = h_scale, h_mismatch, "hessian"
    if progress and not mismatch <= MISMATCH_WARN:
        progress(f"the optimum's covariance misdescribes the posterior (Δln p {mismatch:.0f}× a "
                 "Gaussian's at 1σ): expect tiny NUTS steps, a long run and chains that do "
                 "not mix (R̂ and flag 1 will say)")
    chains = sample_from_optimum(method, fit.model, fit.data, param, u0, scale, seed=seed,
                                 **sizes)
    state, unc = posterior_median(chains, param)
    _, images = _chi2(fit.model, fit.data, state)
    seconds = time.perf_counter() - t0
    record = dict(stage=method, n_draws=int(chains.flat_x().shape[0]), seconds=round(seconds, 3),
                  cpu_seconds=round(time.process_time() - c0, 3))
    timings = {**fit.timings_s, "sampler": round(seconds, 3)}
    sampled = dataclasses.replace(fit, state=state, uncertainty=unc, images=tuple(images),
                                  steps=fit.steps + [record], timings_s=timings,
                                  clump_unconverged=unmixed_clumps(chains, fit.n_clumps))
    summary = diagnostics(chains, options, seconds)
    summary.update(laplace_mismatch=mismatch, metric=metric,
                   laplace_mismatch_fisher=fisher_mismatch)
    return SampledFit(sampled, chains, summary)


def _closer_to_gaussian(check: float, other: float) -> bool:
    """True where `laplace_mismatch` value `check` is nearer 1 (a unit Gaussian) than `other`
    by |ln check|: a metric far too narrow (check ≪ 1) is no better than one too wide; a
    non-positive or non-finite check never wins."""
    if not (np.isfinite(check) and check > 0):
        return False
    return not (np.isfinite(other) and other > 0) or abs(np.log(check)) < abs(np.log(other))


def unmixed_clumps(chains: ChainResult, n_clumps: int, rhat_max: float = RHAT_MAX) -> np.ndarray:
    """[n_clumps] True where split R̂ of one of the clump's parameters ("clumps.<field>[i…]")
    exceeds rhat_max (or is not finite)."""
    out = np.zeros(n_clumps, bool)
    for label, r in zip(chains.labels, np.asarray(chains.rhat, float)):
        m = re.match(r"clumps\.\w+\[(\d+)", label)
        if m and not (np.isfinite(r) and r <= rhat_max):
            out[int(m.group(1))] = True
    return out


def _angles_bounded(param: Parametrization, state) -> Parametrization:
    """`param` with each free position angle (a leaf "….pa_rad" with the identity transform)
    bounded to (a − π/2, a + π/2) around its value a in `state`: every orientation once."""
    leaves = []
    for leaf in param.leaves:
        if leaf.path.endswith("pa_rad") and leaf.transform.kind == "identity":
            a = np.ravel(np.asarray(_getter(leaf.path)(state), float))[list(leaf.index)]
            leaf = FreeLeaf(leaf.path, leaf.shape, leaf.index, Transform(
                "bounded", tuple(float(v) for v in a - np.pi / 2),
                tuple(float(v) for v in a + np.pi / 2)))
        leaves.append(leaf)
    return Parametrization(state, tuple(leaves))


def diagnostics(chains: ChainResult, options, seconds: float) -> dict:
    """summary.json's "sampler": settings, acceptance, divergences, worst R̂ and ESS (and which
    parameter), and what the reported values are."""
    ess = np.asarray(chains.ess, float)
    rhat = np.asarray(chains.rhat, float)
    worst_rhat = int(np.nanargmax(rhat)) if np.any(np.isfinite(rhat)) else None
    low_ess = int(np.nanargmin(ess)) if np.any(np.isfinite(ess)) else None
    n_chains, n_draws = chains.samples_x.shape[:2]
    return {
        "method": chains.method, "chains": int(n_chains), "draws_per_chain": int(n_draws),
        "warmup": int(options.sampler_warmup), "acceptance": float(chains.acceptance),
        "divergent": int(chains.n_divergent),
        "rhat_max": None if worst_rhat is None else float(rhat[worst_rhat]),
        "rhat_max_parameter": None if worst_rhat is None else chains.labels[worst_rhat],
        "ess_min": None if low_ess is None else float(ess[low_ess]),
        "ess_min_parameter": None if low_ess is None else chains.labels[low_ess],
        "converged": bool(worst_rhat is not None and rhat[worst_rhat] <= RHAT_MAX),
        "rhat_limit": RHAT_MAX,
        "seconds": round(seconds, 3),
        "values": "posterior median; errors: the samples' standard deviation (covariance "
                  "propagated to magnitudes, sizes, masses)",
    }
