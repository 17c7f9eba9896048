"""`run_fit`: the end-to-end fit the CLI calls (`clumpylen fit`).

    run_fit(scene_model, source_start, images, variances=None, *, free=None,
            method="map", likelihood="gaussian", mask=None, zeropoints_ab=None,
            background=False, n_starts=1, seed=0, mcmc=None, out_dir=None) -> FitRun

1. data from `images` (dict band → array or FITS path), `variances`, `mask`;
2. MAP fit (Levenberg–Marquardt for fixed-variance Gaussian data, else BFGS;
   vmapped multi-start when n_starts > 1) from `source_start`;
3. errors: Fisher matrix in physical parameters at the optimum ("map"), or
   posterior median and standard deviation from emcee / NUTS started at the MAP;
4. if out_dir: `fit.ecsv` (fit_table), `chains.npz` (sampled methods: samples_x,
   samples_u, log_posterior, labels, acceptance, ess, rhat, autocorr_time) and
   `residuals_<band>.fits` (extensions DATA, MODEL, RESIDUAL, CHI; counts/s), all
   written atomically.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Optional

import jax
import numpy as np

from ..errors import require
from .catalog import errors_state, fit_table, host_meta
from .likelihood import make_data, predicted_images
from .mcmc import ChainResult, posterior_median, sample_from_optimum, whitening_scale
from .optimize import MapResult, fit_map, fit_map_multistart
from .params import FitState, default_free, make_state, parametrize
from .uncertainty import Uncertainty, fisher_uncertainty


@dataclasses.dataclass
class FitRun:
    """What run_fit returns: the MAP result, the reported state and errors, table, chains, files."""

    map_result: MapResult
    state: FitState
    uncertainty: Uncertainty
    table: object
    chains: Optional[ChainResult] = None
    files: tuple = ()


def _write_residuals(out: Path, scene_model, data, state) -> list:
    from ..io import write_residual_fits

    paths = []
    model = predicted_images(scene_model, state)
    for k, name in enumerate(scene_model.band_names):
        d = np.asarray(data.images[k])
        mu = np.asarray(model[k])
        var = (np.asarray(data.variances[k]) if data.variances is not None
               else np.maximum(mu, 1e-12) / data.exptime_s[k])
        chi = np.asarray(data.masks[k]) * (d - mu) / np.sqrt(var)
        path = out / f"residuals_{name}.fits"
        write_residual_fits(path, d, mu, chi, header={"BUNIT": "counts/s", "FILTER": name},
                            chi_bunit="")
        paths.append(path)
    return paths


def run_fit(scene_model, source_start, images, variances=None, *, free=None, method="map",
            likelihood="gaussian", mask=None, zeropoints_ab=None, background=False, n_starts=1,
            seed=0, mcmc=None, out_dir=None, background_start=None) -> FitRun:
    """Fit a scene model's source to images and (optionally) write the results.

    scene_model: `model.build_model(...)` output (lens and bands fixed).
    source_start: `Source` giving the structure and the starting values.
    images, variances, mask: dict band → array or FITS path (or sequences in band order).
    free: `params.parametrize` mapping; None: flux, centre and R_e of every clump.
    method: "map", "emcee" or "nuts".  likelihood: "gaussian" (needs variances),
        "gaussian_model_variance" or "poisson".
    zeropoints_ab: {band: ZP} for mag columns.  background: fit a level per band.
    background_start: [B] its start (counts/s per pixel; None: 0).
    n_starts: MAP starts (perturbed by 0.1 in u, vmapped).  seed: for starts and samplers.
    mcmc: keyword arguments for `run_emcee` / `run_nuts` (n_steps, n_walkers, n_warmup, ...).
    out_dir: where to write fit.ecsv, chains.npz, residuals_<band>.fits (None: nothing written).
    """
    require(method in ("map", "emcee", "nuts"), "method", method, '"map", "emcee" or "nuts"')
    data = make_data(scene_model, images, variances, mask, kind=likelihood)
    state0 = make_state(source_start, len(scene_model.layouts),
                        background_counts_per_s=background_start)
    param = parametrize(state0, _free_with_background(free, source_start, background))
    key = jax.random.key(seed)
    if n_starts > 1:
        res = fit_map_multistart(scene_model, data, param, key, n_starts=n_starts)
    else:
        res = fit_map(scene_model, data, param)
    unc = fisher_uncertainty(scene_model, param, res.x, data)
    chains = None
    state, err = res.state, unc.err
    if method != "map":
        chains, state, err, unc = _sample_posterior(method, scene_model, data, param, res.u,
                                                    unc.cov, seed, mcmc)
    table = fit_table(state, errors_state(param, err), band_names=scene_model.band_names,
                      zeropoints_ab=zeropoints_ab)
    table.meta.update({"method": method, "likelihood": likelihood,
                       "map_log_posterior": float(res.log_posterior),
                       "map_success": bool(res.success), "free": list(param.labels),
                       "host": host_meta(state, param.labels, err)})
    files = []
    if out_dir is not None:
        files = _write_fit_files(Path(out_dir), table, chains, scene_model, data, state)
    return FitRun(res, state, unc, table, chains, tuple(files))


def _free_with_background(free, source_start, background):
    """The `parametrize` mapping: the default one when free is None; with background, the
    per-band level added to a given one that lacks it."""
    if free is None:
        return default_free(source_start, background=background)
    if background and "background" not in free:
        return {**dict(free), "background": True} if isinstance(free, dict) else \
            list(free) + ["background"]
    return free


def _sample_posterior(method, scene_model, data, param, u_start, cov_x, seed, mcmc):
    """Run emcee or NUTS from the MAP point u_start (Fisher covariance cov_x: the NUTS metric
    and the walkers' ball, `mcmc.sample_from_optimum`); returns (chains, the state at the
    posterior median, standard deviations, the sample covariance as an Uncertainty)."""
    chains = sample_from_optimum(method, scene_model, data, param, u_start,
                                 whitening_scale(param, u_start, cov_x), seed=seed,
                                 **dict(mcmc or {}))
    state, unc = posterior_median(chains, param)
    return chains, state, chains.flat_x().std(axis=0, ddof=1), unc


def write_chains(path: Path, chains: ChainResult) -> Path:
    """chains.npz (atomically): samples_x, samples_u [chains, draws, parameters],
    log_posterior, labels, acceptance, ess, rhat, autocorr_time, method."""
    from ..io import atomic_write
    with atomic_write(path, "wb") as fh:
        np.savez(fh, samples_x=chains.samples_x, samples_u=chains.samples_u,
                 log_posterior=chains.log_posterior, labels=np.array(chains.labels),
                 acceptance=chains.acceptance, ess=chains.ess, rhat=chains.rhat,
                 autocorr_time=chains.autocorr_time, method=chains.method)
    return path


def _write_fit_files(out: Path, table, chains, scene_model, data, state) -> list:
    """Write fit.ecsv, chains.npz (sampled methods) and residuals_<band>.fits in out; their paths."""
    from ..io import write_catalog
    out.mkdir(parents=True, exist_ok=True)
    write_catalog(out / "fit.ecsv", table)
    files = [out / "fit.ecsv"]
    if chains is not None:
        files.append(write_chains(out / "chains.npz", chains))
    files += _write_residuals(out, scene_model, data, state)
    return files
