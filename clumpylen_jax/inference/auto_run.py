"""`clumpylen fit SCENE --image BAND=FILE`: the images fitted by `auto.fit_without_truth`.

The scene gives only what an observer knows: bands (pixels, PSFs, exposure, sky), the
lens and the redshift, the detector grids of the images and the clumps' Sérsic index
(the population setting, not the sampled clumps). Its sampled catalogue and its host's
parameters are never read: the host starts from the images' moments.

Writes into out_dir (atomically): fit.ecsv (the catalogue, with flag and blend
columns), fit_steps.json (one entry per counting step) and residuals_<band>.fits.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from ..errors import require
from .auto import AutoOptions, fit_without_truth, lensed_fit_accuracy


def make_model_factory(prep):
    """make_model(source) for `fit_without_truth` on the scene's bands, lens and detector grids."""
    from ..model import build_model

    grids = [lay.grid for lay in prep.model.layouts]
    field = prep.field_arcsec
    if field is None:   # unlensed: the images' own area (all bands share it)
        field = (grids[0].x_range, grids[0].y_range)
    acc = lensed_fit_accuracy(prep.accuracy) if prep.lens is not None else prep.accuracy

    def make_model(source):
        return build_model(source, prep.bands, lens=prep.lens, field_arcsec=field, accuracy=acc,
                           dtype=prep.dtype)
    return make_model


def run_auto_fit(prep, images, variances=None, *, out_dir=None, options=None):
    """Fit images (list in the scene's band order, counts/s) of a prepared scene; write results.

    variances: list of σ² maps, or None (Poisson from the images: max(d, sky)/t).
    """
    if variances is None:
        variances = [np.maximum(np.asarray(d, float), max(lay.sky_counts_per_s, 1e-12)) / lay.exptime_s
                     for d, lay in zip(images, prep.model.layouts)]
    opts = options or AutoOptions(clump_n=float(_clump_n(prep.scene)), seed=int(prep.scene.seed))
    fit = fit_without_truth(make_model_factory(prep), images, variances, lens=prep.lens,
                            zeropoints_ab=prep.zeropoints, options=opts)
    if out_dir is not None:
        write_auto_fit(fit, images, variances, out_dir)
    return fit


def _clump_n(scene):
    cl = getattr(scene.source, "clumps", None)
    return getattr(cl, "sersic_n", AutoOptions.clump_n) if cl is not None else AutoOptions.clump_n


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
    state = masked(fit.param.state(fit.u), fit.active)
    return [out / "fit.ecsv", out / "fit_steps.json"] + _write_residuals(out, fit.model, data, state)
