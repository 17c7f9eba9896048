"""Fit the mixture of round Gaussians that stands for a round exponential (Sérsic n = 1)
clump: `clumpylen_jax.gaussian_mixtures.EXPONENTIAL` (prints the constants to paste there).

    .venv/bin/python scripts/fit_exponential_mog.py [K ...]       (default K = 8; ~2 min)

Units of R_e = 1. Unknowns: K light fractions (a softmax: they sum to 1, so a mixture
conserves the clump's flux exactly) and K widths σ_k in [1e-5, 5] R_e. Objective: the error
of the brightness relative to the central one, ΔI(r)/I(0), and of the enclosed light
fraction, ΔL(r), on 500 radii from 1e-5 to 15 R_e (log and linear spacing), both at once;
least squares, reweighted 12 times towards the largest errors (Lawson), the best minimax
kept. Bounding σ matters: without it the solver parks light in a component of infinite
width, which no radius sees.

Pixel errors of the result against the exact Sérsic pixel integrals, with and without a
PSF, are measured by benchmarks/bench_mog_accuracy.py.
"""

import sys

import numpy as np
from scipy.optimize import least_squares
from scipy.special import gammaincinv

B = gammaincinv(2.0, 0.5)                                   # b(1)
R = np.unique(np.r_[np.geomspace(1e-5, 15, 300), np.linspace(0, 15, 200)])
I_EXACT = np.exp(-B * R)                                    # brightness / I(0)
L_EXACT = 1 - (1 + B * R) * np.exp(-B * R)                  # enclosed light fraction


def unpack(p, k):
    a = np.exp(p[:k] - p[:k].max())
    return a / a.sum(), np.exp(p[k:])


def errors(p, k):
    """(ΔI / I(0), ΔL) on R."""
    a, s = unpack(p, k)
    g = np.exp(-R[:, None] ** 2 / (2 * s**2))
    return (a / (s * B) ** 2 * g).sum(1) - I_EXACT, (a * (1 - g)).sum(1) - L_EXACT


def fit(k, rounds=12):
    p = np.r_[np.zeros(k), np.linspace(np.log(3e-3), np.log(1.5), k)]
    lo = np.r_[np.full(k, -60.0), np.full(k, np.log(1e-5))]
    hi = np.r_[np.zeros(k), np.full(k, np.log(5.0))]
    w = np.ones(2 * R.size)
    best = (np.inf, p)
    for _ in range(rounds):
        p = least_squares(lambda v: w * np.concatenate(errors(v, k)), p, bounds=(lo, hi),
                          max_nfev=400).x
        e = np.abs(np.concatenate(errors(p, k)))
        best = min(best, (e.max(), p), key=lambda t: t[0])
        w = w * (1 + e / e.max())
        w /= w.max()
    return best[1]


def main():
    for k in [int(v) for v in sys.argv[1:]] or [8]:
        p = fit(k)
        a, s = unpack(p, k)
        d_i, d_l = errors(p, k)
        o = np.argsort(s)
        print(f"K = {k}: max |ΔI|/I(0) = {np.abs(d_i).max():.2e}, max |ΔL| = {np.abs(d_l).max():.2e}")
        print("amplitudes =", tuple(float(f"{v:.12g}") for v in a[o]))
        print("sigma_per_re =", tuple(float(f"{v:.12g}") for v in s[o]))


if __name__ == "__main__":
    main()
