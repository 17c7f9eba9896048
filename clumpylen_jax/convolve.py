"""PSF convolution by zero-padded FFT: linear (not circular) convolution, centred.

Kernels have odd sizes with their centre on the central pixel (`psf.resample_psf`
produces them so); the output has the input's shape and flux that the PSF
spreads beyond the frame is lost, never wrapped around to the other side.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import scipy.fft

from .errors import ConfigError


def check_psf_values(psf, name="psf"):
    """Validate a PSF image (numpy): 2-D, finite, positive sum. Returns it normalised to unit sum."""
    k = np.asarray(psf, dtype=float)
    if k.ndim != 2:
        raise ConfigError(name, f"array of shape {k.shape}", "a 2-D PSF image")
    if not np.all(np.isfinite(k)):
        bad = np.argwhere(~np.isfinite(k))[0]
        raise ConfigError(name, f"non-finite value at pixel {tuple(int(i) for i in bad)}",
                          "a PSF with finite values")
    total = k.sum()
    if not total > 0:
        raise ConfigError(name, f"sum {total:g}", "a PSF with a positive sum")
    return k / total


def check_kernel(kernel, name="psf"):
    """Validate and normalise a convolution kernel: a valid PSF with odd sizes."""
    k = check_psf_values(kernel, name)
    if k.shape[0] % 2 == 0 or k.shape[1] % 2 == 0:
        raise ConfigError(name, f"shape {k.shape}",
                          "an odd-sized kernel centred on its central pixel "
                          "(resample even PSFs with clumpylen_jax.psf.resample_psf)")
    return k


def fft_shape(image_shape, kernel_shape):
    """Padded FFT shape for a linear convolution cropped to the image (its entries k//2 …
    k//2 + n − 1, `fft_convolve`): n + k//2 per axis, not the whole n + k − 1, is what keeps
    the circular convolution's wrapped terms out of that crop (at least k, to hold the
    kernel), rounded up to a fast size. For a 120² image and a 91² PSF: 180², not 210²."""
    return tuple(scipy.fft.next_fast_len(int(max(n + m // 2, m)), real=True)
                 for n, m in zip(image_shape, kernel_shape))


def kernel_rfft(kernel, image_shape, dtype=np.float64, check=True):
    """The kernel's rfft2 on the padded grid used by `fft_convolve` (precompute once per band).
    check: validate and normalise it as a PSF (`check_kernel`); False for kernels that are
    not one (a stack [..., ky, kx] of derivative kernels, `model.detector.psf_kernel`)."""
    k = check_kernel(kernel) if check else np.asarray(kernel, float)
    shape = fft_shape(image_shape, k.shape[-2:])
    # device_put, not jnp.asarray: the latter compiles a small program per shape
    return jax.device_put(np.fft.rfft2(k.astype(dtype), s=shape))


def _convolved(images, kernel_shape, combine):
    """The padded rfft2 of images [..., ny, nx], `combine`d (multiplied by the kernels' rfft2,
    summed), transformed back and cropped to the image: the one crop `fft_shape` pads for."""
    ny, nx = images.shape[-2:]
    ky, kx = kernel_shape
    shape = fft_shape((ny, nx), (ky, kx))
    full = jnp.fft.irfft2(combine(jnp.fft.rfft2(images, s=shape)), s=shape)
    return full[..., ky // 2:ky // 2 + ny, kx // 2:kx // 2 + nx].astype(images.dtype)


def fft_convolve(image, kernel_ft, kernel_shape):
    """Linear convolution of `image` [..., ny, nx] with a kernel given by its padded rfft2."""
    return _convolved(image, kernel_shape, lambda ft: ft * kernel_ft.astype(ft.dtype))


def fft_convolve_sum(images, kernels_ft, kernel_shape):
    """Σ_m images[m] ⊛ kernel m ([M, ny, nx] and their padded rfft2s [M, ...]): one inverse
    transform for all."""
    return _convolved(images, kernel_shape,
                      lambda ft: jnp.sum(ft * kernels_ft.astype(ft.dtype), axis=0))
