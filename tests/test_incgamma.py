"""The fast Q(a, x) of the exact pixel integrals against scipy and JAX's gammaincc."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.special import gammaincc

from clumpylen_jax import incgamma

ORDERS = [0.4, 0.5, 1.0, 1.37, 2.0, 3.7, 8.0, 12.5, 20.0]      # a = 2n, n = 0.2 … 10
X = np.concatenate([[0.0, 1e-300, 1e-30, 1e-12], np.logspace(-8, np.log10(400), 6001)])


@pytest.mark.parametrize("a", ORDERS)
def test_q_upper_matches_scipy(a):
    got = np.asarray(jax.jit(incgamma.q_upper)(incgamma.q_table(jnp.float64(a)), jnp.asarray(X)))
    want = gammaincc(a, X)
    assert np.all(np.isfinite(got))
    assert np.max(np.abs(got - want)) < 5e-11          # measured ≤ 1.7e-11 (a = 20)
    # relative precision down the tail (the wings' pixels are differences of Q): on the
    # table (Q > 1e-25) measured ≤ 7.2e-8 (a = 20), ≤ 4.5e-11 for n ≤ 2; beyond it the
    # 4-term asymptotic series, ≤ 6.4e-5
    rel = np.abs(got / np.where(want > 0, want, 1.0) - 1)
    assert np.max(rel[want > 1e-25]) < 2e-7
    assert np.max(rel[want > 1e-300]) < 1e-3


def test_q_upper_float32():
    a = jnp.float32(2.6)
    got = np.asarray(incgamma.q_upper(incgamma.q_table(a), jnp.asarray(X, jnp.float32)))
    assert got.dtype == np.float32 and np.all(np.isfinite(got))
    assert np.max(np.abs(got - gammaincc(2.6, X.astype(np.float32)))) < 2e-6


@pytest.mark.parametrize("a", [0.4, 2.0, 20.0])
def test_q_upper_derivatives_match_gammaincc(a):
    x = jnp.asarray(np.concatenate([np.logspace(-4, 2.2, 80)]))

    def fast(a, x):
        return incgamma.q_upper(incgamma.q_table(a), x)

    for arg in (0, 1):
        g1 = jax.vmap(jax.grad(fast, arg), (None, 0))(jnp.float64(a), x)
        g2 = jax.vmap(jax.grad(jax.scipy.special.gammaincc, arg), (None, 0))(jnp.float64(a), x)
        np.testing.assert_allclose(g1, g2, atol=1e-9)


def test_q_upper_at_zero_is_one_with_finite_gradient():
    t = incgamma.q_table(jnp.float64(0.6))
    assert float(incgamma.q_upper(t, jnp.float64(0.0))) == 1.0
    g = jax.grad(lambda x: incgamma.q_upper(incgamma.q_table(jnp.float64(0.6)), x))(0.0)
    assert np.isfinite(g)


def test_indexed_tables_equal_single_tables():
    a = jnp.asarray([0.5, 3.0, 11.0])
    x = jnp.asarray(np.logspace(-3, 2, 7))
    tables = incgamma.q_table(a)
    for k in range(3):
        np.testing.assert_allclose(jax.vmap(lambda xx: incgamma.q_upper(tables, xx, k))(x),
                                   incgamma.q_upper(incgamma.q_table(a[k]), x), rtol=1e-14)


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_q_upper_gradients_finite_off_the_table(dtype):
    """Regression: lanes in the series or asymptotic range once took a NaN gradient from the
    (unused) table polynomial evaluated far off its interval (float32, n = 0.2)."""
    x = jnp.asarray([1e-40, 1e-20, 1e-6, 0.3, 3.0, 60.0, 500.0], dtype)
    for a in (0.4, 20.0):
        def total(a, x):
            return jnp.sum(incgamma.q_upper(incgamma.q_table(a), x))
        ga, gx = jax.grad(total, (0, 1))(jnp.asarray(a, dtype), x)
        assert np.isfinite(ga) and np.all(np.isfinite(gx))


@pytest.mark.parametrize("a", ORDERS)
def test_lower_gives_p_with_its_own_relative_precision(a):
    """P = 1 − Q where asked (pixels near a profile's centre): relative precision where P ≪ 1,
    which 1 − Q cannot have (the exact integrals of huge profiles, float32 above all)."""
    from scipy.special import gammainc
    x = np.concatenate([[1e-200, 1e-40], np.logspace(-25, np.log10(400), 3001)])
    want = gammainc(a, x)
    table = incgamma.q_table(jnp.float64(a))
    got = np.asarray(incgamma.q_upper(table, jnp.asarray(x), lower=True))
    assert np.all(np.isfinite(got))
    assert np.max(np.abs(got - want)) < 5e-11
    # where the series holds P (x ≤ x_lo): full relative precision, 1e-25 included
    series = (x <= float(table.x_lo)) & (want > 1e-290)     # (below, subnormal P is 0)
    np.testing.assert_allclose(got[series], want[series], rtol=3e-10)   # 1.1e-10 at x_lo (a = 20)
    # per element: P where lower, Q where not
    lower = np.arange(x.size) % 2 == 0
    mixed = np.asarray(incgamma.q_upper(table, jnp.asarray(x), lower=jnp.asarray(lower)))
    np.testing.assert_array_equal(mixed[lower], got[lower])
    np.testing.assert_array_equal(mixed[~lower], np.asarray(incgamma.q_upper(table, jnp.asarray(x)))[~lower])


def test_p_float32_keeps_relative_precision_near_zero():
    x = np.logspace(-30, -2, 57).astype(np.float32)
    got = np.asarray(incgamma.q_upper(incgamma.q_table(jnp.float32(0.4)), jnp.asarray(x), lower=True))
    from scipy.special import gammainc
    # exp(a ln x) in float32: ~eps·|a ln x| ≲ 4e-6
    np.testing.assert_allclose(got, gammainc(0.4, x.astype(np.float64)), rtol=1e-5)


@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32])
def test_lower_series_matches_scipy_where_b_of_n_needs_it(dtype):
    """`p_lower_series` (a fixed number of terms) is P(a, x) to rounding for x ≤ a ≤ 20,
    where b(n) of Sérsic n ≤ 10 is solved, with finite gradients in a and x."""
    from scipy.special import gammainc
    a = np.linspace(0.4, 20.0, 60)[:, None]
    x = a * np.linspace(0.01, 1.0, 40)[None, :]
    got = np.asarray(incgamma.p_lower_series(jnp.asarray(a, dtype), jnp.asarray(x, dtype)))
    tol = 1e-13 if dtype == jnp.float64 else 2e-5
    np.testing.assert_allclose(got, gammainc(a, x), rtol=tol)
    ga, gx = jax.grad(lambda a, x: incgamma.p_lower_series(a, x).sum(), (0, 1))(
        jnp.asarray(a, dtype), jnp.asarray(x, dtype))
    assert np.isfinite(np.asarray(ga)).all() and np.isfinite(np.asarray(gx)).all()
