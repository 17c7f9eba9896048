"""`clumpylen fit SCENE --image BAND=FILE`: the images fitted by `auto.fit_without_truth`.

The scene gives only what an observer knows: bands (pixels, PSFs, exposure, sky), the
lens and the redshift, the detector grids of the images and the clumps' Sérsic index
(the population setting, not the sampled clumps). Its sampled catalogue and its host's
parameters are never read: the host starts from the images' moments.

Writes into out_dir (atomically): fit.ecsv (the catalogue, with flag and blend
columns), fit_steps.json (one entry per counting step) and residuals_<band>.fits.

`--method emcee|nuts` (`run_sampled_fit`): the same data-driven MAP fit first, then the
sampler from it (the clumps it kept, the host and background it fitted), as an astronomer
would: never from the scene's catalogue.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from .auto import AutoOptions, fit_clump_pixels, fit_without_truth, lensed_fit_accuracy


def make_model_factory(prep, options: AutoOptions):
    """make_model(source) for `fit_without_truth` with `options` on the scene's bands, lens
    and detector grids (n = 0.5 or n = 1 clumps of an unlensed scene known to be round,
    `AutoOptions.round_clumps`: the separable Gaussian-mixture renderer, `fit_clump_pixels`)."""
    from ..model import build_model

    grids = [lay.grid for lay in prep.model.layouts]
    field = prep.field_arcsec
    if field is None:   # unlensed: the images' own area (all bands share it)
        field = (grids[0].x_range, grids[0].y_range)
    acc = lensed_fit_accuracy(prep.accuracy) if prep.lens is not None else prep.accuracy
    # Gaussian clumps through a lens: averaged over each ray's cell, not point-sampled (a thin
    # clump aliased at 2 rays per lens pixel, and the fits ran to such shapes: issue 18)
    acc = dataclasses.replace(acc, clump_pixels=fit_clump_pixels(
        options.clump_n, options.round_clumps and not options.fit_shape, prep.lens is not None),
        ray_footprint=prep.lens is not None and float(options.clump_n) == 0.5)

    render = prep.scene.render

    def make_model(source):
        # the scene's lens-plane and source-plane pixels, as the simulation used (the
        # defaults are 4× finer: 16× the rays of a 0.01" scene, 7.5 GB for 103² pixels)
        return build_model(source, prep.bands, lens=prep.lens, field_arcsec=field, accuracy=acc,
                           lens_pixel_arcsec=render.lens_pixel_arcsec,
                           source_pixel_arcsec=render.source_pixel_arcsec, dtype=prep.dtype)
    return make_model


def run_auto_fit(prep, images, variances=None, *, out_dir=None, options=None):
    """Fit images (list in the scene's band order, counts/s) of a prepared scene; write results.

    variances: list of σ² maps, or None (Poisson from the images: max(d, sky)/t).
    """
    if variances is None:
        variances = [np.maximum(np.asarray(d, float), max(lay.sky_counts_per_s, 1e-12)) / lay.exptime_s
                     for d, lay in zip(images, prep.model.layouts)]
    opts = options or scene_options(prep.scene)
    fit = fit_without_truth(make_model_factory(prep, opts), images, variances, lens=prep.lens,
                            zeropoints_ab=prep.zeropoints, options=opts)
    if out_dir is not None:
        write_auto_fit(fit, images, variances, out_dir)
    return fit


def scene_options(scene) -> AutoOptions:
    """The fit's options from the scene: its clumps' Sérsic index, whether its clumps are
    round (q_range [1, 1]: `AutoOptions.round_clumps`) and its seed: the population's law,
    never its draw.

    Clumps are counted round through a lens too: fitting q and PA for all of them
    (`AutoOptions.fit_shape`) was tried on the SIS recovery scene
    (benchmarks/results/recovery_shape_lensed.md): an elongated clump then absorbed its
    neighbours, 4 clumps kept instead of 6 and 2 of 6 recovered instead of 5. After the
    counting, the merge and shape moves (`AutoOptions.merge`, on) make a clump elliptical
    where the criterion asks for it (benchmarks/results/recovery_merge.md), and the final
    refit frees every kept clump's shape (`AutoOptions.final_shape`, on)."""
    cl = getattr(scene.source, "clumps", None)
    n = getattr(cl, "sersic_n", AutoOptions.clump_n) if cl is not None else AutoOptions.clump_n
    q_lo = cl.q_range[0] if cl is not None else 0.0
    return AutoOptions(clump_n=float(n), round_clumps=bool(q_lo >= 1.0), seed=int(scene.seed))


def write_auto_fit(fit, images, variances, out_dir) -> list:
    """fit.ecsv, fit_steps.json and residuals_<band>.fits in out_dir."""
    from ..io import write_catalog, write_json
    from .likelihood import make_data
    from .params import masked_clumps
    from .run import _write_residuals

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    write_catalog(out / "fit.ecsv", fit.table)
    write_json(out / "fit_steps.json", fit.steps)
    data = make_data(fit.model, list(images), list(variances), kind="gaussian")
    state = masked_clumps(fit.param.state(fit.u), fit.active)
    return [out / "fit.ecsv", out / "fit_steps.json"] + _write_residuals(out, fit.model, data, state)


def run_sampled_fit(prep, images, variances=None, *, method="emcee", out_dir=None, mcmc=None):
    """`run_auto_fit` (clumps found and counted from the images), then `run_fit` with
    `method` ("emcee" or "nuts") started at that optimum: flux, centre and R_e of every kept
    clump, the host's flux, R_e and centre and the background level per band are sampled.

    The sampling model is built for the kept clumps with every stamp at the R_e bound of the
    auto fit (a clump the chain grows is not truncated). Returns (AutoFit, FitRun).
    """
    import jax.numpy as jnp

    from .run import run_fit
    from .params import default_free

    opts = scene_options(prep.scene)
    auto_fit = run_auto_fit(prep, images, variances, options=opts)
    src = auto_fit.state.source
    build = src
    if src.clumps is not None and src.clumps.count > 0:
        re_hi = float(auto_fit.table.meta["re_bounds_arcsec"][1])
        build = dataclasses.replace(src, clumps=dataclasses.replace(
            src.clumps, re_arcsec=jnp.full_like(src.clumps.re_arcsec, re_hi)))
    model = make_model_factory(prep, opts)(build)
    free = default_free(src, host_fields=("flux", "re_arcsec", "center_arcsec"), background=True)
    run = run_fit(model, src, list(images), None if variances is None else list(variances),
                  free=free, method=method,
                  likelihood="gaussian" if variances is not None else "gaussian_model_variance",
                  zeropoints_ab=prep.zeropoints, seed=int(prep.scene.seed), mcmc=mcmc,
                  out_dir=out_dir, background_start=np.asarray(auto_fit.state.background_counts_per_s))
    if out_dir is not None:
        from ..io import write_json
        write_json(Path(out_dir) / "fit_steps.json", auto_fit.steps)
    return auto_fit, run
