"""Fisher-forecast detectability of clumps: S/N of each clump's flux and size.

For a noiseless scene (no data needed), the Fisher matrix of the clumps'
fluxes (every band), half-light radii and, by default, centres — with the
expected Poisson variance (model + sky)/t per pixel — gives

    S/N_flux = F / σ_F,   S/N_size = R_e / σ_Re,

marginalised over the other free parameters (σ from the inverse Fisher
matrix) and "isolated" (σ = 1/√F_ii: every other parameter known). Their ratio
measures how much neighbours and the size–flux trade-off degrade a clump:
blended clumps have marginal S/N far below the isolated one.
"""

from __future__ import annotations

import numpy as np

from .params import make_state, parametrize
from .uncertainty import fisher_matrix, safe_inverse


def clump_detectability(scene_model, source, *, marginalise_centres: bool = True,
                        rcond: float = 1e-12):
    """astropy Table, one row per clump: snr_flux_<band>, snr_flux_<band>_isolated, snr_re, snr_re_isolated.

    scene_model: built for `source`'s structure.  source: the clumps at their true values.
    marginalise_centres: also free the clump centres (positions unknown a priori).
    """
    from astropy.table import Table

    n = source.clumps.count
    state = make_state(source, len(scene_model.layouts))
    free = {"clumps.flux": True, "clumps.re_arcsec": True}
    if marginalise_centres:
        free["clumps.center_arcsec"] = True
    param = parametrize(state, free)
    x = param.physical_of_state()
    fisher = np.asarray(fisher_matrix(scene_model, param, x))
    cov = np.asarray(safe_inverse(fisher, rcond))
    x = np.asarray(x)
    sig_marg = np.sqrt(np.diag(cov))
    with np.errstate(divide="ignore"):
        sig_iso = 1.0 / np.sqrt(np.maximum(np.diag(fisher), 0.0))
    labels = param.labels
    index = {lab: i for i, lab in enumerate(labels)}
    t = Table()
    t["id"] = np.arange(n)
    for b, name in enumerate(scene_model.band_names):
        idx = [index[f"clumps.flux[{k},{b}]"] for k in range(n)]
        t[f"flux_{name}"] = x[idx]
        t[f"snr_flux_{name}"] = x[idx] / sig_marg[idx]
        t[f"snr_flux_{name}_isolated"] = x[idx] / sig_iso[idx]
    idx = [index[f"clumps.re_arcsec[{k}]"] for k in range(n)]
    t["re_arcsec"] = x[idx]
    t["snr_re"] = x[idx] / sig_marg[idx]
    t["snr_re_isolated"] = x[idx] / sig_iso[idx]
    return t
