"""Analytic lenses: closed forms, κ from AD, rasterisation, safety at singular points."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from clumpylen_jax.lensing import (DPIE, NFW, SIE, SIS, ExternalShear, LensSum, MassSheet,
                                   grid_lensing_quantities, lensing_quantities, rasterize, with_scale)

C = jnp.array([0.3, -0.2])


def _lenses(dtype=jnp.float64):
    f = lambda v: jnp.asarray(v, dtype)  # noqa: E731
    c = f(C)
    return {
        "sis": SIS(f(1.5), c),
        "sie": SIE(f(1.5), f(0.7), f(0.4), c),
        "sie_round": SIE(f(1.5), f(1.0), f(0.4), c),
        "nfw": NFW(f(0.3), f(5.0), c),
        "dpie": DPIE(f(2.0), f(0.1), f(20.0), f(0.6), f(0.3), c),
        "dpie_nocore": DPIE(f(2.0), f(0.0), f(20.0), f(1.0), f(0.3), c),
        "shear": ExternalShear(f(0.05), f(-0.03), c),
        "sheet": MassSheet(f(0.2), c),
    }


@pytest.mark.parametrize("name", ["sis", "sie", "sie_round", "nfw", "dpie", "dpie_nocore"])
def test_kappa_from_ad_matches_closed_form(name):
    lens = _lenses()[name]
    rng = np.random.default_rng(1)
    t1 = jnp.asarray(rng.uniform(-6, 6, 50)).at[0].set(C[0] + 5.0)  # x = 1 for the NFW
    t2 = jnp.asarray(rng.uniform(-6, 6, 50)).at[0].set(C[1])
    k_ad = lensing_quantities(lens, t1, t2).kappa
    np.testing.assert_allclose(k_ad, lens.convergence(t1, t2), rtol=1e-9, atol=1e-12)


def test_nfw_at_x_equal_one_and_series_edges():
    lens = _lenses()["nfw"]
    for x in (1.0 - 1.001e-3, 1.0 - 0.999e-3, 1.0, 1.0 + 0.999e-3, 1.0 + 1.001e-3):
        k = lensing_quantities(lens, C[0] + 5.0 * x, C[1]).kappa
        assert np.isfinite(k)
    a_in = lens.deflection(C[0] + 5.0 * (1 - 0.999e-3), C[1])[0]
    a_out = lens.deflection(C[0] + 5.0 * (1 - 1.001e-3), C[1])[0]
    assert abs(a_in - a_out) < 1e-5  # continuous across the series switch
    assert float(lensing_quantities(lens, C[0] + 5.0, C[1]).kappa) == pytest.approx(0.2, rel=1e-6)


def test_sie_reduces_to_sis_and_dpie_to_circular_formula():
    t1, t2 = jnp.array([1.1, -2.0, 0.31]), jnp.array([0.7, 3.0, -0.2])
    sis, sie = _lenses()["sis"], SIE(1.5, 1.0 - 1e-9, 0.4, C)
    np.testing.assert_allclose(sie.deflection(t1, t2), sis.deflection(t1, t2), rtol=1e-7, atol=1e-8)
    b0, a, s = 2.0, 0.3, 15.0
    lens = DPIE(b0, a, s, 1.0, 0.0, jnp.zeros(2))
    r = jnp.array([0.5, 2.0, 40.0])
    expect = b0 * s / (s - a) * ((jnp.sqrt(a * a + r * r) - a) - (jnp.sqrt(s * s + r * r) - s)) / r
    np.testing.assert_allclose(lens.deflection(r, 0 * r)[0], expect, rtol=1e-10)


def test_dpie_from_sigma_matches_sis_einstein_radius():
    # SIS: θ_E = 4π σ²/c²; Lenstool dPIE: b0 = 6π σ0²/c², with σ_SIS² = 3/2 σ0².
    sigma_sis = 1000.0
    lens = DPIE.from_sigma(sigma_sis / np.sqrt(1.5), 0.0, 1e6, 1.0, 0.0, (0.0, 0.0))
    theta_e = 4 * np.pi * (sigma_sis / 299792.458) ** 2 * (180 / np.pi * 3600)
    assert float(lens.b0_arcsec) == pytest.approx(theta_e, rel=1e-9)


def test_shear_and_sheet_jacobians():
    lenses = _lenses()
    m = lensing_quantities(lenses["shear"], jnp.array([1.0, -3.0]), jnp.array([2.0, 0.5]))
    np.testing.assert_allclose(m.gamma1, 0.05)
    np.testing.assert_allclose(m.gamma2, -0.03)
    np.testing.assert_allclose(m.kappa, 0.0, atol=1e-15)
    m = lensing_quantities(lenses["sheet"], jnp.array([1.0]), jnp.array([2.0]))
    np.testing.assert_allclose(m.kappa, 0.2)


def test_lens_sum_and_scale():
    lenses = _lenses()
    total = LensSum([lenses["sie"], lenses["shear"]])
    t1, t2 = jnp.array([1.0, -2.0]), jnp.array([0.5, 1.5])
    a = np.add(lenses["sie"].deflection(t1, t2), lenses["shear"].deflection(t1, t2))
    np.testing.assert_allclose(total.deflection(t1, t2), a)
    np.testing.assert_allclose(with_scale(total, 0.8).deflection(t1, t2), 0.8 * a)
    np.testing.assert_allclose(with_scale(lenses["nfw"], 0.5).deflection(t1, t2),
                               0.5 * np.asarray(lenses["nfw"].deflection(t1, t2)))


def test_rasterized_kappa_matches_analytic():
    lens = SIE(1.5, 0.7, 0.4, jnp.zeros(2))
    nfw = NFW(0.2, 4.0, jnp.array([0.5, 0.5]))
    grid = rasterize(LensSum([lens, nfw]), ((-4, 4), (-4, 4)), 0.02)
    T1, T2, m = grid_lensing_quantities(grid)
    k_true = lens.convergence(T1, T2) + nfw.convergence(T1, T2)
    # away from the singular centres, where finite differences cannot follow κ
    far = (np.hypot(T1, T2) > 0.5) & (np.hypot(T1 - 0.5, T2 - 0.5) > 0.5)
    rel = np.abs(np.asarray(m.kappa)[far] / np.asarray(k_true)[far] - 1)
    assert np.median(rel) < 1e-4 and rel.max() < 2e-2


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_finite_value_and_gradient_at_centres(dtype):
    for name, lens in _lenses(dtype).items():
        def f(theta, lens=lens):
            a1, a2 = lens.deflection(theta[0], theta[1])
            return a1 + 2 * a2

        for pt in (C, C + jnp.array([1e-30, 0.0])):
            theta = pt.astype(dtype)
            val, grad = jax.value_and_grad(f)(theta)
            assert np.isfinite(val) and np.all(np.isfinite(grad)), name
            assert val.dtype == dtype, name

        # gradient with respect to every parameter, at the centre and at 1″
        for pt in (C, C + 1.0):
            g = jax.grad(lambda l, p=pt.astype(dtype): (lambda a: a[0] + a[1])(l.deflection(p[0], p[1])))(lens)
            leaves = jax.tree_util.tree_leaves(g)
            assert all(np.all(np.isfinite(x)) for x in leaves), name


def test_gradient_in_q_at_round_lens():
    g = jax.grad(lambda q: SIE(1.5, q, 0.4, C).deflection(2.0, 1.0)[0])(1.0)
    g2 = jax.grad(lambda q: DPIE(1.5, 0.1, 10.0, q, 0.4, C).deflection(2.0, 1.0)[0])(1.0)
    assert np.isfinite(g) and np.isfinite(g2)
    # compare with a one-sided finite difference
    eps = 1e-6
    fd = (SIE(1.5, 1.0, 0.4, C).deflection(2.0, 1.0)[0] - SIE(1.5, 1 - eps, 0.4, C).deflection(2.0, 1.0)[0]) / eps
    assert float(g) == pytest.approx(float(fd), rel=1e-3, abs=1e-6)
