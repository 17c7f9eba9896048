"""The composed model: lensing, pixels, PSF, noise, stages and gradients."""

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import clumpylen_jax
from clumpylen_jax import convolve, noise
from clumpylen_jax.errors import ConfigError
from clumpylen_jax.lensing.analytic import SIS
from clumpylen_jax.lensing.grid import DeflectionGrid
from clumpylen_jax.model import Accuracy, Band, build_model
from clumpylen_jax.model.renderer import first_band_per_subgrid
from clumpylen_jax.pixels import Grid, overlap_matrix, rebin, rebin_operators
from clumpylen_jax.source import Clumps, Disk, Sersic, Source, SpiralArms, Texture

f64 = lambda x: jnp.asarray(x, jnp.float64)  # noqa: E731


def gaussian_psf(size, sigma_pix):
    y, x = np.mgrid[:size, :size] - (size - 1) / 2
    return np.exp(-(x**2 + y**2) / (2 * sigma_pix**2))


def clump(beta, flux, re=0.002):
    return Clumps(f64([beta]), f64([[flux]]), f64([re]), f64([0.5]), f64([1.0]), f64([0.0]))


# ------------------------------------------------------------------ lensing


def test_sis_image_positions_and_flux_ratio():
    """A compact source behind an SIS: images at β ± θ_E, flux ratio |θ+|/|θ−| (1 %)."""
    beta, theta_e = 0.3, 1.0
    src = Source(clumps=clump([beta, 0.0], 100.0, re=0.001))
    lens = SIS(f64(theta_e), f64([0.0, 0.0]))
    m = build_model(src, [Band("X", 0.02, 1.0)], lens=lens, field_arcsec=((-2, 2), (-1, 1)),
                    lens_pixel_arcsec=0.002, accuracy=Accuracy(source_mode="analytic"))
    img = np.asarray(eqx.filter_jit(lambda m, s: m.lens_plane(s))(m, src))[0]
    g = m.hr_grid
    x = g.x_centers()[None, :]
    y = g.y_centers()[:, None]
    plus, minus = img * (x > 0), img * (x < 0)
    xp = (plus * x).sum() / plus.sum()
    xm = (minus * x).sum() / minus.sum()
    assert abs(xp - (beta + theta_e)) < 0.01 * (beta + theta_e)
    assert abs(xm - (beta - theta_e)) < 0.01 * abs(beta - theta_e)
    assert abs(float((plus * y).sum() / plus.sum())) < 0.01
    ratio = plus.sum() / minus.sum()
    expected = (beta + theta_e) / (theta_e - beta)
    assert abs(ratio / expected - 1) < 0.01
    # total magnification of a point source behind an SIS: 2 θ_E / β
    assert abs(img.sum() / 100.0 / (2 * theta_e / beta) - 1) < 0.01


def _compact_host_behind_sis(dtype):
    f = lambda x: jnp.asarray(x, dtype)  # noqa: E731
    src = Source(bulge=Sersic(flux=f([100.0]), re_arcsec=f(0.005), n=f(4.0), q=f(0.7),
                              pa_rad=f(0.3), center_arcsec=f([0.3, 0.05])))
    m = build_model(src, [Band("X", 0.03, 1.0)], lens=SIS(f64(1.0), f64([0.0, 0.0])),
                    field_arcsec=((-0.9, 1.5), (-0.45, 0.45)), dtype=dtype,
                    accuracy=Accuracy(source_flux_fraction=0.999))
    return m, src


def test_compact_lensed_host_keeps_its_flux_near_its_cusp():
    """An n = 4 host of R_e 5 mas (2 lens pixels) behind an SIS: the lensed total is the
    point-source |μ| (2 θ_E / β) to 0.5 % (sampled at lens-pixel centres: +7 %, and 15 %
    of the peak), in float64 and float32, with finite gradients in both."""
    totals = {}
    for dtype in (jnp.float64, jnp.float32):
        m, src = _compact_host_behind_sis(dtype)
        assert m.host_core_index is not None and m.host_core_index.size > 1000, m.host_core_index
        # one compile per dtype: the image comes out as the aux of its own gradient
        def loss(s, m):
            img = m.noiseless(s)[0]
            return jnp.sum(img ** 2), img

        (_, img), grads = jax.jit(jax.value_and_grad(loss, has_aux=True))(src, m)
        assert img.dtype == dtype
        totals[dtype] = float(jnp.sum(img))
        leaves = jax.tree_util.tree_leaves(grads.bulge)
        assert all(bool(jnp.all(jnp.isfinite(g))) for g in leaves)
    beta = float(np.hypot(0.3, 0.05))
    assert abs(totals[jnp.float64] / (100.0 * 2 / beta) - 1) < 5e-3
    assert abs(totals[jnp.float32] / totals[jnp.float64] - 1) < 1e-4


def test_grid_and_analytic_clump_modes_agree():
    src = Source(bulge=Sersic(f64([20.0]), f64(0.03), f64(1.0), f64(0.8), f64(0.2), f64([0.2, 0.05])),
                 clumps=Clumps(f64([[0.21, 0.06], [0.18, 0.03]]), f64([[5.0], [3.0]]),
                               f64([0.004, 0.006]), f64([0.5, 0.5]), f64([0.7, 0.5]), f64([0.3, 1.2])))
    lens = SIS(f64(1.0), f64([0.0, 0.0]))
    kw = dict(lens=lens, field_arcsec=((-1.5, 1.5), (-1.5, 1.5)), lens_pixel_arcsec=0.005,
              source_pixel_arcsec=0.0004)
    bands = [Band("X", 0.03, 1.0)]
    a = build_model(src, bands, accuracy=Accuracy(source_mode="analytic"), **kw)
    g = build_model(src, bands, accuracy=Accuracy(source_mode="grid"), **kw)
    ia = np.asarray(eqx.filter_jit(lambda m, s: m.band_images(s))(a, src)[0])
    ig = np.asarray(eqx.filter_jit(lambda m, s: m.band_images(s))(g, src)[0])
    assert abs(ig.sum() / ia.sum() - 1) < 2e-3
    assert np.max(np.abs(ig - ia)) < 0.02 * ia.max()


def test_deflection_map_matches_analytic_lens_and_clamps_outside():
    """An in-memory map of an SIS traces like the SIS; rays outside get the edge value."""
    lens = SIS(f64(1.0), f64([0.0, 0.0]))
    p = 0.01
    ax = np.arange(-300, 301) * p
    X, Y = np.meshgrid(ax, ax)
    a1, a2 = lens.deflection(f64(X), f64(Y))
    grid = DeflectionGrid(a1, a2, f64([ax[0], ax[0]]), p)
    t1 = f64([1.234, -0.711, 2.5])
    t2 = f64([0.456, 0.3, -1.7])
    g1, g2 = grid.deflection(t1, t2)
    e1, e2 = lens.deflection(t1, t2)
    assert np.allclose(g1, e1, atol=2e-4) and np.allclose(g2, e2, atol=2e-4)
    o1, o2 = grid.deflection(f64([10.0]), f64([0.0]))
    c1, c2 = grid.deflection(f64([3.0]), f64([0.0]))
    assert float(o1[0]) == float(c1[0]) and float(o2[0]) == float(c2[0])
    g = jax.grad(lambda t: sum(grid.deflection(t, t * 0.3)[0]))(f64([10.0, 0.2]))
    assert np.all(np.isfinite(np.asarray(g)))


def test_only_traced_pixels_are_computed():
    src = Source(bulge=Sersic(f64([1.0]), f64(0.02), f64(1.0), f64(1.0), f64(0.0), f64([0.3, 0.0])))
    lens = SIS(f64(1.0), f64([0.0, 0.0]))
    m = build_model(src, [Band("X", 0.05, 1.0)], lens=lens, field_arcsec=((-2, 2), (-2, 2)),
                    lens_pixel_arcsec=0.01)
    n_field = m.hr_grid.nx * m.hr_grid.ny
    assert m.traced_rows.shape[0] < 0.2 * n_field  # an extended ring, not the whole field


# ------------------------------------------------------------------ pixels and PSF


def test_rebinning_conserves_flux_for_non_integer_ratios():
    rng = np.random.default_rng(0)
    src = Grid(-1.0, -1.0, 0.0025, 800, 800)
    dst = Grid.covering(src.x_range, src.y_range, 0.031)
    img = rng.random(src.shape)
    wy, wx = rebin_operators(src, dst)
    out = np.asarray(rebin(jnp.asarray(img), wy, wx))
    assert abs(out.sum() / img.sum() - 1) < 1e-12
    w = overlap_matrix([0, 1, 2, 3], [0, 1.5, 3])
    assert np.allclose(w, [[1, 0.5, 0], [0, 0.5, 1]])


def test_sparse_rebinning_is_exact_for_linear_light_and_stays_positive():
    """Lens pixels split between detector pixels share their light as a (minmod-limited)
    linear profile: a linear ramp rebins exactly to non-nested pixels away from the edges
    (sharing flat pixels errs by 1e-2 of a pixel's flux here), a lone bright pixel stays
    ≥ 0 everywhere, and flux is conserved; nested grids carry no moments at all."""
    from clumpylen_jax.pixels import sparse_rebin_operators, rebin_sparse
    src = Grid(0.5, 0.5, 1.0, 60, 60)                    # edges at 0, 1, ..., 60
    dst = Grid.covering((0.0, 59.4), (0.0, 59.4), 2.7)   # 22 pixels, edges at k·2.7
    x = src.x_centers()
    ramp = np.broadcast_to(3.0 + 0.5 * x, src.shape).copy()     # flux of density 3 + x/2
    ops = sparse_rebin_operators(src, dst)

    def rebinned(img, ops):
        return np.asarray(rebin_sparse(jnp.asarray(img), tuple(
            tuple(None if a is None else jnp.asarray(a) for a in op) for op in ops), dst.shape))

    out = rebinned(ramp, ops)
    e = dst.x_edges()
    exact = (3.0 * np.diff(e) + 0.25 * np.diff(e**2)) * 2.7    # ∫ density dx × row height
    inner = slice(2, -2)
    assert np.allclose(out[inner, inner], exact[None, inner], rtol=1e-12)
    out_flat = rebinned(ramp, tuple((t, w, None) for t, w, _ in ops))
    assert np.max(np.abs(out_flat[inner, inner] / exact[None, inner] - 1)) > 1e-3
    spike = np.zeros(src.shape)
    spike[30, 31] = 1.0
    out = rebinned(spike, ops)
    assert out.min() >= 0.0 and abs(out.sum() - 1.0) < 1e-12
    nested = sparse_rebin_operators(src, Grid.covering((0.0, 60.0), (0.0, 60.0), 3.0))
    assert all(m is None for _, _, m in nested)


@pytest.mark.parametrize("size", [21, 22])
def test_psf_convolution_conserves_flux_and_centres_a_point(size):
    from clumpylen_jax.psf import PSF, resample_psf
    psf = PSF(gaussian_psf(size, 2.0), 0.01, False)
    kernel = resample_psf(psf, 0.01)
    assert kernel.shape[0] % 2 == 1
    img = np.zeros((61, 61))
    img[30, 30] = 1.0
    ft = convolve.kernel_rfft(kernel, img.shape)
    out = np.asarray(convolve.fft_convolve(jnp.asarray(img), ft, kernel.shape))
    assert abs(out.sum() - 1) < 1e-6
    y, x = np.mgrid[:61, :61]
    assert abs((out * x).sum() - 30) < 1e-6 and abs((out * y).sum() - 30) < 1e-6
    # no wrap-around: a point at the edge loses flux, it does not appear on the other side
    img = np.zeros((61, 61))
    img[30, 0] = 1.0
    out = np.asarray(convolve.fft_convolve(jnp.asarray(img), ft, kernel.shape))
    assert out[:, -5:].max() < 1e-12 and out.sum() < 0.99


@pytest.mark.parametrize("image_shape,kernel_shape", [((61, 47), (21, 9)), ((12, 40), (41, 31)),
                                                      ((5, 5), (3, 61)), ((120, 120), (91, 91))])
def test_fft_convolution_is_the_cropped_linear_convolution(image_shape, kernel_shape):
    """`convolve.fft_convolve` and `fft_convolve_sum` on the smallest padding that keeps the
    wrapped terms out of the crop (`fft_shape`: n + k//2, at least k) against direct
    convolution (scipy, mode "same"), for random images and kernels, kernels larger than the
    image included."""
    from scipy.signal import convolve2d
    rng = np.random.default_rng(sum(image_shape + kernel_shape))
    imgs = rng.normal(size=(3,) + image_shape)
    kernels = rng.random((3,) + kernel_shape)
    want = [convolve2d(i, k, mode="same") for i, k in zip(imgs, kernels)]
    for i, k, w in zip(imgs, kernels, want):
        got = np.asarray(convolve.fft_convolve(jnp.asarray(i), convolve.kernel_rfft(
            k, image_shape, check=False), kernel_shape))
        np.testing.assert_allclose(got, w, rtol=0, atol=1e-12 * np.abs(w).max())
    got = np.asarray(convolve.fft_convolve_sum(jnp.asarray(imgs), convolve.kernel_rfft(
        kernels, image_shape, check=False), kernel_shape))
    np.testing.assert_allclose(got, sum(want), rtol=0, atol=1e-12 * np.abs(sum(want)).max())


def test_model_psf_band_conserves_flux_and_effective_psf_is_not_double_counted():
    src = Source(bulge=Sersic(f64([50.0]), f64(0.05), f64(1.0), f64(1.0), f64(0.0), f64([0.0, 0.0])))
    psf = gaussian_psf(41, 4.0)  # sampled at 0.01": an optical PSF of σ = 0.04"
    bands = [Band("none", 0.03, 1.0), Band("optical", 0.03, 1.0, 0.0, psf, 0.01, False)]
    m = build_model(src, bands, field_arcsec=((-1.5, 1.5), (-1.5, 1.5)))
    none, opt = (np.asarray(x) for x in eqx.filter_jit(lambda m, s: m.band_images(s))(m, src))
    assert abs(opt.sum() / none.sum() - 1) < 1e-5
    # the same PSF declared effective must not be integrated over the pixel again:
    # its image is narrower than the optical one (which gains the pixel response)
    eff = build_model(src, [Band("eff", 0.03, 1.0, 0.0, psf, 0.01, True)],
                      field_arcsec=((-1.5, 1.5), (-1.5, 1.5)))
    e = np.asarray(eqx.filter_jit(lambda m, s: m.band_images(s))(eff, src)[0])
    assert abs(e.sum() / none.sum() - 1) < 1e-3
    assert e.max() > opt.max()


def test_invalid_psf_and_parameters_raise_before_computing():
    good = Sersic(f64([1.0]), f64(0.1), f64(1.0), f64(1.0), f64(0.0), f64([0.0, 0.0]))
    bad_psf = gaussian_psf(11, 2.0)
    bad_psf[3, 3] = np.nan
    with pytest.raises(ConfigError, match="psf"):
        build_model(Source(bulge=good), [Band("X", 0.03, 1.0, 0.0, bad_psf, 0.01)])
    with pytest.raises(ConfigError, match="positive sum"):
        build_model(Source(bulge=good), [Band("X", 0.03, 1.0, 0.0, -gaussian_psf(11, 2.0), 0.01)])
    cases = {"flux": f64([-1.0]), "re_arcsec": f64(0.0), "q": f64(1.5), "n": f64(12.0)}
    for field, value in cases.items():
        bad = eqx.tree_at(lambda s: getattr(s, field), good, value)
        with pytest.raises(ConfigError, match=f"source.bulge.{field}"):
            build_model(Source(bulge=bad), [Band("X", 0.03, 1.0)])
    with pytest.raises(ConfigError, match="shape"):
        DeflectionGrid(jnp.zeros((5, 5)), jnp.zeros((5, 6)), f64([0.0, 0.0]), 0.1)


# ------------------------------------------------------------------ noise


def test_noise_mean_and_variance():
    img = jnp.full((200, 200), 2.5)
    t = 40.0
    draws = noise.add_photon_noise(jax.random.key(1), img, t)
    assert abs(float(draws.mean()) - 2.5) < 4 * np.sqrt(2.5 / t / img.size)
    assert abs(float(draws.var()) / (2.5 / t) - 1) < 0.03
    var = noise.variance_map(img, t)
    assert np.allclose(var, 2.5 / t)
    big = jnp.full((200, 200), 1e6)
    g = noise.add_photon_noise(jax.random.key(2), big, 1.0, gaussian_above_counts=1e4)
    assert abs(float(g.var()) / 1e6 - 1) < 0.03
    again = noise.add_photon_noise(jax.random.key(1), img, t)
    assert np.array_equal(np.asarray(draws), np.asarray(again))


@pytest.mark.parametrize("gaussian_above", [None, 1e3])
def test_band_noise_one_sampler_independent_of_other_bands(gaussian_above):
    """Bands of different shapes share one sampler (chunks of a fixed size); a band's
    noise is the same bits whichever bands are simulated with it, and photon noise."""
    rng = np.random.default_rng(4)
    shapes = ((31, 40), (150, 130), (17, 9))
    images = [jnp.asarray(rng.gamma(0.7, 30.0, size=s)) for s in shapes]
    names, t = ("F105W", "F200W", "F444W"), (500.0, 1000.0, 2000.0)
    key = jax.random.key(7)
    together = noise.add_photon_noise_bands(key, images, names, t, gaussian_above)
    assert [x.shape for x in together] == list(shapes)
    for sub in ([0], [2], [1, 2], [2, 0]):
        alone = noise.add_photon_noise_bands(key, [images[k] for k in sub],
                                             [names[k] for k in sub], [t[k] for k in sub],
                                             gaussian_above)
        for j, k in enumerate(sub):
            assert np.array_equal(np.asarray(alone[j]), np.asarray(together[k]))
    again = noise.add_photon_noise_bands(key, images, names, t, gaussian_above)
    assert all(np.array_equal(np.asarray(a), np.asarray(b)) for a, b in zip(again, together))
    # photon noise: (draw - mean)² / variance averages to 1
    lam = np.concatenate([np.ravel(np.asarray(im) * tk) for im, tk in zip(images, t)])
    counts = np.concatenate([np.ravel(np.asarray(d) * tk) for d, tk in zip(together, t)])
    assert abs(np.mean((counts - lam) ** 2 / np.maximum(lam, 1e-9)) - 1) < 0.05
    # one sampler, however many image shapes: a third shape adds no loop
    program = jax.jit(lambda k, im: noise.add_photon_noise_bands(k, im, names, t, gaussian_above))
    assert (program.lower(key, images).as_text().count("stablehlo.while")
            == program.lower(key, images[:2]).as_text().count("stablehlo.while"))


# ------------------------------------------------------------------ stages in the compiled model


def _primitives(fn, *args):
    jaxpr = jax.make_jaxpr(fn)(*args)
    names = set()

    def walk(jp):
        for eqn in jp.eqns:
            names.add(eqn.primitive.name)
            for p in eqn.params.values():
                for sub in (p if isinstance(p, (list, tuple)) else [p]):
                    if hasattr(sub, "jaxpr"):
                        walk(sub.jaxpr if hasattr(sub.jaxpr, "eqns") else sub.jaxpr.jaxpr)
                    elif hasattr(sub, "eqns"):
                        walk(sub)

    walk(jaxpr.jaxpr)
    return names


def test_stages_not_called_for_are_absent_from_the_computation():
    # resolved (q·R_e = 2.4 pixels): a thin profile's exact strip would scatter too
    src = Source(bulge=Sersic(f64([5.0]), f64(0.15), f64(2.0), f64(0.8), f64(0.1), f64([0.3, 0.0])))
    psf = gaussian_psf(21, 2.0)
    plain = build_model(src, [Band("X", 0.05, 100.0, 0.1)], field_arcsec=((-1, 1), (-1, 1)))
    with_psf = build_model(src, [Band("X", 0.05, 100.0, 0.1, psf, 0.0167)],
                           field_arcsec=((-1, 1), (-1, 1)))

    calls = []

    class SpyLens(eqx.Module):
        inner: SIS

        def deflection(self, t1, t2):
            calls.append(1)
            return self.inner.deflection(t1, t2)

    lensed = build_model(src, [Band("X", 0.05, 100.0, 0.1)], lens=SpyLens(SIS(f64(1.0), f64([0, 0]))),
                         field_arcsec=((-2, 2), (-2, 2)), lens_pixel_arcsec=0.01)
    assert calls and plain.beta1 is None and not plain.lensed
    key = jax.random.key(0)
    p_plain = _primitives(lambda s: plain.noiseless(s), src)
    p_psf = _primitives(lambda s: with_psf.noiseless(s), src)
    p_lens = _primitives(lambda s: lensed.noiseless(s), src)
    p_noise = _primitives(lambda s, k: plain.observe(s, k), src, key)
    assert "fft" not in p_plain and "fft" in p_psf
    assert not any("random" in n or "threefry" in n for n in p_plain | p_psf | p_lens)
    assert any("random" in n or "threefry" in n for n in p_noise)
    # ray-traced values are scattered into the lens plane only when there is a lens
    assert "scatter" not in p_plain and "scatter" in p_lens


# ------------------------------------------------------------------ gradients


def _full_source():
    perm = jnp.asarray(5, jnp.uint32)
    bulge = Sersic(f64([8.0, 5.0]), f64(0.03), f64(3.0), f64(0.9), f64(0.3), f64([0.25, 0.02]))
    disk = Disk(Sersic(f64([20.0, 25.0]), f64(0.08), f64(1.0), f64(0.8), f64(0.5), f64([0.25, 0.02])),
                f64(0.4), SpiralArms(2, f64(0.6), f64(4.0), f64(1.0), f64(0.05), f64(0.3)),
                Texture(f64(0.3), f64(0.04), 2, perm))
    clumps = Clumps(f64([[0.27, 0.03], [0.22, 0.0]]), f64([[4.0, 3.0], [2.0, 2.5]]),
                    f64([0.006, 0.01]), f64([0.5, 1.0]), f64([0.7, 0.5]), f64([0.3, 1.2]))
    return Source(bulge, disk, clumps)


@pytest.mark.slow  # 20-30 s (compiles): pytest -m slow; test_profiles has the fast check
@pytest.mark.parametrize("lensed", [False, True])
def test_held_host_light_gives_the_same_images_bit_for_bit(lensed):
    """`with_host_light`: the host's light per unit flux made by one program and held as
    data by the next (as `clumpylen simulate` reads it back from its cache) gives the
    images the model draws itself, bit for bit (XLA reassociates flux × pixel area within
    one program: `render.disk_image_values`)."""
    full = _full_source()     # the bulge and an armed disk (its sampled image), no texture
    src = Source(full.bulge, Disk(full.disk.sersic, full.disk.inclination_rad, full.disk.arms))
    lens = SIS(f64(1.0), f64([0.0, 0.0])) if lensed else None
    m = build_model(src, [Band("A", 0.06, 500.0, 0.1)], lens=lens,
                    field_arcsec=((-1.2, 1.2), (-1.2, 1.2)), lens_pixel_arcsec=0.03,
                    accuracy=Accuracy(psf_oversampling=1))
    images = eqx.filter_jit(lambda m, s: m.band_images(s))
    units = eqx.filter_jit(lambda m, s: m.hosts.unit_light(s, first_band_per_subgrid(
        m.layouts)))(m, src)
    for own, held in zip(images(m, src), images(m.with_host_light(units), src)):
        np.testing.assert_array_equal(np.asarray(held), np.asarray(own))


def test_gradient_of_chi2_matches_finite_differences_on_a_lensed_psf_scene():
    src = _full_source()
    lens = SIS(f64(1.0), f64([0.0, 0.0]))
    psf = gaussian_psf(15, 1.5)
    bands = [Band("A", 0.06, 500.0, 0.1, psf, 0.02), Band("B", 0.06, 500.0, 0.1)]
    m = build_model(src, bands, lens=lens, field_arcsec=((-1.5, 1.5), (-1.5, 1.5)),
                    lens_pixel_arcsec=0.015, accuracy=Accuracy(source_mode="analytic",
                                                               lens_subsampling=2, psf_oversampling=1))
    params, static = eqx.partition(src, eqx.is_inexact_array)
    leaves, treedef = jax.tree_util.tree_flatten(params)
    # drop the texture's hash table (integers) — not a parameter
    def chi2(leaves, data):
        s = eqx.combine(jax.tree_util.tree_unflatten(treedef, leaves), static)
        return sum(jnp.sum((mi - di) ** 2) for mi, di in zip(m.noiseless(s), data))

    # Two compiles: the images (for the data and for every finite difference, χ² summed
    # in numpy) and the gradient. (Evaluating the model op by op dispatches thousands of
    # primitives; a third compile for χ² alone is not needed.)
    images = jax.jit(lambda l: m.noiseless(eqx.combine(jax.tree_util.tree_unflatten(treedef, l), static)))
    rng = np.random.default_rng(3)
    data = tuple(np.asarray(c) + 0.05 * rng.standard_normal(c.shape) for c in images(leaves))
    f = lambda l: sum(float(np.sum((np.asarray(mi) - di) ** 2)) for mi, di in zip(images(l), data))  # noqa: E731
    grads = jax.jit(jax.grad(lambda l: chi2(l, data)))(leaves)
    f0 = f(leaves)
    checked = 0
    for k, (leaf, g) in enumerate(zip(leaves, grads)):
        g = np.asarray(g)
        assert np.all(np.isfinite(g))
        flat = np.asarray(leaf).ravel()
        for i in range(flat.size):
            h = 1e-6 * max(abs(flat[i]), 1e-3)
            up = flat.copy(); up[i] += h
            dn = flat.copy(); dn[i] -= h
            lu = list(leaves); lu[k] = jnp.asarray(up.reshape(np.shape(leaf)))
            ld = list(leaves); ld[k] = jnp.asarray(dn.reshape(np.shape(leaf)))
            fd = (f(lu) - f(ld)) / (2 * h)
            gi = float(g.ravel()[i])
            scale = max(abs(fd), abs(gi), 1e-6 * f0)
            assert abs(gi - fd) <= 1e-4 * scale, (k, i, gi, fd)
            checked += 1
    assert checked >= 30


@pytest.mark.slow  # 40-80 s: the thorough profile (pytest -m slow); keeps make test under 10 min
def test_float32_model_is_finite_and_close_to_float64():
    src = _full_source()
    lens = SIS(f64(1.0), f64([0.0, 0.0]))
    kw = dict(lens=lens, field_arcsec=((-1.5, 1.5), (-1.5, 1.5)), lens_pixel_arcsec=0.01,
              source_pixel_arcsec=0.001)
    bands = [Band("A", 0.06, 500.0, 0.1, gaussian_psf(15, 1.5), 0.02), Band("B", 0.06, 500.0, 0.1)]
    m64 = build_model(src, bands, **kw)
    src32 = src.astype(jnp.float32)
    m32 = build_model(src32, bands, dtype=jnp.float32, **kw)
    i64 = eqx.filter_jit(lambda m, s: m.noiseless(s))(m64, src)
    i32 = eqx.filter_jit(lambda m, s: m.noiseless(s))(m32, src32)
    for a, b in zip(i64, i32):
        assert b.dtype == jnp.float32 and np.all(np.isfinite(np.asarray(b)))
        assert np.max(np.abs(np.asarray(a) - np.asarray(b))) < 1e-4 * float(jnp.max(a))


# ------------------------------------------------------------------ ray footprints (issue 18)


def test_cell_brightness_without_a_cell_is_the_gaussian_clumps_point_value():
    """gaussian_clumps_cell_brightness with zero cell moments is clumps_brightness of
    n = 0.5 clumps (elliptical, rotated), and a cell moment s² widens each axis as σ² + s²
    (the peak of a round clump falls by σ²/(σ² + s²), its integral stays 1)."""
    from clumpylen_jax import gaussian_mixtures, render
    cl = Clumps(f64([[0.01, -0.02], [0.0, 0.03]]), f64([[2.0], [1.0]]), f64([0.006, 0.01]),
                f64([0.5, 0.5]), f64([0.3, 0.8]), f64([0.7, -1.9]))
    x1, x2 = (f64(v) for v in np.random.default_rng(0).normal(0, 0.02, (2, 50)))
    zero = jnp.zeros_like(x1)
    a = render.gaussian_clumps_cell_brightness(cl, x1, x2, (zero, zero, zero))
    b = render.clumps_brightness(cl, x1, x2)
    assert np.allclose(a, b, rtol=1e-10, atol=1e-12 * float(jnp.max(b)))
    one = Clumps(f64([[0.0, 0.0]]), f64([[1.0]]), f64([0.006]), f64([0.5]), f64([1.0]), f64([0.0]))
    sig2 = (0.006 * gaussian_mixtures.round_mixture("round_gaussian")[2][0]) ** 2
    s2 = f64([0.5 * sig2])
    peak = render.gaussian_clumps_cell_brightness(one, f64([0.0]), f64([0.0]), (s2, f64([0.0]), s2))
    assert float(peak[0, 0]) == pytest.approx(1 / (2 * np.pi * 1.5 * sig2), rel=1e-12)


def test_ray_footprint_draws_a_thin_lensed_clump_that_point_rays_alias():
    """A thin Gaussian clump (R_e 7.5 mas, q 0.27: minor σ 1.7 mas) behind an SIS, 2 rays per
    0.01" lens pixel (rays ~5 mas apart: the clump fits' sampling): averaged over each ray's
    cell (`Accuracy.ray_footprint`) its image is within a fifth of the point-sampled error of
    a converged one (8 rays per 0.0025" pixel) and keeps its flux to 0.5 % (measured: peak
    pixel 1.9 % against 14 %, flux 0.36 % against 3.8 %)."""
    lens = SIS(f64(1.0), f64([0.0, 0.0]))
    src = Source(clumps=Clumps(f64([[0.061, 0.0071]]), f64([[10.0]]), f64([0.0075]), f64([0.5]),
                               f64([0.27]), f64([1.85])))
    kw = dict(lens=lens, field_arcsec=((0.9, 1.2), (-0.21, 0.45)), source_pixel_arcsec=0.001)
    bands = [Band("X", 0.03, 1.0)]
    fast = Accuracy(source_mode="analytic", lens_subsampling=2)
    imgs = {}
    for name, acc, lp in (("point", fast, 0.01), ("cell", Accuracy(source_mode="analytic",
                          lens_subsampling=2, ray_footprint=True), 0.01),
                          ("ref", Accuracy(source_mode="analytic", lens_subsampling=8), 0.0025)):
        m = build_model(src, bands, accuracy=acc, lens_pixel_arcsec=lp, **kw)
        imgs[name] = np.asarray(m.band_images(src)[0])
    ref = imgs["ref"]
    err = {k: np.max(np.abs(imgs[k] - ref)) / ref.max() for k in ("point", "cell")}
    assert err["cell"] < err["point"] / 5, err
    assert abs(imgs["cell"].sum() / ref.sum() - 1) < 5e-3
    with pytest.raises(ConfigError, match="ray_footprint"):
        expo = Clumps(f64([[0.06, 0.0]]), f64([[1.0]]), f64([0.005]), f64([1.0]), f64([1.0]),
                      f64([0.0]))   # n = 1: the cell average is the Gaussian's only
        build_model(Source(clumps=expo), bands, lens_pixel_arcsec=0.01,
                    accuracy=dataclasses.replace(fast, ray_footprint=True), **kw)
