"""Free-parameter maps, transforms, diagnostics, covariance inversion and the fit table (no model)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from clumpylen_jax.errors import ConfigError
from clumpylen_jax.inference import Free, Transform, make_state, parametrize, safe_inverse
from clumpylen_jax.inference.catalog import errors_state, fit_table
from clumpylen_jax.inference.diagnostics import effective_sample_size, split_rhat
from clumpylen_jax.inference.transforms import default_transform
from clumpylen_jax.inference.uncertainty import covariance_from_fisher_u
from clumpylen_jax.source import Clumps, Sersic, Source


def _source():
    return Source(bulge=Sersic(jnp.array([10.0, 8.0]), jnp.asarray(0.3), jnp.asarray(2.0),
                               jnp.asarray(1.0), jnp.asarray(0.0), jnp.zeros(2)),
                  clumps=Clumps(jnp.array([[0.1, 0.2], [-0.1, 0.0], [0.3, -0.2]]),
                                jnp.array([[1.0, 2.0], [0.0, 1.0], [3.0, 3.0]]),
                                jnp.array([0.05, 0.06, 0.07]), jnp.full(3, 0.5),
                                jnp.array([1.0, 0.5, 0.9]), jnp.array([0.1, 0.2, 0.3])))


@pytest.mark.parametrize("t", [Transform("identity"), Transform("log"), Transform("bounded", 1e-3, 1.0),
                               Transform("bounded", 0.2, 10.0), Transform("log_bounded", 0.1, 1e4)])
def test_transform_roundtrip_and_jacobian(t):
    u = jnp.linspace(-5, 5, 11)
    x = t.forward(u)
    np.testing.assert_allclose(t.inverse(x), u, atol=1e-8)
    jac = jax.vmap(jax.grad(lambda v: t.forward(v)))(u)
    np.testing.assert_allclose(t.log_abs_det_jacobian(u), np.log(np.abs(jac)), atol=1e-10)


def test_inverse_clips_bounds():
    q = default_transform("clumps.q")
    assert np.isfinite(q.inverse(1.0)) and q.forward(q.inverse(1.0)) <= 1.0
    assert np.isfinite(default_transform("clumps.flux").inverse(0.0))
    assert default_transform("clumps.n").kind == "bounded"
    assert default_transform("clumps.center_arcsec").kind == "identity"
    with pytest.raises(ConfigError):
        Transform("bounded", 1.0, 0.5)


def test_parametrize_roundtrip_selection_and_labels():
    src = _source()
    st = make_state(src, 2)
    p = parametrize(st, {"clumps.flux": [0, 2], "clumps.center_arcsec": True, "clumps.q": True,
                         "bulge.re_arcsec": True, "background": Free([1])})
    assert p.size == 4 + 6 + 3 + 1 + 1
    assert p.labels[0] == "clumps.flux[0,0]" and p.labels[-1] == "background[1]"
    u = p.initial()
    back = p.state(u)
    for a, b in zip(jax.tree_util.tree_leaves(back), jax.tree_util.tree_leaves(st)):
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-9)
    # fixed entries stay, free ones move, q never leaves (0, 1]
    moved = p.state(u + 3.0)
    assert float(moved.source.clumps.flux[1, 0]) == 0.0
    assert np.all(np.asarray(moved.source.clumps.q) <= 1.0)
    assert np.all(np.asarray(p.state(u - 50.0).source.clumps.q) > 0)
    errs = p.scatter(jnp.arange(p.size, dtype=float))
    assert np.isnan(float(errs.source.clumps.flux[1, 0])) and float(errs.source.clumps.flux[0, 0]) == 0.0
    with pytest.raises(ConfigError):
        parametrize(st, {"disk.sersic.flux": True})
    with pytest.raises(ConfigError):
        parametrize(st, {"clumps.flux": [7]})


def test_safe_inverse_singular_stays_finite():
    f = np.diag([4.0, 1.0, 0.0])
    c = np.asarray(safe_inverse(jnp.asarray(f)))
    assert np.all(np.isfinite(c))
    np.testing.assert_allclose(c[0, 0], 0.25)
    assert c[2, 2] > 1e10
    assert np.all(np.isfinite(np.asarray(safe_inverse(jnp.zeros((2, 2))))))


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_covariance_from_fisher_u_with_a_saturated_transform(dtype):
    """`uncertainty.covariance_from_fisher_u`: an entry whose transform has saturated (dx/du
    = 0, so its Jacobian column in u and its row of JᵀJ are 0) gets a huge variance and the
    others their exact one, finite, in float32 and float64 (dividing by the slope squared,
    which underflows, gave 0/0: NaN everywhere)."""
    f = np.zeros((3, 3))
    f[:2, :2] = [[4.0, 1.0], [1.0, 3.0]]
    slope = np.array([2.0, 0.5, 0.0])
    cov = np.asarray(covariance_from_fisher_u(jnp.asarray(f, dtype), jnp.asarray(slope, dtype)))
    assert np.all(np.isfinite(cov))
    want = np.linalg.inv(f[:2, :2] / np.outer(slope[:2], slope[:2]))
    np.testing.assert_allclose(cov[:2, :2], want, rtol=1e-5 if dtype == np.float32 else 1e-10)
    assert cov[2, 2] > 1e6 * np.abs(want).max()


def test_safe_inverse_keeps_weak_parameters_errors_beside_a_strong_one():
    """Fisher diagonals spanning 20 decades (physical units) and two null directions: the
    measured parameters get the errors of inverting their own block (the nulls are
    uncorrelated with them up to 1e-10); unscaled, the eigenvalue floor rcond·max (4e8) sat
    above their eigenvalues (4e4, 4e2) and shrank their errors 100×."""
    rng = np.random.default_rng(0)
    b = rng.normal(size=(400, 5))
    jac = b * np.array([1e9, 10.0, 1.0, 1e-9, 1e-9])
    jac[:, 3:] += 1e-10 * b[:, 1:2]
    f = jac.T @ jac
    err = np.sqrt(np.diag(np.asarray(safe_inverse(jnp.asarray(f)))))
    np.testing.assert_allclose(err[:3], np.sqrt(np.diag(np.linalg.inv(f[:3, :3]))), rtol=1e-6)
    assert np.all(err[3:] > 1e3) and np.all(np.isfinite(err))


def test_diagnostics_iid_and_stuck_chains():
    rng = np.random.default_rng(1)
    iid = rng.standard_normal((4, 1000, 2))
    assert np.all(np.abs(split_rhat(iid) - 1) < 0.02)
    ess = effective_sample_size(iid)
    assert np.all(ess > 2500) and np.all(ess < 5500)
    ar = np.zeros((4, 1000))
    for t in range(1, 1000):  # AR(1), ρ = 0.9: τ = 19
        ar[:, t] = 0.9 * ar[:, t - 1] + rng.standard_normal(4)
    assert 80 < effective_sample_size(ar)[0] < 450
    shifted = iid + np.arange(4)[:, None, None]
    assert np.all(split_rhat(shifted) > 1.5)


def test_fit_table_columns_and_errors():
    src = _source()
    st = make_state(src, 2)
    p = parametrize(st, {"clumps.flux": True, "clumps.center_arcsec": True})
    t = fit_table(st, errors_state(p, np.full(p.size, 0.1)), band_names=("F150W", "F200W"),
                  zeropoints_ab={"F150W": 28.0, "F200W": 27.5})
    for c in ("beta1_arcsec", "beta1_arcsec_err", "beta2_arcsec", "re_arcsec", "re_arcsec_err", "q",
              "pa_rad", "flux_F150W", "flux_F150W_err", "mag_F200W", "mag_F200W_err"):
        assert c in t.colnames
    assert len(t) == 3
    np.testing.assert_allclose(t["mag_F150W"][0], 28.0)
    np.testing.assert_allclose(t["mag_F150W_err"][0], 2.5 / np.log(10) * 0.1)
    assert np.isinf(t["mag_F150W"][1])  # zero flux
    assert np.all(np.isnan(t["re_arcsec_err"]))  # not fitted
