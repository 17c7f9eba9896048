# %% [markdown]
# # Fitting clumps in a mock lensed arc
#
# A jupytext percent script (open as a notebook with `jupytext --to notebook`).
# Three Gaussian clumps behind an SIS lens form an arc; we observe it with photon
# noise, fit clump fluxes, positions and sizes (MAP, Levenberg–Marquardt), read
# Fisher errors, sample the posterior with NUTS, and write the fitted catalogue.

# %%
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import clumpylen_jax  # noqa: E402
clumpylen_jax.enable_float64()  # float64: the caller's choice
from clumpylen_jax.inference import fisher_uncertainty, fit_map, make_data, make_state, parametrize
from clumpylen_jax.inference.catalog import errors_state, fit_table
from clumpylen_jax.inference.mcmc import run_nuts
from clumpylen_jax.inference.mock import toy_bands, toy_model
from clumpylen_jax.lensing.analytic import SIS
from clumpylen_jax.source import Clumps, Source

# %% the truth: three clumps near the caustic of an SIS with θ_E = 1"
truth = Source(clumps=Clumps(jnp.array([[0.05, 0.02], [0.0, -0.03], [-0.04, 0.04]]),
                             jnp.array([[3.0], [2.0], [1.0]]), jnp.array([0.02, 0.03, 0.025]),
                             jnp.full(3, 0.5), jnp.array([0.8, 1.0, 0.9]), jnp.array([0.3, 0.0, 1.0])))
bands = toy_bands(1, pixel_arcsec=0.06, psf_sigma_pix=1.0)
model = toy_model(truth, bands, npix=40, lens=SIS(jnp.asarray(1.0), jnp.zeros(2)),
                  lens_pixel_arcsec=0.015, source_pixel_arcsec=0.004)
noisy, clean, var = eqx.filter_jit(model.observe)(truth, jax.random.key(0))

# %% fit from a perturbed start
start = Source(clumps=eqx.tree_at(lambda c: c.flux, truth.clumps, truth.clumps.flux * 0.7))
data = make_data(model, noisy, var)
param = parametrize(make_state(start, 1), {"clumps.flux": True, "clumps.center_arcsec": True,
                                           "clumps.re_arcsec": True})
res = fit_map(model, data, param)
unc = fisher_uncertainty(model, param, res.x, data)
truth_x = param.physical_of_state(make_state(truth, 1))
for lab, t, x, e in zip(param.labels, truth_x, res.x, unc.err):
    print(f"{lab:28s} truth {float(t):9.4f}  fit {float(x):9.4f} ± {float(e):.4f}")

# %% posterior with NUTS, started at the MAP
chains = run_nuts(model, data, param, res.u, jax.random.key(1), n_chains=2, n_warmup=200, n_samples=300)
print("acceptance", chains.acceptance, "R-hat", chains.rhat.round(3), "ESS", chains.ess.round(0))

# %% the fitted catalogue
table = fit_table(res.state, errors_state(param, unc.err), band_names=model.band_names,
                  zeropoints_ab={"B0": 28.0})
table.pprint_all()

# %% a corner plot (optional dependency)
try:
    import corner
    fig = corner.corner(chains.flat_x()[:, :3], labels=list(param.labels[:3]), truths=np.asarray(truth_x[:3]))
    fig.savefig("fit_mock_arc_corner.png", dpi=80)
except ImportError:
    print("corner not installed")
