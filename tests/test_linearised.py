"""Local lens linearisation of clumps ("hybrid" source mode) against exact references."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import clumpylen_jax
from clumpylen_jax import profiles
from clumpylen_jax.lensing.analytic import SIS
from clumpylen_jax.lensing.linearised import ClumpImages, lensed_clumps
from clumpylen_jax.lensing.tracing import point_images, trace_corners
from clumpylen_jax.model import Accuracy, Band, build_model
from clumpylen_jax.pixels import Grid
from clumpylen_jax.source import Clumps, Source

f64 = lambda x: jnp.asarray(x, jnp.float64)  # noqa: E731


def _clumps(rng, k):
    return Clumps(f64(rng.uniform(-1, 1, (k, 2))), f64(rng.uniform(1, 3, (k, 2))),
                  f64(rng.uniform(0.001, 0.01, k)), f64(rng.uniform(0.3, 4, k)),
                  f64(rng.uniform(0.1, 1, k)), f64(rng.uniform(-3, 3, k)))


def test_lensed_clump_is_the_clump_through_the_linear_map():
    """S_lensed(θ) = S(β0 + A (θ − θ0)) for random Jacobians (both parities), shapes, moves."""
    rng = np.random.default_rng(3)
    k = 12
    cl = _clumps(rng, k)
    A = rng.normal(0, 1, (k, 2, 2)) + 0.3 * np.eye(2)
    images = ClumpImages(jnp.arange(k), f64(rng.normal(0, 1, (k, 2))),
                         cl.center_arcsec + f64(rng.normal(0, 1e-3, (k, 2))), f64(A))
    lens = lensed_clumps(cl, images)
    t = np.asarray(lens.center_arcsec)[:, None, :] + rng.normal(0, 0.01, (k, 50, 2))
    # the true mapping, linear about the build-time point (θ0, β0)
    beta = (np.asarray(images.beta0)[:, None, :]
            + np.einsum("kab,ksb->ksa", A, t - np.asarray(images.theta0)[:, None, :]))
    for j in range(k):
        kw = dict(n=cl.n[j], q=cl.q[j], pa_rad=cl.pa_rad[j])
        want = profiles.sersic_brightness(beta[j, :, 0], beta[j, :, 1], flux=cl.flux[j, 0],
                                          re_arcsec=cl.re_arcsec[j], center1=cl.center_arcsec[j, 0],
                                          center2=cl.center_arcsec[j, 1], **kw)
        got = profiles.sersic_brightness(t[j, :, 0], t[j, :, 1], flux=lens.flux[j, 0],
                                         re_arcsec=lens.re_arcsec[j], n=lens.n[j], q=lens.q[j],
                                         pa_rad=lens.pa_rad[j], center1=lens.center_arcsec[j, 0],
                                         center2=lens.center_arcsec[j, 1])
        np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-12 * float(np.max(want)))
    mu = 1 / np.abs(np.linalg.det(A))
    np.testing.assert_allclose(lens.flux[:, 1] / cl.flux[:, 1], mu, rtol=1e-12)


def test_lensed_clump_gradients_finite_for_circular_images():
    """A round clump behind A = c·I has a circular image (degenerate eigenvalues)."""
    cl = Clumps(f64([[0.0, 0.0]]), f64([[1.0]]), f64([0.01]), f64([1.0]), f64([1.0]), f64([0.0]))
    images = ClumpImages(jnp.arange(1), f64([[1.0, 2.0]]), f64([[0.0, 0.0]]), f64([np.eye(2) * 0.5]))

    def total(c):
        lens = lensed_clumps(c, images)
        return jnp.sum(lens.re_arcsec + lens.q + lens.pa_rad + lens.flux[:, 0]
                       + lens.center_arcsec.sum())

    g = jax.grad(total)(cl)
    assert all(np.all(np.isfinite(x)) for x in jax.tree_util.tree_leaves(g))
    lens = lensed_clumps(cl, images)
    np.testing.assert_allclose([lens.re_arcsec[0], lens.q[0]], [0.02, 1.0], rtol=1e-12)


def test_point_images_on_an_sis():
    """Images of β behind an SIS at β ± θ_E (on the β axis), with μ± = 1 ± θ_E/β."""
    theta_e, beta = 1.0, 0.3
    grid = Grid.covering((-1.6, 1.6), (-0.4, 0.4), 0.01)
    b1, b2 = trace_corners(SIS(f64(theta_e), f64([0.0, 0.0])), grid)
    rows, cols = (a.ravel() for a in np.meshgrid(np.arange(grid.ny), np.arange(grid.nx),
                                                 indexing="ij"))
    idx, theta, A = point_images(b1, b2, grid, rows, cols, np.array([[beta, 0.0123]]))
    keep = np.abs(theta[:, 0]) > 0.05        # drop the SIS centre's spurious μ→0 image
    theta, A = theta[keep], A[keep]
    order = np.argsort(theta[:, 0])
    theta, A = theta[order], A[order]
    r = np.hypot(beta, 0.0123)
    np.testing.assert_allclose(np.hypot(*theta.T), [theta_e - r, theta_e + r], rtol=1e-4)
    mu = 1 / np.linalg.det(A)
    np.testing.assert_allclose(np.abs(mu), [theta_e / r - 1, theta_e / r + 1], rtol=2e-3)
    assert mu[0] < 0 < mu[1]


def _cluster_scene():
    """Clumps behind an SIS with θ_E = 20" (a cluster's curvature); one on the point caustic,
    whose ring image crosses the field on the critical curve."""
    rng = np.random.default_rng(0)
    # the tangential stretch is ~20: β2 = ±0.01" lands 0.2" off the axis
    centers = np.array([[1.0, 0.01], [0.8, -0.004], [1.2, 0.004], [0.003, 0.0]])
    k = len(centers)
    cl = Clumps(f64(centers), f64(rng.uniform(1, 3, (k, 1))), f64([0.004, 0.0015, 0.003, 0.004]),
                f64([0.5, 1.0, 0.5, 0.5]), f64([0.5, 0.8, 1.0, 0.6]), f64([0.3, 1.0, 2.0, 0.0]))
    lens = SIS(f64(20.0), f64([0.0, 0.0]))
    kw = dict(lens=lens, field_arcsec=((19.6, 21.5), (-0.5, 0.6)), lens_pixel_arcsec=0.004,
              source_pixel_arcsec=0.0005)
    return Source(clumps=cl), [Band("X", 0.03, 1.0)], kw


@pytest.fixture(scope="module")
def cluster_hybrid():
    """The cluster scene and its hybrid model, built once for the tests that use it."""
    src, bands, kw = _cluster_scene()
    return src, bands, kw, build_model(src, bands, accuracy=Accuracy(source_mode="hybrid"), **kw)


def _only(src, j):
    """The source with every clump but j dark (same structure: the same compiled model)."""
    keep = (jnp.arange(src.clumps.count) == j)[:, None]
    return Source(clumps=eqx.tree_at(lambda c: c.flux, src.clumps, src.clumps.flux * keep))


def test_hybrid_linearises_off_caustic_clumps_and_traces_the_caustic_one(cluster_hybrid):
    """The default-run version of the test below (which compares against a converged
    analytic reference of 10² rays per lens pixel, behind `slow`): the same hybrid model
    linearises the three clumps off the caustic, their magnifications are the SIS's
    1 + θ_E/β, each linearised image carries flux × that magnification, and the clump on
    the caustic is rendered exactly as in grid mode."""
    src, bands, kw, hyb = cluster_hybrid
    grid = build_model(src, bands, accuracy=Accuracy(source_mode="grid"), **kw)
    assert set(np.asarray(hyb.lin_images.clump_index).tolist()) == {0, 1, 2}
    mag = np.asarray(eqx.filter_jit(lambda m, s: m.clump_magnifications(s))(hyb, src))
    beta = np.hypot(*np.asarray(src.clumps.center_arcsec[:3]).T)
    np.testing.assert_allclose(mag[:3], 1 + 20.0 / beta, rtol=1e-3)
    f = eqx.filter_jit(lambda m, s: m.band_images(s)[0])
    flux = np.asarray(src.clumps.flux)[:, 0]
    for j in range(3):
        h = np.asarray(f(hyb, _only(src, j)))
        assert abs(h.sum() / (flux[j] * mag[j]) - 1) < 2e-3, j
    s = _only(src, 3)
    h = np.asarray(f(hyb, s))
    np.testing.assert_allclose(h, np.asarray(f(grid, s)), rtol=1e-10, atol=1e-12 * h.max())


@pytest.mark.slow
def test_hybrid_matches_analytic_reference_and_traces_caustic_clumps():
    src, bands, kw = _cluster_scene()
    # converged reference: every clump at every ray, 10² rays per 4 mas lens pixel
    ref = build_model(src, bands, accuracy=Accuracy(source_mode="analytic", lens_subsampling=10),
                      **kw)
    hyb = build_model(src, bands, accuracy=Accuracy(source_mode="hybrid"), **kw)
    grid = build_model(src, bands, accuracy=Accuracy(source_mode="grid"), **kw)
    linearised = set(np.asarray(hyb.lin_images.clump_index).tolist())
    assert linearised == {0, 1, 2}               # the clump on the caustic is ray traced
    f = eqx.filter_jit(lambda m, s: m.band_images(s)[0])
    for j in range(4):
        s = _only(src, j)
        a, h = np.asarray(f(ref, s)), np.asarray(f(hyb, s))
        if j in linearised:
            # the linear map is exact to the tolerance: per-clump flux and pixels
            assert abs(h.sum() / a.sum() - 1) < 1e-3, j
            assert np.max(np.abs(h - a)) < 0.01 * a.max(), j
        else:
            # the traced clump is rendered as in grid mode; the 0.5 mas source grid's
            # bilinear smoothing costs ~1 % here (it converges as pixel², measured)
            np.testing.assert_allclose(h, np.asarray(f(grid, s)), rtol=1e-10,
                                       atol=1e-12 * h.max())
            assert abs(h.sum() / a.sum() - 1) < 0.015
    mag = np.asarray(eqx.filter_jit(lambda m, s: m.clump_magnifications(s))(hyb, src))
    # SIS: one image in this field for β < θ_E, |μ+| = 1 + θ_E/β
    beta = np.hypot(*np.asarray(src.clumps.center_arcsec[:3]).T)
    np.testing.assert_allclose(mag[:3], 1 + 20.0 / beta, rtol=1e-3)
    lp = np.asarray(eqx.filter_jit(lambda m, s: m.lens_plane(s))(hyb, src))[0]
    lpa = np.asarray(eqx.filter_jit(lambda m, s: m.lens_plane(s))(grid, src))[0]
    assert abs(lp.sum() / lpa.sum() - 1) < 2e-3


@pytest.mark.slow  # 40-80 s: the thorough profile (pytest -m slow); keeps make test under 10 min
def test_hybrid_gradients_match_finite_differences(cluster_hybrid):
    src, bands, kw, m = cluster_hybrid
    data = eqx.filter_jit(lambda m, s: m.band_images(s)[0])(m, src) * 1.1

    def chi2(center, re, q):
        cl = eqx.tree_at(lambda c: (c.center_arcsec, c.re_arcsec, c.q), src.clumps,
                         (center, re, q))
        img = m.band_images(Source(clumps=cl))[0]
        return jnp.sum((img - data) ** 2)

    f = jax.jit(jax.value_and_grad(chi2, argnums=(0, 1, 2)))
    args = [src.clumps.center_arcsec, src.clumps.re_arcsec, src.clumps.q]
    _, grads = f(*args)
    assert all(np.all(np.isfinite(g)) for g in grads)
    value = float(f(*args)[0])
    # linearised clumps 0–2 and the ray-traced clump 3. Steps are small enough for the
    # ×26 stretch of clump 1 (its FD error is quadratic in h: 0.05 % at 1e-6) and for
    # clump 3 on the caustic, where FD converges to the gradient only slowly (22 % off at
    # h = 1e-6, 0.3 % at 1e-8: measured)
    for a, idx, h, rel in ((0, (0, 0), 1e-6, 1e-4), (0, (1, 1), 1e-7, 1e-4),
                           (0, (3, 0), 1e-8, 5e-3), (1, (0,), 1e-7, 1e-4), (1, (3,), 1e-7, 1e-4),
                           (2, (1,), 1e-5, 1e-4)):
        up, dn = list(args), list(args)
        up[a] = args[a].at[idx].add(h)
        dn[a] = args[a].at[idx].add(-h)
        fd = (float(f(*up)[0]) - float(f(*dn)[0])) / (2 * h)
        assert fd == pytest.approx(float(grads[a][idx]), rel=rel, abs=1e-9 * value / h), (a, idx)


def test_images_without_the_strip_hold_their_light_in_the_exact_core():
    """`strip_needed` False ⇒ the exact core block (core² pixels around the centre's pixel)
    holds ≥ 1 − 1e-4 of the profile's light, by exact pixel integrals, for thin and round
    profiles and centres anywhere in their pixel; large profiles do need the strip."""
    from clumpylen_jax.render import strip_needed
    rng = np.random.default_rng(11)
    p, core = 0.006, 5
    re = np.exp(rng.uniform(np.log(2e-4), np.log(2e-2), 200))
    n = rng.uniform(0.5, 2.0, 200)
    need = strip_needed(re, n, p, core)
    assert need.any() and not need.all()
    k = np.arange(core) - core // 2
    checked = 0
    small = np.nonzero(~need)[0]
    for j in small[np.argsort(-re[small])][:30]:        # the largest: nearest the threshold
        c = rng.uniform(-0.5, 0.5, 2) * p             # centre anywhere in pixel (0, 0)
        lo = (k - 0.5) * p
        block = profiles.sersic_pixel_flux_exact(
            f64(lo[None, :]), f64(lo[None, :] + p), f64(lo[:, None]), f64(lo[:, None] + p),
            flux=1.0, re_arcsec=f64(re[j]), n=f64(n[j]), q=f64(rng.uniform(0.05, 1)),
            pa_rad=f64(rng.choice([0.0, np.pi / 4])), center1=f64(c[0]), center2=f64(c[1]))
        assert float(jnp.sum(block)) >= 1 - 1e-4, (re[j], n[j])
        checked += 1
    assert checked == 30


def test_linearised_flux_follows_the_magnification_averaged_over_the_clump():
    """A clump 0.15" from an SIS's centre: |μ+| = 1 + θ_E/|β| changes by ±6 % across it.
    Its linearised image carries ∫ S |μ| / ∫ S (source-plane quadrature, independent of
    the lens-plane machinery), not the centre's |μ|, which is 0.3 % off here."""
    theta_e = 1.0
    c0 = np.array([0.15, 0.02])
    cl = Clumps(f64([c0]), f64([[1.0]]), f64([0.01]), f64([1.0]), f64([0.6]), f64([0.4]))
    src = Source(clumps=cl)
    model = build_model(src, [Band("X", 0.03, 1.0)], lens=SIS(f64(theta_e), f64([0.0, 0.0])),
                        field_arcsec=((0.9, 1.4), (-0.5, 0.8)), lens_pixel_arcsec=0.002,
                        accuracy=Accuracy(source_mode="hybrid", linearise_tolerance=100.0))
    assert model.lin_images is not None and model.lin_images.count == 1
    # reference: the + image's |μ| averaged over the clump's light on a fine β grid
    h = 1e-4      # R_e / 100: the weighted mean moves by 3e-10 from h = 2.5e-5 (6 s, not 18 s)
    x = np.arange(-0.12, 0.12, h) + h / 2
    b1, b2 = np.meshgrid(c0[0] + x, c0[1] + x)
    s = np.asarray(profiles.sersic_brightness(f64(b1), f64(b2), flux=1.0, re_arcsec=0.01, n=1.0,
                                              q=0.6, pa_rad=0.4, center1=c0[0], center2=c0[1]))
    mu_ref = np.sum(s * (1 + theta_e / np.hypot(b1, b2))) / np.sum(s)
    mu_center = 1 + theta_e / np.hypot(*c0)
    assert abs(mu_center / mu_ref - 1) > 2e-3           # the test can tell them apart
    mag = float(eqx.filter_jit(lambda m, s: m.clump_magnifications(s))(model, src)[0])
    assert abs(mag / mu_ref - 1) < 1e-4, (mag, mu_ref, mu_center)
    img = np.asarray(eqx.filter_jit(lambda m, s: m.band_images(s)[0])(model, src))
    assert abs(img.sum() / mu_ref - 1) < 2e-4, (img.sum(), mu_ref)


def test_magnifications_beside_band_images_are_the_standalone_ones(cluster_hybrid):
    """`clump_magnifications(beside_band_images=True)` (the band render's program computes
    them from the stamps it makes for the band images, no exact-pixel kernel of their own)
    gives the standalone program's values to rounding (two programs, fused differently by
    XLA: 1 ulp apart in one clump), for linearised and ray-traced clumps, and leaves the
    band images as they are (to the bit)."""
    src, bands, kw, hyb = cluster_hybrid
    assert hyb.clumps.traced is not None and hyb.clumps.linearised is not None
    alone = np.asarray(eqx.filter_jit(lambda m, s: m.clump_magnifications(s))(hyb, src))
    images, mags = eqx.filter_jit(lambda m, s: (
        m.band_images(s), m.clump_magnifications(s, beside_band_images=True)))(hyb, src)
    np.testing.assert_allclose(np.asarray(mags), alone, rtol=4 * np.finfo(float).eps, atol=0)
    only = eqx.filter_jit(lambda m, s: m.band_images(s))(hyb, src)
    np.testing.assert_array_equal(np.asarray(images[0]), np.asarray(only[0]))


def test_band_render_together_matches_each_alone(cluster_hybrid):
    """`noiseless_lens_plane_magnifications` (one stamp call and one ray-traced pass for
    the band images, the lens plane of a source with other fluxes and the magnifications,
    as the `simulate` band render uses it) gives what `noiseless`, `lens_plane` and
    `clump_magnifications` give alone, for linearised and ray-traced clumps."""
    src, bands, kw, hyb = cluster_hybrid
    flux = src.clumps.flux
    other = Source(clumps=eqx.tree_at(lambda c: c.flux, src.clumps,
                                      jnp.concatenate([flux * 3.0, flux[:, :1] * 0.5], axis=1)))
    clean, plane, mags = eqx.filter_jit(
        lambda m, s, o: m.noiseless_lens_plane_magnifications(s, o, True))(hyb, src, other)
    alone = eqx.filter_jit(lambda m, s, o: (m.noiseless(s), m.lens_plane(o),
                                            m.clump_magnifications(s)))(hyb, src, other)
    for a, b in zip(clean, alone[0]):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-12,
                                   atol=1e-12 * float(np.max(np.abs(b))))
    assert plane.shape == alone[1].shape
    np.testing.assert_allclose(np.asarray(plane), np.asarray(alone[1]), rtol=1e-12,
                               atol=1e-12 * float(np.max(np.abs(alone[1]))))
    np.testing.assert_allclose(np.asarray(mags), np.asarray(alone[2]), rtol=1e-12)
    none = eqx.filter_jit(lambda m, s: m.noiseless_lens_plane_magnifications(s))(hyb, src)
    assert none[1] is None and none[2] is None
