"""Sky, photon noise and variance maps. Images are in counts/s per pixel; counts = e⁻."""

from __future__ import annotations

import zlib

import jax
import jax.numpy as jnp


def band_key(filter_name: str) -> int:
    """A stable 31-bit integer of a band's filter name, folded into the scene's noise key.

    CRC-32 of the upper-case name (not Python's hash(), which changes between processes).
    """
    return zlib.crc32(str(filter_name).upper().encode("utf-8")) & 0x7FFFFFFF


def variance_map(expected_counts_per_s, exptime_s):
    """Poisson variance of a count-rate image: (source + sky) / t, in (counts/s)²."""
    return jnp.maximum(expected_counts_per_s, 0.0) / exptime_s


def add_photon_noise(key, expected_counts_per_s, exptime_s, gaussian_above_counts=None):
    """A Poisson draw of source + sky counts over the exposure, returned as counts/s.

    expected_counts_per_s: noiseless image including sky, counts/s per pixel.
    gaussian_above_counts: if set, pixels expecting more counts than this use
        the Gaussian approximation N(λ, λ) (cheaper, indistinguishable there).
    """
    lam = jnp.maximum(expected_counts_per_s, 0.0) * exptime_s
    kp, kg = jax.random.split(key)
    if gaussian_above_counts is None:
        counts = jax.random.poisson(kp, lam, dtype=jnp.int64 if lam.dtype == jnp.float64
                                    else jnp.int32).astype(lam.dtype)
    else:
        small = lam <= gaussian_above_counts
        lam_p = jnp.where(small, lam, 0.0)
        pois = jax.random.poisson(kp, lam_p).astype(lam.dtype)
        gauss = lam + jnp.sqrt(lam) * jax.random.normal(kg, lam.shape, lam.dtype)
        counts = jnp.where(small, pois, gauss)
    return counts / exptime_s
