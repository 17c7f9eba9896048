"""Masses and ages from band fluxes (`observations.answers.sed_fit`) against draws of known
truth: the grid posterior's ±1σ must hold the truth as often as a 1σ interval should."""

import numpy as np
import pytest

from clumpylen_jax.cosmology import make_cosmology
from clumpylen_jax.observations.answers import CALIBRATION_FLOOR, sed_fit
from clumpylen_jax.photometry import band_fluxes_ujy

FILTERS = ["F115W", "F150W", "F200W", "F277W", "F356W"]
Z = 2.0


def _fluxes(mass, age):
    return np.asarray(band_fluxes_ujy(mass, age, filters=FILTERS, z=Z,
                                      cosmology=make_cosmology(70.0, 0.3)), float)


@pytest.mark.parametrize("mass,age", [(3e7, 30.0), (1e8, 300.0)])
def test_noiseless_fluxes_give_the_truth(mass, age):
    """Fluxes with no noise: the posterior's median is the truth within the grids' steps
    (mass: 6 dex in 241 steps; age: 60 log steps over the library)."""
    f = _fluxes(mass, age)
    sig = 0.05 * f
    cov = np.outer(sig, sig) * (0.5 + 0.5 * np.eye(len(f)))
    out = sed_fit(f[None], cov[None], FILTERS, Z)
    assert abs(np.log10(out["mass_msun"][0] / mass)) < 0.05
    assert abs(np.log10(out["age_myr"][0] / age)) < 0.1
    # the same fluxes with their σ only: the same answer (no noise to weigh)
    same = sed_fit(f[None], sig[None], FILTERS, Z)
    assert abs(np.log10(same["mass_msun"][0] / mass)) < 0.05


@pytest.mark.parametrize("mass,age", [(3e7, 30.0), (1e8, 300.0)])
def test_correlated_flux_errors_give_calibrated_masses_and_ages(mass, age):
    """400 draws of fluxes with errors of 20 % correlated at 0.9 between every pair of bands
    (as a clump's shared R_e makes them) plus the calibration floor: with the covariance,
    |fit − truth| < σ for 60–78 % of the draws in mass and age (68 % expected). The same
    draws with the σ alone (independent bands, what the answers used before) hold the
    mass's truth ≥ 78 % of the time: its errors are too wide (the common error cancels in
    the colours, which fix the age)."""
    f = _fluxes(mass, age)
    n, b = 400, len(f)
    sig = 0.2 * f
    cov = np.outer(sig, sig) * (0.9 + 0.1 * np.eye(b))
    draws = f + np.random.default_rng(0).multivariate_normal(
        np.zeros(b), cov + np.diag((CALIBRATION_FLOOR * f) ** 2), n)

    def within(out, key, truth):
        return np.mean(np.abs(out[key] - truth) < out[f"{key}_err"])

    full = sed_fit(draws, np.broadcast_to(cov, (n, b, b)), FILTERS, Z)
    for key, truth in (("mass_msun", mass), ("age_myr", age)):
        assert np.all(np.isfinite(full[key])) and np.all(full[f"{key}_err"] > 0)
        assert 0.60 <= within(full, key, truth) <= 0.78, key
    indep = sed_fit(draws, np.broadcast_to(sig, (n, b)), FILTERS, Z)
    assert within(indep, "mass_msun", mass) >= 0.78
