"""Sky, photon noise and variance maps. Images are in counts/s per pixel; counts = e⁻."""

from __future__ import annotations

import zlib

import jax
import jax.numpy as jnp
import numpy as np


def band_key(filter_name: str) -> int:
    """A stable 31-bit integer of a band's filter name, folded into the scene's noise key.

    CRC-32 of the upper-case name (not Python's hash(), which changes between processes).
    """
    return zlib.crc32(str(filter_name).upper().encode("utf-8")) & 0x7FFFFFFF


def variance_map(expected_counts_per_s, exptime_s):
    """Poisson variance of a count-rate image: (source + sky) / t, in (counts/s)². A numpy
    image gives a numpy map (the same bits: max and / are exact in both), computed without
    JAX's op-by-op compiles (two per image shape, ~0.5 s of a cold `simulate`)."""
    xp = np if isinstance(expected_counts_per_s, np.ndarray) else jnp
    return xp.maximum(expected_counts_per_s, 0.0) / exptime_s


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


# Pixels per draw of `add_photon_noise_bands`: every band's pixels are cut into chunks of this
# many, so that one sampler of one shape serves bands of any shape (2**12: the paper scene's
# bands take 1 to 7 chunks; its noise runs in ~0.05 s with 2**12 or 2**14).
NOISE_CHUNK = 1 << 12


def add_photon_noise_bands(key, images, names, exptimes_s, gaussian_above_counts=None):
    """Photon noise (as `add_photon_noise`) of each band's image: a band's noise depends
    on its own image, filter name and `key` only, not on which other bands are simulated
    with it.

    images: noiseless images with sky, counts/s per pixel.  exptimes_s: one per band.
    Each band's expected counts are flattened and cut into chunks of `NOISE_CHUNK` pixels
    (the last one padded with zeros), chunk j drawn with the key
    ``fold_in(fold_in(key, band_key(name)), j)``, and all chunks of all bands of one dtype
    by one sampler (`lax.map` over them): JAX's Poisson sampler is nearly all of the noise
    program, and one copy per image shape (as before) was three over the paper scene, ~6 s
    of a cold run's compile. Chunks of a fixed size, rather than padding every band to the
    longest: a draw's bits depend on the length of the array it fills (XLA's vectorised
    transcendental functions treat an array's tail apart), so padding to the longest band
    would tie a band's noise to the others' shapes.
    """
    out = [None] * len(images)
    groups = {}
    for k, img in enumerate(images):
        groups.setdefault(jnp.result_type(img), []).append(k)
    for ks in groups.values():
        bands, chunks, lams, counts = [], [], [], []
        for k in ks:
            flat = jnp.ravel(jnp.maximum(images[k], 0.0) * exptimes_s[k])
            n_chunks = -(-flat.size // NOISE_CHUNK)
            lams.append(jnp.pad(flat, (0, n_chunks * NOISE_CHUNK - flat.size))
                        .reshape(n_chunks, NOISE_CHUNK))
            bands += [band_key(names[k])] * n_chunks
            chunks += range(n_chunks)
            counts.append(n_chunks)
        # every chunk's key by one vectorised pair of fold_ins (one per band was a copy of
        # threefry each in the program)
        keys = jax.vmap(lambda b, j: jax.random.fold_in(jax.random.fold_in(key, b), j))(
            jnp.asarray(bands, jnp.uint32), jnp.asarray(chunks, jnp.uint32))
        drawn = jax.lax.map(lambda a: _photon_counts(a[0], a[1], gaussian_above_counts),
                            (keys, jnp.concatenate(lams)))
        first = 0
        for k, n_chunks in zip(ks, counts):
            img = images[k]
            mine = drawn[first:first + n_chunks].reshape(-1)[:img.size]
            out[k] = mine.reshape(img.shape) / exptimes_s[k]
            first += n_chunks
    return tuple(out)
