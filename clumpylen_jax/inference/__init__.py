"""Inference: likelihoods, free parameters, MAP fits, Fisher/Laplace errors, MCMC, detectability.

Modules (one job each):
    transforms    bijections between unconstrained u and physical parameters
    params        FitState, free-parameter selection, u ↔ state
    photometric   clump fluxes from mass and age (photometry.ab_magnitudes)
    likelihood    Gaussian / model-variance Gaussian / Poisson (Cash) log-likelihoods
    optimize      MAP with optimistix (Levenberg–Marquardt, BFGS), vmapped multi-start
    uncertainty   Fisher matrix, Laplace approximation, delta method
    mcmc          emcee (vectorised walkers) and NUTS (blackjax; whitened by a Laplace metric)
    diagnostics   split-R̂ and effective sample size
    detect        Fisher-forecast S/N of clump fluxes and sizes
    completeness  injection–recovery completeness with photutils segmentation
    catalog       fitted-clump table (fit_table)
    run           run_fit: fit images and write fit.ecsv, chains.npz, residual FITS
"""

from .likelihood import ImageData, log_likelihood, make_data, make_log_likelihood, make_log_posterior
from .optimize import MapResult, fit_map, fit_map_multistart
from .params import FitState, Free, Parametrization, default_free, make_state, parametrize
from .transforms import Transform
from .uncertainty import Uncertainty, fisher_matrix, fisher_uncertainty, laplace, safe_inverse

__all__ = [
    "FitState", "Free", "ImageData", "MapResult", "Parametrization", "Transform", "Uncertainty",
    "default_free", "fisher_matrix", "fisher_uncertainty", "fit_map", "fit_map_multistart",
    "laplace", "log_likelihood", "make_data", "make_log_likelihood", "make_log_posterior",
    "make_state", "parametrize", "safe_inverse",
]
