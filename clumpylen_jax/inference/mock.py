"""Small mock scenes for tests, benchmarks and examples of the inference package.

Gaussian (n = 0.5) clumps on a small field, cheap to compile and evaluate:
`toy_clumps` places N clumps on a ring-free grid with fluxes and sizes in a
range; `toy_model` builds the scene model (unlensed, or behind an SIS).
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from ..model import Accuracy, Band, build_model
from ..source import Clumps, Source

#: cheap accuracy for small Gaussian clumps (R_e ≥ pixel): no exact cores, 2×2 sampling
TOY_ACCURACY = Accuracy(exact_core=0, source_order=2, stamp_flux_fraction=0.9999)


def toy_clumps(n_clumps: int, *, seed=0, half_width_arcsec=0.45, flux=(1.0, 5.0),
               re_arcsec=(0.05, 0.1), n_bands=1, min_separation_arcsec=0.12) -> Source:
    """N Gaussian clumps, positions drawn in a square (rejecting close pairs), fluxes [N, B]."""
    rng = np.random.default_rng(seed)
    pos = []
    tries = 0
    while len(pos) < n_clumps:
        p = rng.uniform(-half_width_arcsec, half_width_arcsec, 2)
        tries += 1
        if tries > 10000 or all(np.hypot(*(p - q)) >= min_separation_arcsec for q in pos):
            pos.append(p)
    pos = np.array(pos).reshape(n_clumps, 2)
    f = rng.uniform(*flux, (n_clumps, 1)) * np.linspace(1.0, 0.6, n_bands)[None, :]
    return Source(clumps=Clumps(jnp.asarray(pos), jnp.asarray(f),
                                jnp.asarray(rng.uniform(*re_arcsec, n_clumps)),
                                jnp.full(n_clumps, 0.5), jnp.asarray(rng.uniform(0.6, 1.0, n_clumps)),
                                jnp.asarray(rng.uniform(0, np.pi, n_clumps))))


def toy_bands(n_bands=1, *, pixel_arcsec=0.03, exptime_s=1000.0, sky_counts_per_s=0.05, psf_sigma_pix=None):
    """Bands named B0, B1, ...; optional Gaussian PSF (σ in pixels, sampled at the pixel scale)."""
    psf = None
    if psf_sigma_pix is not None:
        r = np.arange(-4, 5)
        psf = np.exp(-0.5 * (r[:, None] ** 2 + r[None, :] ** 2) / psf_sigma_pix**2)
        psf /= psf.sum()
    return [Band(f"B{k}", pixel_arcsec, exptime_s, sky_counts_per_s, psf=psf,
                 psf_pixel_arcsec=None if psf is None else pixel_arcsec) for k in range(n_bands)]


def toy_model(source: Source, bands, *, npix=41, lens=None, field_arcsec=None,
              accuracy=TOY_ACCURACY, **kw):
    """Scene model on an npix × npix field centred on 0 (β for unlensed, θ for lensed)."""
    if field_arcsec is None:
        half = 0.5 * npix * bands[0].pixel_arcsec
        field_arcsec = ((-half, half), (-half, half))
    return build_model(source, bands, lens=lens, field_arcsec=field_arcsec, accuracy=accuracy, **kw)
