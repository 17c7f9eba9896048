"""Round exponential clumps as a mixture of 8 round Gaussians (`clump_pixels =
"exponential_mog"`): its error against the exact n = 1 pixel integrals, finiteness at
extremes of R_e and position in both dtypes, gradients, determinism, and the fits' choice.
The thorough sweep (R_e 1e-3 to 30 px, with PSFs) is benchmarks/bench_mog_accuracy.py."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from clumpylen_jax import gaussian_mixtures, profiles
from clumpylen_jax.errors import ConfigError
from clumpylen_jax.model import Accuracy, Band, build_model
from clumpylen_jax.model.clumps import RoundGaussianClumps
from clumpylen_jax.source import Clumps, Source

PIX = 0.03
MOG = Accuracy(clump_pixels="exponential_mog")
FIELD = ((-0.3, 0.3), (-0.3, 0.3))


def clumps(centers, re, flux=None, dtype=jnp.float64, n=1.0):
    c = np.asarray(centers, float).reshape(-1, 2)
    k = c.shape[0]
    f = np.ones((k, 1)) if flux is None else np.asarray(flux, float).reshape(k, -1)
    a = lambda v: jnp.asarray(v, dtype)  # noqa: E731
    return Clumps(a(c), a(f), a(np.broadcast_to(re, (k,))), a(np.full(k, n)), a(np.ones(k)),
                  a(np.zeros(k)))


def test_mixture_conserves_flux_and_keeps_its_half_light_radius():
    """Light fractions sum to 1; half the mixture's light lies within R_e (to the fit's
    stated enclosed-light error)."""
    n, a, s = gaussian_mixtures.round_mixture("exponential_mog")
    assert n == 1.0 and len(a) == len(s) == 8
    assert sum(a) == pytest.approx(1.0, abs=1e-15)
    half = sum(ak * (1 - np.exp(-1 / (2 * sk**2))) for ak, sk in zip(a, s))
    assert abs(half - 0.5) <= gaussian_mixtures.EXP_ERR_LIGHT


def test_model_matches_the_exact_exponential_pixel_integrals():
    """The whole model, no PSF (sub-grid = detector), three clumps of R_e 0.3, 2 and 5 px at
    off-grid centres against the exact fan integrals of every pixel: per pixel within 1e-3
    of each clump's peak pixel (measured ≤ 8.4e-4, bench_mog_accuracy.py)."""
    re = np.array([0.3, 2.0, 5.0]) * PIX
    centers = [[-0.1813, 0.1207], [0.0311, -0.0173], [0.12, 0.05]]
    src = Source(clumps=clumps(centers, re))
    model = build_model(src, [Band("X", PIX, 1.0)], field_arcsec=FIELD, accuracy=MOG)
    assert isinstance(model.clumps, RoundGaussianClumps)
    render = eqx.filter_jit(model.band_images)
    g = model.layouts[0].grid
    x, y = g.x_edges(), g.y_edges()

    def fan(c, r):
        return profiles.sersic_pixel_flux_exact(
            x[None, :-1], x[None, 1:], y[:-1, None], y[1:, None], flux=1.0, re_arcsec=r, n=1.0,
            q=1.0, pa_rad=0.0, center1=c[0], center2=c[1])
    exact = np.asarray(jax.jit(jax.vmap(fan))(jnp.asarray(centers), jnp.asarray(re)))
    for k in range(3):      # one clump at a time: the others' flux 0
        one = eqx.tree_at(lambda s: s.clumps.flux, src, jnp.eye(3)[:, k:k + 1])
        mog = np.asarray(render(one)[0])
        assert np.abs(mog - exact[k]).max() < 1e-3 * exact[k].max(), k
        assert mog.sum() == pytest.approx(exact[k].sum(), rel=1e-3), k


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_images_and_gradients_finite_at_extremes(dtype):
    """R_e 1e-3 px and 1e4 px, centres on a pixel edge and far off the grid, in one model:
    images and forward-mode gradients in centres, R_e and fluxes finite."""
    band = Band("X", PIX, 1.0, psf=np.ones((3, 3)) / 9, psf_pixel_arcsec=PIX)
    centers = [[0.01, 0.02], [0.0, 0.0], [900.0, -700.0], [0.45 * PIX, 0.0]]
    re = np.array([1e-3, 1e4, 1.0, 1e-3]) * PIX
    src = Source(clumps=clumps(centers, re, dtype=dtype))
    model = build_model(src, [band], field_arcsec=FIELD, accuracy=MOG, dtype=dtype)
    cl = src.clumps
    x0 = jnp.concatenate([cl.center_arcsec.ravel(), cl.re_arcsec, cl.flux[:, 0]])

    def image(x):
        return model.band_images(Source(clumps=Clumps(x[:8].reshape(4, 2), x[12:, None], x[8:12],
                                                      cl.n, cl.q, cl.pa_rad)))[0]

    img = jax.jit(image)(x0)
    jac = jax.jit(jax.jacfwd(image))(x0)
    assert img.dtype == dtype and jac.dtype == dtype
    assert np.all(np.isfinite(np.asarray(img))) and np.all(np.isfinite(np.asarray(jac)))


def test_gradient_matches_finite_differences_and_is_deterministic():
    """d image / d(centre, R_e, flux) against central differences (float64, R_e 1.3 px,
    Gaussian PSF), and two calls give the same bits."""
    psf = np.exp(-0.5 * (np.arange(-3, 4)[:, None] ** 2 + np.arange(-3, 4)[None, :] ** 2))
    band = Band("X", PIX, 1.0, psf=psf / psf.sum(), psf_pixel_arcsec=PIX)
    src = Source(clumps=clumps([[0.0137, -0.0291]], 1.3 * PIX))
    model = build_model(src, [band], field_arcsec=((-0.15, 0.15), (-0.15, 0.15)),
                        accuracy=MOG)
    cl = src.clumps

    def image(x):
        return model.band_images(Source(clumps=Clumps(x[None, :2], x[None, 3:4], x[2:3],
                                                      cl.n, cl.q, cl.pa_rad)))[0]

    x0 = jnp.asarray([0.0137, -0.0291, 1.3 * PIX, 2.0])
    f = jax.jit(image)
    assert np.array_equal(np.asarray(f(x0)), np.asarray(f(x0)))
    jac = np.asarray(jax.jit(jax.jacfwd(image))(x0))
    for k, h in enumerate([1e-6 * PIX, 1e-6 * PIX, 1e-6 * PIX, 1e-6]):
        e = np.zeros(4)
        e[k] = h
        fd = (np.asarray(f(x0 + e)) - np.asarray(f(x0 - e))) / (2 * h)
        assert np.abs(jac[..., k] - fd).max() < 1e-6 * np.abs(fd).max(), k


def test_build_refuses_other_clumps_and_the_fits_choose_it():
    src = Source(clumps=clumps([[0, 0], [0.1, 0]], PIX, n=0.5))
    with pytest.raises(ConfigError) as e:
        build_model(src, [Band("X", PIX, 1.0)], field_arcsec=FIELD, accuracy=MOG)
    assert e.value.value == "exponential_mog" and "n = 1, q = 1" in e.value.expected
    from clumpylen_jax.inference.auto import fit_clump_pixels
    assert fit_clump_pixels(1.0, True, lensed=False) == "exponential_mog"
    assert {fit_clump_pixels(1.0, False, lensed=False), fit_clump_pixels(1.0, True, lensed=True),
            fit_clump_pixels(2.0, True, lensed=False)} == {"sersic"}
