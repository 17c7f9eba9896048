"""Likelihoods of observed images given a scene model and a FitState (differentiable).

Data images are what `SceneModel.observe` returns and what a telescope gives:
counts/s per pixel *including* the sky. The prediction is

    μ_b = SceneModel.noiseless(source)_b + background_b      (noiseless includes the band's sky)

Three likelihoods, chosen by `ImageData.kind`:

- "gaussian": fixed variance maps σ² (e.g. from the data reduction):
      ln L = −½ Σ m (d − μ)² / σ²                         (constant terms dropped)
- "gaussian_model_variance": σ² = μ / t, the Poisson variance of the model itself:
      ln L = −½ Σ m [(d − μ)² / σ² + ln(2π σ²)]
- "poisson": the Cash statistic on counts D = d t, M = μ t:
      ln L = Σ m [D ln M − M − ln Γ(D + 1)]   (= −C/2 + const, Cash 1979)

m is the mask (1 = use the pixel). Multi-band data sum over bands; geometry is
shared across bands through the source (flux[N, B] per band).

With `ImageData.diffuse` (kind "gaussian" only), each band also carries a smooth diffuse
light whose coefficients are profiled out (diffuse.py): the residuals, χ² and ln L below
are those of the best diffuse light for the given μ.
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable, Optional

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jax.scipy.special import gammaln, xlogy

from ..errors import ConfigError, require
from . import diffuse as _diffuse
from .params import FitState, Parametrization

KINDS = ("gaussian", "gaussian_model_variance", "poisson")
_MODEL_FLOOR = 1e-12  # counts/s: keeps ln M and 1/σ² finite where the model is exactly 0


class ImageData(eqx.Module):
    """Observed images of every band of a scene model, with what the likelihood needs.

    images: tuple [B] of [ny, nx] counts/s per pixel (with sky).
    variances: tuple [B] of σ² maps ((counts/s)²) or None (only "gaussian" needs them).
    masks: tuple [B] of 0/1 weights (1 = fitted).
    exptime_s: per band (static).  kind: one of KINDS (static).
    diffuse: tuple [B] of `diffuse.DiffuseBasis`, or None (no diffuse light).
    """

    images: tuple
    variances: Optional[tuple]
    masks: tuple
    exptime_s: tuple = eqx.field(static=True)
    kind: str = eqx.field(static=True, default="gaussian")
    diffuse: Optional[tuple] = None

    @property
    def n_pixels(self) -> int:
        return int(sum(float(np.sum(np.asarray(m))) for m in self.masks))

    @property
    def n_diffuse(self) -> tuple:
        """Free diffuse coefficients per band (0 without diffuse light)."""
        if self.diffuse is None:
            return (0,) * len(self.images)
        return tuple(b.n_coefficients for b in self.diffuse)


def read_image(x, hdu=None) -> np.ndarray:
    """An image as float64: an array, or a FITS path (the given HDU, else the first with data)."""
    if isinstance(x, (str, Path)):
        from astropy.io import fits
        with fits.open(x) as hdul:
            if hdu is not None:
                return np.asarray(hdul[hdu].data, float)
            for h in hdul:
                if h.data is not None and np.ndim(h.data) == 2:
                    return np.asarray(h.data, float)
        raise ConfigError("image", str(x), "a FITS file with a 2-D image")
    return np.asarray(x, float)


def _per_band(value, names, what):
    if value is None:
        return None
    if isinstance(value, dict):
        missing = [n for n in names if n not in value]
        require(not missing, what, sorted(value), f"an entry for every band {list(names)}")
        return [value[n] for n in names]
    if isinstance(value, (list, tuple)):
        require(len(value) == len(names), what, len(value), f"{len(names)} images (one per band)")
        return list(value)
    require(len(names) == 1, what, "one array", f"a dict or sequence over bands {list(names)}")
    return [value]


def make_data(scene_model, images, variances=None, mask=None, *, kind="gaussian",
              dtype=jnp.float64, diffuse_spacing_arcsec=None) -> ImageData:
    """ImageData for `scene_model` from images (dict band → array/FITS, sequence, or one array).

    variances: same forms (σ² maps) — required for kind="gaussian".
    mask: same forms, or one array for all bands; True/1 = pixel used. None: all pixels.
    diffuse_spacing_arcsec: node spacing of a diffuse light profiled out of the fit
        (diffuse.py; at least `diffuse.MIN_SPACING_PIX` of every band's pixels), or None.
    """
    require(kind in KINDS, "likelihood", kind, " or ".join(KINDS))
    if diffuse_spacing_arcsec is not None:
        require(kind == "gaussian", "likelihood", kind, '"gaussian" with a diffuse light')
        _diffuse.require_spacing(diffuse_spacing_arcsec,
                                 [lay.grid.pixel_arcsec for lay in scene_model.layouts],
                                 "diffuse_spacing_arcsec")
    names = scene_model.band_names
    imgs = [read_image(x) for x in _per_band(images, names, "images")]
    shapes = [lay.grid.shape for lay in scene_model.layouts]
    for name, img, shape in zip(names, imgs, shapes):
        require(img.shape == tuple(shape), f"images[{name}] (shape)", img.shape,
                f"the model's detector shape {tuple(shape)}")
    var = _per_band(variances, names, "variances")
    if kind == "gaussian":
        require(var is not None, "variances", None, 'variance maps for likelihood "gaussian"')
    if var is not None:
        var = [read_image(v) for v in var]
        for name, v, img in zip(names, var, imgs):
            require(v.shape == img.shape, f"variances[{name}] (shape)", v.shape, f"{img.shape}")
            require(bool(np.all(np.isfinite(v)) and np.all(v >= 0)), f"variances[{name}]",
                    "negative or non-finite", "σ² ≥ 0 (0 marks a pixel to ignore)")
    if mask is None:
        masks = [np.ones(img.shape) for img in imgs]
    else:
        ms = [mask] * len(names) if isinstance(mask, np.ndarray) and len(names) > 1 else \
            _per_band(mask, names, "mask")
        masks = [np.asarray(read_image(m) if isinstance(m, (str, Path)) else m, float) for m in ms]
    if var is not None:
        # σ² = 0 (or non-positive) pixels carry no information: masked, and σ² set to 1 for safety
        masks = [m * (v > 0) for m, v in zip(masks, var)]
        var = [np.where(v > 0, v, 1.0) for v in var]
    masks = [m * np.isfinite(img) for m, img in zip(masks, imgs)]
    imgs = [np.where(np.isfinite(img), img, 0.0) for img in imgs]
    exptimes = tuple(float(lay.exptime_s) for lay in scene_model.layouts)
    to = lambda seq: tuple(jnp.asarray(a, dtype) for a in seq)  # noqa: E731
    bases = None
    if diffuse_spacing_arcsec is not None:
        bases = tuple(_diffuse.make_basis(img.shape, diffuse_spacing_arcsec / lay.grid.pixel_arcsec,
                                          v, m, dtype)
                      for img, v, m, lay in zip(imgs, var, masks, scene_model.layouts))
    return ImageData(to(imgs), None if var is None else to(var), to(masks), exptimes, kind, bases)


def predicted_images(scene_model, state: FitState):
    """μ per band: noiseless model (with sky) plus the fitted background level."""
    clean = scene_model.noiseless(state.render_source())
    return tuple(img + state.background_counts_per_s[k] for k, img in enumerate(clean))


def band_log_likelihood(mu, d, m, var, exptime_s: float, kind: str):
    """ln L of one band (see module doc for the three forms)."""
    if kind == "gaussian":
        return -0.5 * jnp.sum(m * (d - mu) ** 2 / var)
    mu_pos = jnp.maximum(mu, _MODEL_FLOOR)
    if kind == "gaussian_model_variance":
        v = mu_pos / exptime_s
        return -0.5 * jnp.sum(m * ((d - mu) ** 2 / v + jnp.log(2 * jnp.pi * v)))
    counts_d = jnp.maximum(d * exptime_s, 0.0)
    counts_m = mu_pos * exptime_s
    return jnp.sum(m * (xlogy(counts_d, counts_m) - counts_m - gammaln(counts_d + 1.0)))


def log_likelihood_images(model_images, data: ImageData):
    """ln L of predicted images μ (tuple over bands) for `data`."""
    if data.diffuse is not None:    # "gaussian" (make_data): profiled over the diffuse light
        return -0.5 * sum(band_chi2(model_images, data))
    total = 0.0
    for k, mu in enumerate(model_images):
        var = None if data.variances is None else data.variances[k]
        total = total + band_log_likelihood(mu, data.images[k], data.masks[k], var,
                                            data.exptime_s[k], data.kind)
    return total


def log_likelihood(scene_model, data: ImageData, state: FitState):
    """ln L of a FitState."""
    return log_likelihood_images(predicted_images(scene_model, state), data)


def make_log_likelihood(scene_model, data: ImageData, param: Parametrization) -> Callable:
    """u ↦ ln L(state(u)): pure, ready for jax.jit / grad / vmap."""
    def f(u):
        return log_likelihood(scene_model, data, param.state(u))
    return f


def make_log_posterior(scene_model, data: ImageData, param: Parametrization, *,
                       log_prior: Optional[Callable] = None, jacobian: bool = True) -> Callable:
    """u ↦ ln L + ln p(state) [+ ln |dx/du|].

    log_prior: callable(FitState) → scalar, a density in physical parameters
        (None: flat in the physical free parameters, improper).
    jacobian: add the transform's log-Jacobian so that the density in u is that of a
        prior flat in x (what samplers need); MAP fits use jacobian=False (maximum
        likelihood / posterior mode in physical parameters).
    """
    def f(u):
        state = param.state(u)
        lp = log_likelihood(scene_model, data, state)
        if log_prior is not None:
            lp = lp + log_prior(state)
        if jacobian:
            lp = lp + param.log_abs_det_jacobian(u)
        return lp
    return f


def _whitened(model_images, data: ImageData) -> list:
    """Per band, √m (d − μ)/σ flattened."""
    return [(jnp.sqrt(m) * (d - mu) / jnp.sqrt(v)).ravel() for mu, d, m, v in
            zip(model_images, data.images, data.masks, data.variances)]


def _band_residuals(model_images, data: ImageData) -> list:
    """Per band, the whitened residual the solvers see: `_whitened`, or with a diffuse light
    `diffuse.profiled_residual` of it (K entries longer)."""
    parts = _whitened(model_images, data)
    if data.diffuse is None:
        return parts
    return [_diffuse.profiled_residual(b, p) for b, p in zip(data.diffuse, parts)]


def whitened_residuals(model_images, data: ImageData):
    """√m (d − μ)/σ over all bands, flattened: Gaussian ln L = −½ |r|² (fixed variances only),
    profiled over the diffuse light where there is one (`_band_residuals`)."""
    if data.kind != "gaussian":
        raise ConfigError("likelihood", data.kind, '"gaussian" (fixed variances) for residual fits')
    return jnp.concatenate(_band_residuals(model_images, data))


def diffuse_images(model_images, data: ImageData):
    """The best diffuse light per band for predicted images μ (zeros without one)."""
    if data.diffuse is None:
        return tuple(jnp.zeros_like(d) for d in data.images)
    return tuple(_diffuse.light(b, r, d.shape) for b, r, d in
                 zip(data.diffuse, _whitened(model_images, data), data.images))


def band_chi2(model_images, data: ImageData) -> list:
    """χ² per band of predicted images μ (fixed variances), profiled over the diffuse light."""
    return [jnp.sum(r * r) for r in _band_residuals(model_images, data)]


@eqx.filter_jit
def chi2_and_images(scene_model, data: ImageData, state: FitState):
    """(χ² per band, μ per band plus its best diffuse light) of a FitState (fixed variances):
    the one program that renders a state outside a fit. The counting's residuals and ln L
    (`auto`) and the observation fit's final images call it with the same model, data
    layout and clump capacity, so it compiles once for both."""
    mu = predicted_images(scene_model, state)
    if data.diffuse is None:
        return tuple(band_chi2(mu, data)), tuple(mu)
    # one solve for each band's diffuse coefficients, for both its χ² and its light
    both = [_diffuse.profiled_residual_and_light(b, r) for b, r in
            zip(data.diffuse, _whitened(mu, data))]
    return (tuple(jnp.sum(r * r) for r, _ in both),
            tuple(m + g.reshape(m.shape) for m, (_, g) in zip(mu, both)))


def make_residuals(scene_model, data: ImageData, param: Parametrization) -> Callable:
    """u ↦ whitened residual vector (for Levenberg–Marquardt)."""
    def f(u):
        return whitened_residuals(predicted_images(scene_model, param.state(u)), data)
    return f
