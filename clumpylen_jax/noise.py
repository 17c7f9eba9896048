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
    return _photon_counts(key, lam, gaussian_above_counts) / exptime_s


def _photon_counts(key, lam, gaussian_above_counts):
    """Counts drawn for expected counts `lam` (see `add_photon_noise`)."""
    kp, kg = jax.random.split(key)
    if gaussian_above_counts is None:
        return jax.random.poisson(kp, lam, dtype=jnp.int64 if lam.dtype == jnp.float64
                                  else jnp.int32).astype(lam.dtype)
    small = lam <= gaussian_above_counts
    lam_p = jnp.where(small, lam, 0.0)
    pois = jax.random.poisson(kp, lam_p).astype(lam.dtype)
    gauss = lam + jnp.sqrt(lam) * jax.random.normal(kg, lam.shape, lam.dtype)
    return jnp.where(small, pois, gauss)


def add_photon_noise_bands(key, images, names, exptimes_s, gaussian_above_counts=None):
    """`add_photon_noise` of each band's image with the key ``fold_in(key, band_key(name))``:
    a band's noise depends on its own image, filter name and `key` only, not on which
    other bands are simulated with it.

    images: noiseless images with sky, counts/s per pixel.  exptimes_s: one per band.
    Bands of one image shape share one sampler (`lax.map` over them): JAX's Poisson
    sampler is the largest part of a band render's program otherwise, repeated per band
    (compiled, stored and loaded nine times over the paper scene). Each band is still
    drawn alone, on its own image (not padded: JAX's Poisson draws depend on the size
    of the array they fill).
    """
    out = [None] * len(images)
    groups = {}
    for k, img in enumerate(images):
        groups.setdefault((img.shape, img.dtype), []).append(k)
    for ks in groups.values():
        keys = jnp.stack([jax.random.fold_in(key, band_key(names[k])) for k in ks])
        lam = jnp.stack([jnp.maximum(images[k], 0.0) * exptimes_s[k] for k in ks])
        drawn = jax.lax.map(lambda a: _photon_counts(a[0], a[1], gaussian_above_counts),
                            (keys, lam))
        for j, k in enumerate(ks):
            out[k] = drawn[j] / exptimes_s[k]
    return tuple(out)
