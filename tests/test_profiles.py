"""Profiles against analytic results and independent (scipy) integrals."""

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import integrate, special

from clumpylen_jax import profiles, render
from clumpylen_jax.pixels import Grid
from clumpylen_jax.source import Disk, Sersic, SpiralArms, Texture

N_VALUES = [0.2, 0.36, 0.5, 1.0, 2.0, 4.0, 8.0, 10.0]


@pytest.mark.parametrize("n", N_VALUES)
def test_sersic_b_exact(n):
    b = float(profiles.sersic_b(n))
    ref = special.gammaincinv(2 * n, 0.5)
    assert abs(b / ref - 1) < 1e-6


def test_sersic_b_to_rounding_over_the_whole_range_in_both_dtypes():
    """b(n) solves P(2n, b) = 1/2 with P by its power series (`incgamma.p_lower_series`):
    to float64 rounding (and float32's) on a dense grid of the scene's range 0.2 ≤ n ≤ 10,
    against scipy's inverse."""
    n = np.linspace(0.2, 10.0, 4001)
    ref = special.gammaincinv(2 * n, 0.5)
    b64 = np.asarray(profiles.sersic_b(jnp.asarray(n)))
    b32 = np.asarray(profiles.sersic_b(jnp.asarray(n, jnp.float32)))
    assert np.max(np.abs(b64 / ref - 1)) < 2e-14
    assert b32.dtype == np.float32 and np.max(np.abs(b32 / ref - 1)) < 1e-5


def test_sersic_b_of_a_profile_does_not_depend_on_the_others_solved_with_it():
    """A clump's b(n) has the same bits whether it is solved alone or beside others (one
    array of n). jax's gammainc, in the solve before, gave 15 of 384 values 1 ulp apart
    when two arrays were joined."""
    rng = np.random.default_rng(2)
    one = jax.jit(profiles.sersic_b)
    joint = jax.jit(lambda x, y: profiles.sersic_b(jnp.concatenate([x, y])))
    for _ in range(12):
        a, c = (jnp.asarray(rng.uniform(0.2, 10, k)) for k in rng.integers(1, 12, 2))
        np.testing.assert_array_equal(np.asarray(joint(a, c)),
                                      np.concatenate([np.asarray(one(a)), np.asarray(one(c))]))


def test_axis_rms_per_re_against_closed_forms():
    """Gaussian (n = 0.5): σ = R_e/√(2 ln 2). Exponential (n = 1, scale h = R_e/b): <r²> = 6h²,
    so σ per axis = √3 h. Numerical: the moment integral of the profile itself."""
    assert profiles.sersic_axis_rms_per_re_np(0.5) == pytest.approx(1 / math.sqrt(2 * math.log(2)),
                                                                    rel=1e-12)
    b1 = float(profiles.sersic_b(1.0))
    assert profiles.sersic_axis_rms_per_re_np(1.0) == pytest.approx(math.sqrt(3) / b1, rel=1e-10)
    b = float(profiles.sersic_b(2.5))
    light = lambda r, k: r**k * np.exp(-b * r**(1 / 2.5))
    r2 = integrate.quad(light, 0, np.inf, args=(3,))[0] / integrate.quad(light, 0, np.inf, args=(1,))[0]
    assert profiles.sersic_axis_rms_per_re_np(2.5) == pytest.approx(math.sqrt(r2 / 2), rel=1e-6)


def test_sersic_b_gradient_matches_implicit_derivative():
    for n in (0.2, 0.5, 1.0, 4.0, 10.0):
        g = float(jax.grad(profiles.sersic_b)(n))
        h = 1e-5
        fd = (special.gammaincinv(2 * (n + h), 0.5) - special.gammaincinv(2 * (n - h), 0.5)) / (2 * h)
        assert abs(g / fd - 1) < 1e-5


def test_eager_b_and_inverse_compile_once():
    """Regression: the Newton loop's body was a closure made per call, so every eager call
    of sersic_b recompiled (0.4 s) and leaked JIT code memory; 3000 calls in
    bench_lenstronomy's 1000-clump row ended in "LLVM compilation error: Cannot allocate
    memory" and a segfault."""
    compiles = []
    jax.monitoring.register_event_duration_secs_listener(
        lambda name, _d, **_kw: compiles.append(name) if "backend_compile" in name else None)
    profiles._newton_gammainc_inverse(1.0, 0.5, 1.0, 5)
    profiles.sersic_b(0.7)
    profiles.gammainc_inverse(1.3, 0.9)
    before = len(compiles)
    for k in range(5):
        profiles._newton_gammainc_inverse(1.0 + 0.1 * k, 0.5, 1.0, 5)
        profiles.sersic_b(0.8 + 0.1 * k)
        profiles.gammainc_inverse(1.4 + 0.1 * k, 0.9)
    assert len(compiles) == before


def test_sersic_b_float32_stays_float32_and_accurate():
    b = profiles.sersic_b(jnp.float32(4.0))
    assert b.dtype == jnp.float32
    assert abs(float(b) / special.gammaincinv(8.0, 0.5) - 1) < 1e-5


def _square_fraction(n, re_pix, half_pix, cx, cy):
    """Light fraction of a circular Sérsic inside the square |x|,|y| ≤ half (scipy, polar)."""
    b = special.gammaincinv(2 * n, 0.5)

    def radius(phi):
        c, s = math.cos(phi), math.sin(phi)
        # distance from (cx, cy) to the square's boundary along direction phi
        tx = ((half_pix - cx) / c) if c > 0 else ((-half_pix - cx) / c) if c < 0 else math.inf
        ty = ((half_pix - cy) / s) if s > 0 else ((-half_pix - cy) / s) if s < 0 else math.inf
        return min(tx, ty)

    def integrand(phi):
        return special.gammainc(2 * n, b * (radius(phi) / re_pix) ** (1 / n))

    corners = sorted({math.atan2(sy * half_pix - cy, sx * half_pix - cx) % (2 * math.pi)
                      for sx in (-1, 1) for sy in (-1, 1)})
    pts = [0.0] + corners + [2 * math.pi]
    total = sum(integrate.quad(integrand, a, c, epsabs=1e-13, epsrel=1e-12, limit=200)[0]
                for a, c in zip(pts[:-1], pts[1:]))
    return total / (2 * math.pi)


_image_fn = {}


def _render(n, re_pix, cx, cy, size=121, q=1.0, pa=0.0):
    grid = Grid(-(size // 2), -(size // 2), 1.0, size, size)
    if size not in _image_fn:
        _image_fn[size] = jax.jit(lambda s: render.sersic_image(s, Grid(-(size // 2), -(size // 2),
                                                                         1.0, size, size)))
    s = Sersic(jnp.ones(1), jnp.asarray(re_pix), jnp.asarray(n), jnp.asarray(q), jnp.asarray(pa),
               jnp.asarray([cx, cy]))
    return np.asarray(_image_fn[size](s)), grid


@pytest.mark.parametrize("n", [0.5, 1.0, 4.0, 8.0])
@pytest.mark.parametrize("re_pix", [0.3, 1.0, 3.0, 10.0, 30.0, 100.0])
@pytest.mark.parametrize("center", [(0.0, 0.0), (0.5, 0.5)], ids=["pixel-centre", "pixel-corner"])
def test_sersic_pixel_integrated_flux(n, re_pix, center):
    """Σ pixels = the analytic light inside the image, to 1e-4, from sub-pixel to huge R_e."""
    img, grid = _render(n, re_pix, *center)
    assert np.all(np.isfinite(img)) and np.all(img >= 0)
    expected = _square_fraction(n, re_pix, grid.nx / 2, *center)
    assert abs(img.sum() - expected) < 1e-4 * expected


@pytest.mark.parametrize("n,re_pix", [(0.5, 0.2), (1.0, 0.5), (4.0, 0.3), (8.0, 2.0), (4.0, 20.0)])
def test_exact_pixel_values_against_scipy_dblquad(n, re_pix):
    """Pixel values near the centre (the hard ones) match a brute-force 2-D integral."""
    q, pa, cx, cy = 0.6, 0.4, 0.13, -0.21
    b = special.gammaincinv(2 * n, 0.5)
    norm = 1 / (2 * math.pi * q * re_pix**2 * n * special.gamma(2 * n) * math.exp(b) * b ** (-2 * n))

    def sb(y, x):
        u = (x - cx) * math.cos(pa) + (y - cy) * math.sin(pa)
        v = -(x - cx) * math.sin(pa) + (y - cy) * math.cos(pa)
        r = math.sqrt(u * u + (v / q) ** 2)
        return norm * math.exp(-b * ((r / re_pix) ** (1 / n) - 1))

    s = Sersic(jnp.ones(1), jnp.asarray(re_pix), jnp.asarray(n), jnp.asarray(q), jnp.asarray(pa),
               jnp.asarray([cx, cy]))
    for (i, j) in [(0, 0), (1, 0), (0, -1), (2, 2)]:
        got = float(profiles.sersic_pixel_flux_exact(
            jnp.asarray(i - 0.5), jnp.asarray(i + 0.5), jnp.asarray(j - 0.5), jnp.asarray(j + 0.5),
            flux=1.0, re_arcsec=s.re_arcsec, n=s.n, q=s.q, pa_rad=s.pa_rad, center1=s.center_arcsec[0],
            center2=s.center_arcsec[1]))
        # split at the centre so that quad sees the cusp on a boundary
        xs = sorted({i - 0.5, i + 0.5, min(max(cx, i - 0.5), i + 0.5)})
        ys = sorted({j - 0.5, j + 0.5, min(max(cy, j - 0.5), j + 0.5)})
        ref = sum(integrate.dblquad(sb, x0, x1, y0, y1, epsabs=1e-12, epsrel=1e-9)[0]
                  for x0, x1 in zip(xs[:-1], xs[1:]) for y0, y1 in zip(ys[:-1], ys[1:]) if x1 > x0 and y1 > y0)
        assert abs(got - ref) <= 2e-6 * max(ref, 1e-6), (i, j, got, ref)


def test_flattened_profile_conserves_flux():
    img, _ = _render(1.0, 8.0, 0.3, 0.1, q=0.05, pa=0.7)
    # q = 0.05: a needle; the analytic light outside the 121² image is negligible here
    assert abs(img.sum() - 1.0) < 1e-4


def test_centre_sample_and_q1_gradients_are_finite():
    def f(params):
        re, n, q, pa, c1, c2 = params
        return profiles.sersic_brightness(jnp.asarray(0.0), jnp.asarray(0.0), flux=1.0,
                                          re_arcsec=re, n=n, q=q, pa_rad=pa, center1=c1,
                                          center2=c2)

    for n in (0.2, 0.5, 1.0, 4.0, 10.0):
        p = jnp.asarray([0.1, n, 1.0, 0.0, 0.0, 0.0])
        v, g = jax.value_and_grad(f)(p)
        assert np.isfinite(float(v)) and np.all(np.isfinite(np.asarray(g)))
        g32 = jax.grad(lambda p: f(p).astype(jnp.float32))(p.astype(jnp.float32))
        assert np.all(np.isfinite(np.asarray(g32)))


def test_exact_fan_gradient_at_centre_and_corner():
    def f(c, n):
        return jnp.sum(profiles.sersic_pixel_flux_exact(
            jnp.asarray([-0.5, 0.5]), jnp.asarray([0.5, 1.5]), jnp.asarray([-0.5, -0.5]),
            jnp.asarray([0.5, 0.5]), flux=1.0, re_arcsec=0.3, n=n, q=1.0, pa_rad=0.0,
            center1=c[0], center2=c[1]) ** 2)

    for c in ([0.0, 0.0], [0.5, 0.5], [0.5, 0.0]):
        for n in (0.5, 4.0, 10.0):
            g = jax.grad(f, argnums=(0, 1))(jnp.asarray(c), n)
            assert all(np.all(np.isfinite(np.asarray(x))) for x in g)


def _disk(amplitude, texture=None, q=0.8, incl=0.3):
    s = Sersic(jnp.ones(1), jnp.asarray(6.0), jnp.asarray(1.0), jnp.asarray(q), jnp.asarray(0.4),
               jnp.asarray([0.2, -0.1]))
    arms = SpiralArms(2, jnp.asarray(amplitude), jnp.asarray(5.0), jnp.asarray(1.0),
                      jnp.asarray(4.0), jnp.asarray(0.3))
    return Disk(s, jnp.asarray(incl), arms, texture)


@pytest.mark.slow  # 40-80 s: the thorough profile (pytest -m slow); keeps make test under 10 min
def test_arms_keep_the_disk_flux_and_set_the_contrast():
    grid = Grid(-80, -80, 1.0, 161, 161)
    f = jax.jit(lambda d: render.disk_image(d, grid))
    smooth = np.asarray(f(_disk(0.0)))
    perm0 = jnp.asarray(0, jnp.uint32)
    for a in (0.5, 1.0):
        # analytically the arms average to 1 on every ellipse (flux kept exactly) ...
        untextured = _disk(a, Texture(jnp.asarray(0.0), jnp.asarray(3.0), 1, perm0))
        assert abs(float(render.disk_modulation_mean(untextured)) - 1) < 1e-9
        # ... and on pixels the only error is aliasing of the infinitely wound centre,
        # which shrinks as the sub-pixel sampling grows
        img = np.asarray(f(_disk(a)))
        coarse = abs(img.sum() - smooth.sum())
        assert coarse < 3e-3
        if a == 1.0:
            fine = jax.jit(lambda d: render.disk_image(d, grid, order=16))
            err = abs(float(fine(_disk(a)).sum() - fine(_disk(0.0)).sum()))
            assert err < 5e-4 and err < coarse / 4
        # contrast along a ring at ~2 R_h: (max - min)/(max + min) ≈ A
        yy, xx = np.mgrid[-80:81, -80:81]
        u = (xx - 0.2) * np.cos(0.4) + (yy + 0.1) * np.sin(0.4)
        v = (-(xx - 0.2) * np.sin(0.4) + (yy + 0.1) * np.cos(0.4)) / (0.8 * np.cos(0.3))
        ring = (np.hypot(u, v) > 7) & (np.hypot(u, v) < 9)
        ratio = img[ring] / smooth[ring]
        contrast = (ratio.max() - ratio.min()) / (ratio.max() + ratio.min())
        assert abs(contrast - a) < 0.1 * a


def test_texture_is_deterministic_smooth_and_flux_preserving():
    perm = jnp.asarray(42, jnp.uint32)
    tex = Texture(jnp.asarray(0.5), jnp.asarray(3.0), 3, perm)
    grid = Grid(-80, -80, 1.0, 161, 161)
    f = jax.jit(lambda d: render.disk_image(d, grid))
    img = np.asarray(f(_disk(0.7, tex)))
    img2 = np.asarray(f(_disk(0.7, Texture(jnp.asarray(0.5), jnp.asarray(3.0), 3,
                                           jnp.asarray(42, jnp.uint32)))))
    assert np.array_equal(img, img2)
    # the disk keeps its flux within the frame's truncation (exponential disk, R_e = 6 px)
    smooth = np.asarray(f(_disk(0.0)))
    assert abs(img.sum() - smooth.sum()) < 5e-3
    # smooth: the noise field is continuous across lattice cell boundaries
    x = jnp.linspace(0.999, 1.001, 3)
    v = profiles.perlin2d(x, jnp.full(3, 0.37), perm)
    assert abs(float(v[2] - v[0])) < 1e-2
    other = np.asarray(f(_disk(0.7, Texture(jnp.asarray(0.5), jnp.asarray(3.0), 3,
                                            jnp.asarray(43, jnp.uint32)))))
    assert not np.allclose(img, other)


@pytest.mark.parametrize("q,pa", [(0.05, 1.0), (0.3, 0.2), (1.0, 0.0)])
def test_centre_on_a_sheared_corner_keeps_the_light(q, pa):
    """Regression (found by hypothesis): a corner's angle is not π/2 once the ellipse is
    circularised, so the pixel sharing that corner must not be classified by quarter turns."""
    xs = np.arange(-3, 3)
    X, Y = np.meshgrid(xs, xs)
    for n, re in ((0.2, 0.001), (4.0, 0.3)):
        f = profiles.sersic_pixel_flux_exact(
            jnp.asarray(X - 0.5), jnp.asarray(X + 0.5), jnp.asarray(Y - 0.5), jnp.asarray(Y + 0.5),
            flux=1.0, re_arcsec=re, n=n, q=q, pa_rad=pa, center1=0.0, center2=0.0)
        whole = profiles.sersic_pixel_flux_exact(
            jnp.asarray(-3.5), jnp.asarray(2.5), jnp.asarray(-3.5), jnp.asarray(2.5), flux=1.0,
            re_arcsec=re, n=n, q=q, pa_rad=pa, center1=0.0, center2=0.0, nodes=64)
        assert abs(float(f.sum()) - float(whole)) < 1e-9


@pytest.mark.parametrize("center", [(0.31, 0.22), (1.7, -0.4)])
def test_quad_flux_exact_matches_brute_force_on_a_parallelogram(center):
    """The exact integral over a sheared, rotated quadrilateral (a lens pixel's source-plane
    footprint) against a 2000² midpoint sum over the affine image of the unit square, with
    the profile's centre inside and outside; either corner order gives the same flux."""
    v0, e1, e2 = np.array([-0.2, -0.3]), np.array([1.1, 0.4]), np.array([-0.5, 0.9])
    corners = np.stack([v0, v0 + e1, v0 + e1 + e2, v0 + e2])
    kw = dict(flux=1.0, re_arcsec=0.8, n=1.0, q=0.6, pa_rad=0.7, center1=center[0],
              center2=center[1])
    ours = float(profiles.sersic_quad_flux_exact(jnp.asarray(corners[:, 0]),
                                                 jnp.asarray(corners[:, 1]), **kw))
    reverse = float(profiles.sersic_quad_flux_exact(jnp.asarray(corners[::-1, 0]),
                                                    jnp.asarray(corners[::-1, 1]), **kw))
    s = (np.arange(2000) + 0.5) / 2000
    ss, tt = np.meshgrid(s, s)
    x = v0[0] + ss * e1[0] + tt * e2[0]
    y = v0[1] + ss * e1[1] + tt * e2[1]
    det = abs(e1[0] * e2[1] - e1[1] * e2[0])
    brute = float(np.mean(profiles.sersic_brightness(jnp.asarray(x), jnp.asarray(y), **kw))) * det
    assert ours == pytest.approx(brute, rel=2e-6)
    assert reverse == pytest.approx(ours, rel=1e-12)


def test_held_disk_values_times_flux_are_flux_times_disk_image_bit_for_bit():
    """A program given `disk_image_values` as data and scaling them by `disk_image_scale`
    and a flux makes flux × disk_image of one program bit for bit (XLA folds the pixel area
    into the flux there: a held disk_image times the flux differs in the last bit)."""
    grid = Grid(-2.1, -2.1, 0.3, 15, 15)    # a pixel area that rounds: 0.09
    d = _disk(0.6)
    d = dataclasses.replace(d, sersic=dataclasses.replace(d.sersic, flux=jnp.asarray([3.7])))
    one = jax.jit(lambda d: d.sersic.flux[0] * render.disk_image(d, grid, order=2))(d)
    values = jax.jit(lambda d: render.disk_image_values(d, grid, order=2))(d)
    scale = render.disk_image_scale(d, grid)
    held = jax.jit(lambda v, d: d.sersic.flux[0] * (v * scale))(values, d)
    np.testing.assert_array_equal(np.asarray(held), np.asarray(one))


@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32])
def test_profiles_on_several_grids_at_once_are_each_grids_own(dtype):
    """`render.sersic_images` / `disk_images_values` on grids of different sizes and pixels
    at once (one loop over the samples, each sample's coordinates from the pixel index) give
    each grid's own `sersic_image` / `disk_image_values`: the same samples added in the same
    order, so equal to the last bits or two."""
    grids = [Grid(-12.0, -9.0, 0.5, 31, 25), Grid(-4.0, -4.0, 0.25, 33, 33),
             Grid(-30.0, -30.0, 2.0, 17, 30)]
    c = lambda v: jnp.asarray(v, dtype)    # noqa: E731
    bulge = Sersic(c([1.0]), c(2.5), c(2.5), c(0.7), c(0.3), c([0.3, -0.2]))
    # with arms (sampled, as a textured disk is), without texture (a quicker compile)
    textured = jax.tree_util.tree_map(lambda a: a.astype(dtype) if a.dtype.kind == "f" else a,
                                      _disk(0.8))
    together = jax.jit(lambda: (render.sersic_images(bulge, grids, order=3, core=5),
                                render.disk_images_values(textured, grids, order=3, core=5)))()
    for k, g in enumerate(grids):
        alone = jax.jit(lambda g=g: (render.sersic_image(bulge, g, order=3, core=5),
                                     render.disk_image_values(textured, g, order=3,
                                                              core=5)))()
        for a, b in zip((together[0][k], together[1][k]), alone):
            a, b = np.asarray(a), np.asarray(b)
            assert a.shape == g.shape and a.dtype == dtype and np.all(np.isfinite(a))
            np.testing.assert_allclose(a, b, rtol=4 * np.finfo(dtype).eps,
                                       atol=4 * np.finfo(dtype).eps * np.abs(b).max())
