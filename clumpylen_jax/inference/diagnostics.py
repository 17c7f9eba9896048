"""MCMC convergence diagnostics on chains shaped [n_chains, n_draws, n_params] (numpy).

- `split_rhat`: the potential scale reduction of Gelman et al. (BDA3 §11.4) with each
  chain split in halves, so that a drifting chain shows up as disagreeing halves.
- `effective_sample_size`: the multi-chain ESS of BDA3 / Stan: autocorrelations
  from the FFT of each chain, combined across chains through the between/within
  variance, summed over Geyer's initial positive sequence (pairs of lags while
  their sum stays positive, made monotone).
"""

from __future__ import annotations

import numpy as np


def _as_chains(samples):
    a = np.asarray(samples, float)
    if a.ndim == 2:
        a = a[:, :, None]
    if a.ndim != 3:
        raise ValueError("chains must be [n_chains, n_draws(, n_params)]")
    return a


def split_rhat(samples) -> np.ndarray:
    """Split-R̂ per parameter (≈ 1 when chains agree; > 1.01–1.05 flags trouble)."""
    a = _as_chains(samples)
    half = a.shape[1] // 2
    split = np.concatenate([a[:, :half], a[:, a.shape[1] - half:]], axis=0)
    n = split.shape[1]
    means = split.mean(axis=1)
    w = split.var(axis=1, ddof=1).mean(axis=0)
    b = n * means.var(axis=0, ddof=1)
    var_plus = (n - 1) / n * w + b / n
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.sqrt(var_plus / w)


def _autocovariance(x):
    """Autocovariance of each chain along axis 1 (biased estimator, as in Stan), via FFT."""
    n = x.shape[1]
    xc = x - x.mean(axis=1, keepdims=True)
    size = 1 << int(np.ceil(np.log2(2 * n)))
    f = np.fft.rfft(xc, n=size, axis=1)
    return np.fft.irfft(f * np.conj(f), n=size, axis=1)[:, :n] / n


def effective_sample_size(samples) -> np.ndarray:
    """Bulk ESS per parameter over all chains."""
    a = _as_chains(samples)
    m, n, d = a.shape
    out = np.empty(d)
    for j in range(d):
        x = a[:, :, j]
        acov = _autocovariance(x)
        w = acov[:, 0].mean() * n / (n - 1)
        var_plus = w * (n - 1) / n + (x.mean(axis=1).var(ddof=1) if m > 1 else 0.0)
        if not np.isfinite(var_plus) or var_plus <= 0:
            out[j] = np.nan
            continue
        rho = 1.0 - (w - acov.mean(axis=0)) / var_plus
        rho[0] = 1.0
        # Geyer: sums of adjacent pairs, truncated at the first non-positive, made monotone
        pairs = rho[: 2 * (n // 2)].reshape(-1, 2).sum(axis=1)
        stop = np.argmax(pairs <= 0) if np.any(pairs <= 0) else pairs.size
        p = np.minimum.accumulate(pairs[:max(stop, 1)])
        tau = -1.0 + 2.0 * p.sum()
        out[j] = m * n / max(tau, 1.0 / np.log10(m * n + 10))
    return out
