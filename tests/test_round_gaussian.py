"""The exact separable renderer of round Gaussian clumps (`clump_pixels = "round_gaussian"`)
against the Sérsic renderers at n = 0.5, at extremes of R_e and position, in both dtypes."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import integrate
from scipy.special import ndtr

from clumpylen_jax import profiles, render
from clumpylen_jax.errors import ConfigError
from clumpylen_jax.lensing.analytic import SIS
from clumpylen_jax.model import Accuracy, Band, build_model
from clumpylen_jax.model.clumps import RoundGaussianClumps, UnlensedClumps
from clumpylen_jax.pixels import Grid
from clumpylen_jax.source import Clumps, Sersic, Source

PIX = 0.03
GAUSS = Accuracy(clump_pixels="round_gaussian")


def clumps(centers, re, flux=None, dtype=jnp.float64, n=0.5, q=1.0):
    c = np.asarray(centers, float).reshape(-1, 2)
    k = c.shape[0]
    f = np.ones((k, 1)) if flux is None else np.asarray(flux, float).reshape(k, -1)
    a = lambda v: jnp.asarray(v, dtype)  # noqa: E731
    return Clumps(a(c), a(f), a(np.broadcast_to(re, (k,))), a(np.full(k, n)), a(np.full(k, q)),
                  a(np.zeros(k)))


def separable_image(grid, center, re):
    """Unit-flux image [ny, nx] of one round Gaussian from the 1-D kernel."""
    sigma = jnp.asarray([re / np.sqrt(2 * float(profiles.sersic_b(0.5)))])
    fx = render.gaussian_pixel_fractions(grid.x_edges(), jnp.asarray([center[0]]), sigma)[0]
    fy = render.gaussian_pixel_fractions(grid.y_edges(), jnp.asarray([center[1]]), sigma)[0]
    return np.outer(np.asarray(fy), np.asarray(fx))


def fan_images(grid, centers, res):
    """The same from the Sérsic renderer's exact-pixel fan integral, every pixel, for each of
    the (centre, R_e) pairs: [K, ny, nx] in one compiled call."""
    x, y = grid.x_edges(), grid.y_edges()

    def fan(c, r):
        return profiles.sersic_pixel_flux_exact(
            x[None, :-1], x[None, 1:], y[:-1, None], y[1:, None], flux=1.0, re_arcsec=r, n=0.5,
            q=1.0, pa_rad=0.0, center1=c[0], center2=c[1])
    return np.asarray(jax.jit(jax.vmap(fan))(jnp.asarray(centers, float), jnp.asarray(res, float)))


# R_e 1e-3 to 50 pixels; centres on a pixel corner, off-grid, just outside and far outside
CASES = [(re_pix, c) for re_pix in (1e-3, 0.05, 0.3, 1.0, 3.0, 10.0, 50.0)
         for c in ((0.0, 0.0), (0.3111, 0.4102), (-0.2, 0.5), (0.161, 0.39), (0.5, 1.5))]


def test_sigma_is_the_half_light_radius():
    """σ per R_e from b(0.5): half the light of a 2-D Gaussian within R_e, i.e.
    1 − exp(−R_e²/2σ²) = ½."""
    (s,) = RoundGaussianClumps.build(Source(clumps=clumps([0, 0], PIX))).sigma_per_re
    assert 1 - np.exp(-1 / (2 * s**2)) == pytest.approx(0.5, abs=1e-15)


def test_cell_averaged_lensed_clumps_render_inside_a_trace():
    """The lensed rays' cell-averaged Gaussian clumps (`render.gaussian_clumps_cell_brightness`)
    take σ/R_e from b(0.5) when they are traced; that used to call the jitted `sersic_b` and
    take float() of a tracer (ConcretizationTypeError: every SIS recovery fit with the
    diffraction PSF stopped there). Jitted and eager give the same bits."""
    cl = clumps([[0.01, -0.02]], PIX)
    x1, x2 = jnp.linspace(-0.05, 0.05, 7), jnp.linspace(-0.04, 0.04, 7)
    cov = (jnp.full(7, 1e-6), jnp.zeros(7), jnp.full(7, 1e-6))
    eager = render.gaussian_clumps_cell_brightness(cl, x1, x2, cov)
    jitted = jax.jit(render.gaussian_clumps_cell_brightness)(cl, x1, x2, cov)
    assert np.all(np.isfinite(np.asarray(jitted)))
    np.testing.assert_array_equal(np.asarray(jitted), np.asarray(eager))


def test_separable_matches_the_fan_integral_everywhere():
    """Per pixel, against the Sérsic renderer's exact fan integral at n = 0.5 over a whole
    31 × 27 grid: the fan's angular quadrature is what limits the agreement (≤ 5.2e-8 of
    the clump's flux measured, at R_e = 0.3 px); 1e-7 fails if either is wrong anywhere,
    and the sums (light on the grid) agree to 1e-9."""
    grid = Grid(0.0, 0.0, PIX, 31, 27)
    fans = fan_images(grid, [c for _, c in CASES], [re_pix * PIX for re_pix, _ in CASES])
    for (re_pix, c), fan in zip(CASES, fans):
        sep = separable_image(grid, c, re_pix * PIX)
        assert np.abs(sep - fan).max() < 1e-7, (re_pix, c)
        assert sep.sum() == pytest.approx(fan.sum(), abs=1e-9), (re_pix, c)


def test_separable_is_exact_where_the_fan_integral_is_least():
    """Where the two differ most, adaptive 2-D quadrature (scipy dblquad, 1e-13) sides with
    the separable integral to 1e-12."""
    grid = Grid(0.0, 0.0, PIX, 31, 27)
    re, c = 0.3 * PIX, (0.3111, 0.4102)
    sep, fan = separable_image(grid, c, re), fan_images(grid, [c], [re])[0]
    j, i = np.unravel_index(np.argmax(np.abs(sep - fan)), sep.shape)
    s = re / np.sqrt(2 * np.log(2))
    x, y = grid.x_edges(), grid.y_edges()
    ref, _ = integrate.dblquad(
        lambda yy, xx: np.exp(-((xx - c[0])**2 + (yy - c[1])**2) / (2 * s * s)) / (2 * np.pi * s * s),
        x[i], x[i + 1], y[j], y[j + 1], epsabs=1e-15, epsrel=1e-13)
    assert abs(sep[j, i] - ref) < 1e-12
    assert abs(fan[j, i] - ref) > 1e-9        # the point of the check: the fan is the looser one


def test_far_tail_keeps_relative_precision():
    """A pixel 30 σ from the centre: erfc of both edges, not 1 − 1 (which gives 0)."""
    edges = np.array([30.0, 31.0])
    f = float(render.gaussian_pixel_fractions(edges, jnp.zeros(1), jnp.ones(1))[0, 0])
    from scipy.special import ndtr
    ref = float(ndtr(-30.0) - ndtr(-31.0))
    assert ref > 0 and f == pytest.approx(ref, rel=1e-12)
    g = float(render.gaussian_pixel_fractions(-edges[::-1], jnp.zeros(1), jnp.ones(1))[0, 0])
    assert g == pytest.approx(ref, rel=1e-12)


def test_model_matches_the_sersic_stamp_renderer():
    """The light each renderer hands the PSF on a 3× sub-grid, clumps of R_e 0.3, 2 and 8 px
    (the last partly off the field), the Sérsic stamps at a converged setting (order 6,
    exact core 7, stamps holding 1 − 1e-9 of the light): the same pixel integrals. Measured:
    per sub-pixel 1.6e-7 of the total flux (the stamps' sampling: 2e-8 once the PSF and
    binning average it), the sums 6e-14; asserted 3e-7 and 1e-12. (Through
    the PSF the two differ: the Gaussians also carry where in each sub-pixel their light
    lies, `test_psf_carries_the_light_within_each_sub_pixel`.)"""
    psf = np.exp(-0.5 * (np.arange(-4, 5)[:, None] ** 2 + np.arange(-4, 5)[None, :] ** 2) / 1.5**2)
    band = Band("X", PIX, 1.0, psf=psf / psf.sum(), psf_pixel_arcsec=PIX / 3)
    src = Source(clumps=clumps([[0.0113, -0.0207], [0.21, 0.05], [0.6, -0.33]],
                               np.array([0.3, 2.0, 8.0]) * PIX, flux=[[1.0], [2.0], [0.5]]))
    field = ((-0.62, 0.62), (-0.5, 0.5))
    fine = Accuracy(source_order=6, exact_core=7, stamp_flux_fraction=1 - 1e-9, psf_oversampling=3)
    ref_model = build_model(src, [band], field_arcsec=field, accuracy=fine)
    new_model = build_model(src, [band], field_arcsec=field,
                            accuracy=Accuracy(psf_oversampling=3, clump_pixels="round_gaussian"))
    assert isinstance(ref_model.clumps, UnlensedClumps)
    assert isinstance(new_model.clumps, RoundGaussianClumps)
    sub = ref_model.layouts[0].sub_grid
    assert new_model.layouts[0].sub_grid == sub

    def light(model):
        part = model.clumps.subgrid_light(src, {sub: 0})[sub]
        return part.add_band(jnp.zeros(sub.shape), 0)
    ref = np.asarray(eqx.filter_jit(light)(ref_model))
    new = np.asarray(eqx.filter_jit(light)(new_model))
    total = 3.5
    assert np.abs(new - ref).max() < 3e-7 * total
    assert new.sum() == pytest.approx(ref.sum(), abs=1e-12 * total)


def _gaussian_psf(pixel, sigma, effective, step=0.005, n=121):
    """A Gaussian PSF of σ `sigma` (arcsec) sampled at `step`: optical (each sample its
    pixel's area average) or effective (× a detector pixel `pixel`: samples of the box
    convolution)."""
    x = (np.arange(n) - (n - 1) / 2) * step
    if effective:
        f = ndtr((x + pixel / 2) / sigma) - ndtr((x - pixel / 2) / sigma)
    else:
        f = np.diff(ndtr(np.append(x - step / 2, x[-1] + step / 2) / sigma))
    return np.outer(f, f)


@pytest.mark.parametrize("effective", [False, True])
def test_psf_carries_the_light_within_each_sub_pixel(effective):
    """A clump smaller than a sub-pixel, drawn through a Gaussian PSF (σ 1.1 px, 0.05" px),
    against the analytic answer (the pixel integrals of the Gaussian of σ² = σ_clump² +
    σ_PSF²). Without the light's moments, its image stayed put while its centre moved within
    a sub-pixel and jumped at the edges: at 1 sub-pixel per pixel, 35 % of the peak off at
    R_e 0.002", 3.9 % at 0.05", and centroid slopes 0–8.6 (benchmarks: a fit could not
    place an unresolved clump within its pixel, and sampling RXJ1131 failed on it).
    Measured now at 1 sub-pixel: 1.25 / 0.25 / 0.16 % (optical) and 1.25 / 0.22 / 0.05 %
    (effective) at R_e 0.002 / 0.02 / 0.05"; at 3: ≤ 0.16 % (optical, the PSF image's own
    sampling) and ≤ 0.03 % (effective); every centroid slope 1.000."""
    pix = 0.05
    sigma_psf = 1.1 * pix
    grid = Grid.covering((-0.8, 0.8), (-0.8, 0.8), pix)
    band = Band("F", pix, 1000.0, psf=_gaussian_psf(pix, sigma_psf, effective),
                psf_pixel_arcsec=0.005, psf_effective=effective)
    xs = (np.linspace(-0.5, 0.5, 11) * pix + 0.0123)
    centers = (0.5 * (grid.x_edges()[1:] + grid.x_edges()[:-1]))
    limits = {1: {0.002: 0.013, 0.02: 0.003, 0.05: 0.002},
              3: {0.002: 0.002, 0.02: 0.002, 0.05: 0.002}}
    for s, by_re in limits.items():
        for re, limit in by_re.items():
            model = build_model(Source(clumps=clumps([0.0, 0.0], re)), [band], grids=[grid],
                                accuracy=Accuracy(clump_pixels="round_gaussian",
                                                  psf_oversampling=s))
            draw = eqx.filter_jit(lambda m, src: m.band_images(src)[0])
            sig = np.hypot(re / np.sqrt(2 * float(profiles.sersic_b(0.5))), sigma_psf)
            err, cx = [], []
            for x0 in xs:
                img = np.asarray(draw(model, Source(clumps=clumps([x0, 0.004], re))))
                exact = np.outer(np.diff(ndtr((grid.y_edges() - 0.004) / sig)),
                                 np.diff(ndtr((grid.x_edges() - x0) / sig)))
                err.append(np.abs(img - exact).max() / exact.max())
                cx.append(np.sum(img.sum(0) * centers) / img.sum())
            assert max(err) < limit, (s, re, max(err))
            np.testing.assert_allclose(np.diff(cx) / np.diff(xs), 1.0, atol=2e-3)


def test_flux_conserved_for_a_clump_well_inside():
    grid = Grid(0.0, 0.0, PIX, 41, 41)
    img = separable_image(grid, (20.37 * PIX, 19.81 * PIX), 2.0 * PIX)
    assert img.sum() == pytest.approx(1.0, abs=1e-13)
    assert img.min() >= 0


def test_moments_match_quadrature():
    """`render.gaussian_pixel_moments` (fraction, first and second moments about each pixel's
    centre, in pixels) against adaptive quadrature, for σ from 1e-3 to 30 pixels and
    centres inside, on an edge and 40 pixels out."""
    edges = np.arange(-20, 21) * 0.05
    for sigma_pix in (1e-3, 0.3, 1.0, 30.0):
        for mu_pix in (0.0, 0.5, 3.217, -40.0):
            mu, sig = mu_pix * 0.05, sigma_pix * 0.05
            frac, m1, m2 = (np.asarray(a)[0] for a in render.gaussian_pixel_moments(
                edges, jnp.asarray([mu]), jnp.asarray([sig])))
            for j in range(edges.size - 1):
                a, b = edges[j], edges[j + 1]
                c = 0.5 * (a + b)
                g = lambda x: np.exp(-0.5 * ((x - mu) / sig) ** 2) / (np.sqrt(2 * np.pi) * sig)  # noqa: E731
                pts = [mu] if a < mu < b else None
                want = [integrate.quad(lambda x: g(x) * ((x - c) / 0.05) ** p, a, b, points=pts,
                                       epsabs=1e-14, epsrel=1e-10)[0] for p in (0, 1, 2)]
                np.testing.assert_allclose([frac[j], m1[j], m2[j]], want, rtol=1e-8, atol=1e-14)


def test_moments_of_wide_gaussians_series_and_float32():
    """Above `render.SERIES_SIGMA_PIXELS` the moments are the Taylor series of g about each
    pixel's centre: within 1e-5 of the largest M2 of adaptive quadrature just above the
    switch (σ 6.5 px), and in float32 within 1e-5 of float64 for σ 8 and 42 px (the exact
    form's shift to the centre cancels there: 2e-3 at 42 px before the series)."""
    edges = np.arange(-30, 31) * 0.05
    for sigma_pix, mu_pix in ((6.5, 0.3), (6.5, 11.7)):
        mu, sig = mu_pix * 0.05, sigma_pix * 0.05
        got = [np.asarray(a)[0] for a in render.gaussian_pixel_moments(
            edges, jnp.asarray([mu]), jnp.asarray([sig]))]
        g = lambda x: np.exp(-0.5 * ((x - mu) / sig) ** 2) / (np.sqrt(2 * np.pi) * sig)  # noqa: E731
        for j in range(0, edges.size - 1, 7):
            a, b = edges[j], edges[j + 1]
            c = 0.5 * (a + b)
            want = [integrate.quad(lambda x: g(x) * ((x - c) / 0.05) ** p, a, b,
                                   epsabs=1e-15, epsrel=1e-11)[0] for p in (1, 2)]
            np.testing.assert_allclose([got[1][j], got[2][j]], want, rtol=0,
                                       atol=1e-5 * np.abs(got[2]).max())
    for sigma_pix in (8.0, 42.0):
        mu = jnp.asarray([3.37 * 0.05])
        m64 = [np.asarray(a) for a in render.gaussian_pixel_moments(
            edges, mu, jnp.asarray([sigma_pix * 0.05]))]
        m32 = [np.asarray(a, float) for a in render.gaussian_pixel_moments(
            edges, mu.astype(jnp.float32),
            jnp.asarray([sigma_pix * 0.05], jnp.float32))]
        for a, b in zip(m32[1:], m64[1:]):
            assert np.abs(a - b).max() < 1e-5 * np.abs(m64[2]).max(), sigma_pix


def test_moments_move_light_and_add_none():
    """Through a PSF with the light's moments, a compact clump well inside the field keeps
    its flux: every kernel that carries the moments sums to 0 (each is a difference of
    kernels of unit sum)."""
    psf = _gaussian_psf(PIX, 1.2 * PIX, False, step=PIX / 5, n=41)
    band = Band("X", PIX, 1.0, psf=psf, psf_pixel_arcsec=PIX / 5)
    for s in (1, 3):
        src = Source(clumps=clumps([[0.0137, -0.0071]], 0.1 * PIX))
        model = build_model(src, [band], grids=[Grid(-0.6, -0.6, PIX, 40, 40)],
                            accuracy=Accuracy(clump_pixels="round_gaussian", psf_oversampling=s))
        ft = np.asarray(model.layouts[0].moment_ft)
        assert ft[0, 0, 0].real == pytest.approx(1.0, abs=1e-14)        # the PSF's sum
        np.testing.assert_allclose(ft[1:, 0, 0].real, 0.0, atol=1e-14)  # the moments' kernels
        img = np.asarray(eqx.filter_jit(model.band_images)(src)[0])
        assert img.sum() == pytest.approx(1.0, abs=1e-12)


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
@pytest.mark.parametrize("re_pix,center", [(1e-3, (0.01, 0.02)), (1e4, (0.0, 0.0)),
                                           (1.0, (900.0, -700.0)), (1e-3, (0.45, 0.0))])
def test_images_and_gradients_finite_at_extremes(dtype, re_pix, center):
    """R_e 1e-3 px and 1e4 px, centres far off the grid and on a pixel edge: images and
    forward- and reverse-mode gradients in centre, R_e and flux finite in float32 and
    float64 (the PSF carries the light's moments here)."""
    psf = np.ones((3, 3)) / 9
    band = Band("X", PIX, 1.0, psf=psf, psf_pixel_arcsec=PIX)
    src = Source(clumps=clumps([center], re_pix * PIX, dtype=dtype))
    model = build_model(src, [band], field_arcsec=((-0.3, 0.3), (-0.3, 0.3)), accuracy=GAUSS,
                        dtype=dtype)
    x0 = jnp.asarray([center[0], center[1], re_pix * PIX, 1.0], dtype)

    def image(x):
        cl = src.clumps
        s = Source(clumps=Clumps(x[None, :2], x[None, 3:4], x[2:3], cl.n, cl.q, cl.pa_rad))
        return model.band_images(s)[0]

    img = jax.jit(image)(x0)
    jac = jax.jit(jax.jacfwd(image))(x0)
    grad = jax.jit(jax.grad(lambda x: jnp.sum(image(x) ** 2)))(x0)
    assert model.layouts[0].moment_ft is not None
    assert img.dtype == dtype and jac.dtype == dtype
    for a in (img, jac, grad):
        assert np.all(np.isfinite(np.asarray(a)))


def test_gradient_matches_finite_differences():
    """d image / d(centre, R_e) against central differences (float64, R_e = 1.3 px)."""
    grid = Grid(0.0, 0.0, PIX, 15, 13)
    s_per_re = 1 / np.sqrt(2 * np.log(2))

    def image(x):
        sig = x[2:3] * s_per_re
        fx = render.gaussian_pixel_fractions(grid.x_edges(), x[0:1], sig)[0]
        fy = render.gaussian_pixel_fractions(grid.y_edges(), x[1:2], sig)[0]
        return jnp.outer(fy, fx)

    x0 = jnp.asarray([7.3 * PIX, 5.9 * PIX, 1.3 * PIX])
    jac = np.asarray(jax.jacfwd(image)(x0))
    h = 1e-6 * PIX
    for k in range(3):
        e = np.zeros(3)
        e[k] = h
        fd = (np.asarray(image(x0 + e)) - np.asarray(image(x0 - e))) / (2 * h)
        assert np.abs(jac[..., k] - fd).max() < 1e-6 * np.abs(fd).max()


def test_build_refuses_other_clumps_and_lensed_scenes():
    band = Band("X", PIX, 1.0)
    field = ((-0.3, 0.3), (-0.3, 0.3))
    for kw, what in (({"n": 1.0}, "n = 1"), ({"q": 0.7}, "q = 0.7")):
        src = Source(clumps=clumps([[0, 0], [0.1, 0]], PIX, **kw))
        with pytest.raises(ConfigError) as e:
            build_model(src, [band], field_arcsec=field, accuracy=GAUSS)
        assert e.value.setting == "render.accuracy.clump_pixels"
        assert e.value.value == "round_gaussian"
        assert "n = 0.5, q = 1" in e.value.expected and what in e.value.expected
    with pytest.raises(ConfigError) as e:
        build_model(Source(clumps=clumps([[0, 0]], PIX)), [band], lens=SIS(1.0, jnp.zeros(2)),
                    field_arcsec=((-2, 2), (-2, 2)), accuracy=GAUSS)
    assert e.value.setting == "render.accuracy.clump_pixels" and "lensed" in e.value.expected
    with pytest.raises(ConfigError) as e:
        Accuracy(clump_pixels="gaussian").validate()
    assert e.value.setting == "render.accuracy.clump_pixels"


def test_default_is_the_sersic_renderer():
    """The simulator's default is unchanged: Sérsic stamps unless asked."""
    src = Source(bulge=Sersic(jnp.ones(1), jnp.asarray(0.1), jnp.asarray(1.0), jnp.asarray(1.0),
                              jnp.asarray(0.0), jnp.zeros(2)),
                 clumps=clumps([[0, 0]], PIX))
    m = build_model(src, [Band("X", PIX, 1.0)], field_arcsec=((-0.3, 0.3), (-0.3, 0.3)))
    assert Accuracy().clump_pixels == "sersic" and isinstance(m.clumps, UnlensedClumps)


def test_fit_factories_choose_the_renderer_from_the_clump_options():
    """Round n = 0.5 clumps of an unlensed fit: the separable renderer; an elliptical shape,
    another n or a lens: the Sérsic stamps (observations.fit.make_model_factory end to end)."""
    from clumpylen_jax.inference.auto import fit_clump_pixels
    from clumpylen_jax.observations import FitOptions
    from clumpylen_jax.observations.fit import make_model_factory
    from clumpylen_jax.observations.frame import BandFrame, fit_frame
    assert fit_clump_pixels(0.5, True, lensed=False) == "round_gaussian"
    assert {fit_clump_pixels(0.5, False, lensed=False), fit_clump_pixels(0.7, True, lensed=False),
            fit_clump_pixels(0.5, True, lensed=True)} == {"sersic"}

    class _Ob:   # what make_model_factory reads of an observation
        name, psf = "F150W", None

    frame = fit_frame([BandFrame((20, 20), PIX)], ["F150W"])
    src = Source(bulge=Sersic(jnp.ones(1), jnp.asarray(0.1), jnp.asarray(1.0), jnp.asarray(1.0),
                              jnp.asarray(0.0), jnp.zeros(2)), clumps=clumps([[0, 0]], PIX))
    for opts, kind in ((FitOptions(clump_n=0.5), RoundGaussianClumps),
                       (FitOptions(clump_n=0.5, clump_shape="elliptical"), UnlensedClumps)):
        assert isinstance(make_model_factory([_Ob()], frame, opts)(src).clumps, kind)


_MOCK_SCENE = """
[scene]
name = "round-or-not"
seed = 3
z_source = 2.0

[source.bulge]
magnitudes = {{ F200W = 24.0 }}
re_arcsec = 0.1
n = 1.0

[source.clumps]
catalog = "clumps.ecsv"
sersic_n = 0.5
q_range = {q_range}

[render]
source_pixel_arcsec = 0.01
lens_pixel_arcsec = 0.01
field_arcsec = {{ x = [-0.3, 0.3], y = [-0.3, 0.3] }}
accuracy = "fast"

[[bands]]
instrument = "JWST/NIRCam"
filter = "F200W"
exptime_s = 1000.0
psf = "none"
"""


def test_mock_fits_draw_clumps_round_only_where_the_scene_says_they_are(tmp_path):
    """`clumpylen fit` on a mock: the scene's clump law (q_range), never its catalogue, says
    whether clumps may be elliptical. q_range [1, 1]: the separable round renderer and no
    shape moves; the default [0.3, 1]: the Sérsic stamps, and the shape moves try each clump
    elliptical (fitted round, elliptical clumps' R_e pulls missed ±3 for 7 of 46,
    benchmarks/results/unl5_round.md, unl5_shapes.md)."""
    from astropy.table import Table

    from clumpylen_jax import pipeline, scene as sc
    from clumpylen_jax.inference import auto
    from clumpylen_jax.inference.auto_run import make_model_factory, scene_options

    Table({"beta1_arcsec": [0.05], "beta2_arcsec": [0.0], "re_arcsec": [0.02], "q": [1.0],
           "pa_rad": [0.3], "mag_F200W": [25.0]}).write(tmp_path / "clumps.ecsv",
                                                        format="ascii.ecsv")
    for q_range, kind, round_clumps in (("[1.0, 1.0]", RoundGaussianClumps, True),
                                        ("[0.3, 1.0]", UnlensedClumps, False)):
        path = tmp_path / "scene.toml"
        path.write_text(_MOCK_SCENE.format(q_range=q_range))
        prep = pipeline.prepare(sc.load_scene(str(path)))
        opts = scene_options(prep.scene).validate()
        assert opts.round_clumps is round_clumps and opts.clump_n == 0.5
        model = make_model_factory(prep, opts)(prep.source)
        assert isinstance(model.clumps, kind)
        assert auto._shape_moves(model, opts) is not round_clumps
