"""fit_without_truth: clumps found, seeded and counted from the image alone (issue 18)."""

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from clumpylen_jax import profiles
from clumpylen_jax.errors import ConfigError
from clumpylen_jax.inference import auto
from clumpylen_jax.inference.auto import AutoOptions, fit_without_truth
from clumpylen_jax.inference.capacity import psf_sigma_pixels
from clumpylen_jax.inference.mock import TOY_ACCURACY, toy_bands
from clumpylen_jax.inference.seeding import Candidates
from clumpylen_jax.model import Band, build_model
from clumpylen_jax.pixels import Grid
from clumpylen_jax.source import Clumps, Sersic, Source

PIX = 0.03
NPIX = 41
HALF = 0.5 * NPIX * PIX
FIELD = ((-HALF, HALF), (-HALF, HALF))
ACC = dataclasses.replace(TOY_ACCURACY, psf_oversampling=3)
BANDS = toy_bands(1, psf_sigma_pix=1.0)
HOST = Sersic(jnp.array([40.0]), jnp.asarray(0.25), jnp.asarray(1.0), jnp.asarray(0.7),
              jnp.asarray(0.4), jnp.zeros(2))
CENTERS = np.array([[-0.2, 0.1], [0.2, -0.15], [0.05, 0.25]])
CLUMPS = Clumps(jnp.asarray(CENTERS), jnp.array([[4.0], [3.0], [2.0]]), jnp.array([0.02, 0.04, 0.03]),
                jnp.full(3, 0.5), jnp.array([0.8, 0.9, 0.7]), jnp.array([0.3, 1.0, -0.5]))


def make_model(src):
    return build_model(src, BANDS, field_arcsec=FIELD, accuracy=ACC)


def _observe(truth, seed):
    noisy, _, var = make_model(truth).observe(truth, jax.random.key(seed))
    return [np.asarray(noisy[0])], [np.asarray(var[0])]


def test_options_are_checked_before_any_work():
    with pytest.raises(ConfigError, match="fit.criterion"):
        fit_without_truth(make_model, [np.zeros((NPIX, NPIX))], [np.ones((NPIX, NPIX))],
                          options=AutoOptions(criterion="aic"))
    with pytest.raises(ConfigError, match="fit.rtol"):
        fit_without_truth(make_model, [np.zeros((NPIX, NPIX))], [np.ones((NPIX, NPIX))],
                          options=AutoOptions(rtol=0.0))
    with pytest.raises(ConfigError, match="data"):
        fit_without_truth(make_model, [np.zeros((5, 5))], [np.ones((5, 5))])


def _blobs(centers_pix, fluxes, sigma=1.2, shape=(NPIX, NPIX)):
    yy, xx = np.mgrid[:shape[0], :shape[1]]
    img = np.zeros(shape)
    for (r, c), f in zip(centers_pix, fluxes):
        img += f * np.exp(-0.5 * ((yy - r) ** 2 + (xx - c) ** 2) / sigma**2) / (2 * np.pi * sigma**2)
    return img


def test_candidates_from_residual_peaks():
    """Three blobs in noise: three candidates at their pixels, brightest first, fluxes close."""
    from clumpylen_jax.inference.seeding import find_candidates
    grid_model = auto._GridsOnly([Grid.covering(*FIELD, PIX)])
    rng = np.random.default_rng(0)
    sigma = 0.02
    pix = [(10, 12), (25, 30), (30, 8)]
    img = _blobs(pix, [4.0, 2.0, 1.0]) + rng.normal(0, sigma, (NPIX, NPIX))
    cand = find_candidates(grid_model, [img], [np.full(img.shape, sigma**2)],
                           [np.ones(img.shape)], psf_sigma_pix=np.array([1.2]),
                           threshold_snr=5.0, max_candidates=5)
    assert len(cand) == 3
    assert [tuple(p) for p in cand.theta_pix] == pix
    assert np.all(np.abs(cand.flux[:, 0] / np.array([4.0, 2.0, 1.0]) - 1) < 0.35)
    g = grid_model.layouts[0].grid
    assert np.allclose(cand.beta_arcsec[0], [g.x_centers()[12], g.y_centers()[10]])


def test_candidates_in_bands_of_two_pixel_scales():
    """NIRCam SW and LW fitted together (pixels 1 and 2 × PIX, images of different shapes):
    the peaks are found in the finer band and each band's flux measured on its own grid
    (this crashed on an aperture of the finer grid applied to the coarser image)."""
    from clumpylen_jax.inference.seeding import find_candidates
    fine, coarse = Grid.covering(*FIELD, PIX), Grid.covering(*FIELD, 2 * PIX)
    grid_model = auto._GridsOnly([fine, coarse])
    rng = np.random.default_rng(1)
    sigma = 0.02
    pix = [(10, 12), (26, 30)]
    img = _blobs(pix, [4.0, 2.0], shape=fine.shape) + rng.normal(0, sigma, fine.shape)
    img2 = _blobs([(r / 2 - 0.25, c / 2 - 0.25) for r, c in pix], [3.0, 1.5], sigma=0.7,
                  shape=coarse.shape) + rng.normal(0, sigma, coarse.shape)
    assert img.shape != img2.shape
    cand = find_candidates(grid_model, [img, img2], [np.full(img.shape, sigma**2),
                                                    np.full(img2.shape, sigma**2)],
                           [np.ones(img.shape), np.ones(img2.shape)],
                           psf_sigma_pix=np.array([1.2, 0.7]), threshold_snr=5.0, max_candidates=5)
    assert [tuple(p) for p in cand.theta_pix] == pix
    np.testing.assert_allclose(cand.flux / np.array([[4.0, 3.0], [2.0, 1.5]]), 1.0, atol=0.35)


def test_psf_sigma_is_the_cores_not_the_wings():
    """The seeding's PSF σ (matched filter, size deconvolution) is the core's: FWHM / 2.3548.
    A Gaussian gives its σ (⊕ the pixel's 1/12); a Gaussian core with 10 % of the flux in a
    broad halo (σ 8 px, like a real PSF's wings) still gives the core's, where the second
    moments would give √(0.9 + 0.1 · 64) ≈ 2.7 px."""

    r = np.arange(-30, 31)
    rr = r[:, None] ** 2 + r[None, :] ** 2
    core, halo = np.exp(-0.5 * rr / 1.0**2), np.exp(-0.5 * rr / 8.0**2)
    winged = 0.9 * core / core.sum() + 0.1 * halo / halo.sum()
    bands = [Band("G", PIX, 1000.0, 0.05, psf=core / core.sum(), psf_pixel_arcsec=PIX),
             Band("W", PIX, 1000.0, 0.05, psf=winged, psf_pixel_arcsec=PIX)]
    src = Source(clumps=CLUMPS)
    model = build_model(src, bands, field_arcsec=FIELD, accuracy=TOY_ACCURACY)
    sig = psf_sigma_pixels(model)
    expect = np.sqrt(1.0 + 1 / 12)
    np.testing.assert_allclose(sig[0], expect, rtol=0.02)
    # the halo widens the half-maximum contour a little (its 10 % adds to the core's wings)
    assert sig[0] < sig[1] < 1.15 * sig[0]


def test_images_of_one_source_clump_are_merged():
    """Two candidates whose β agree within the tolerance are one clump (fluxes de-magnified)."""
    from clumpylen_jax.inference.seeding import merge_images
    beta = np.array([[0.1, 0.0], [0.1004, 0.0003], [0.3, 0.2]])
    det = np.array([0.1, 0.1, 0.5])      # |μ| = 10, 10, 2
    groups = merge_images(beta, det, np.array([20.0, 12.0, 8.0]), 2.0, 0.03)
    assert groups == [[0, 1], [2]]


@pytest.mark.slow
def test_three_clumps_found_from_a_generic_start():
    """Host + 3 clumps, nothing known: 3 clumps kept, each within 1 pixel of a true one."""
    data, var = _observe(Source(bulge=HOST, clumps=CLUMPS), 1)
    fit = fit_without_truth(make_model, data, var, options=AutoOptions(max_clumps=5, n_starts=3))
    t = fit.table
    assert len(t) == 3, fit.steps
    got = np.c_[t["beta1_arcsec"], t["beta2_arcsec"]]
    d = np.hypot(*(got[:, None, :] - CENTERS[None]).transpose(2, 0, 1))
    assert np.all(d.min(axis=0) < PIX), d
    assert sorted(np.argmin(d, axis=1)) == [0, 1, 2]
    assert [s["action"] for s in fit.steps][:4] == ["host", "add", "add", "add"]
    assert fit.steps[4]["action"] in ("reject", "stop")
    assert np.all(np.isfinite(t["flux_B0_err"])) and np.all(t["flux_B0_err"] > 0)
    assert "flag" in t.colnames and "blend_corr" in t.colnames
    # an R_e upper limit (size_limits) where, and only where, the size is unresolved
    ul, unresolved = np.asarray(t["re_arcsec_ul"]), (t["flag"] & auto.FLAGS["size_unresolved"]) > 0
    assert np.array_equal(np.isfinite(ul), unresolved)
    assert np.all(ul[unresolved] > np.asarray(t["re_arcsec"])[unresolved])


@pytest.mark.slow
def test_start_size_does_not_change_the_optimum():
    """Regression: a clump started at R_e = 1 px that grows to 5 px lands where one started at
    5 px does (its stamp is sized for the prior range, not for the start)."""
    big = Clumps(jnp.array([[0.03, -0.02]]), jnp.array([[30.0]]), jnp.array([5 * PIX]),
                 jnp.full(1, 0.5), jnp.ones(1), jnp.zeros(1))
    data, var = _observe(Source(bulge=HOST, clumps=big), 2)
    opts = AutoOptions(max_clumps=1, n_starts=2, re_max_arcsec=10 * PIX).validate()
    ctx, u0 = auto._setup(make_model, data, var, None, None, None, opts)
    u_host, _ = auto._fit_host(ctx, u0, [])

    def cand(re):
        return Candidates(np.array([[0.0, 0.0]]), np.array([[20.0]]), np.array([re]), np.ones(1),
                          np.zeros(1), np.ones(1), np.ones(1, int), np.zeros((1, 2), int))
    starts = np.stack([auto._seed_slot(ctx, u_host, 0, cand(r), 0) for r in (1 * PIX, 5 * PIX)])
    us, lnl, ok, _ = auto._fit_local(ctx, starts, [[0], [0]], np.ones((2, 1)))
    x = [np.asarray(ctx.param.state(jnp.asarray(u)).source.clumps.re_arcsec)[0] for u in us]
    assert np.all(ok)
    assert abs(x[0] / (5 * PIX) - 1) < 0.15
    assert abs(x[0] / x[1] - 1) < 1e-4 and abs(lnl[0] - lnl[1]) < 1e-3


def _final_near_truth():
    """`auto._final` (3 starts) of the three clumps started 0.01" off their true centres:
    (us, lnls, oks, best, JᵀJ, entries, steps)."""
    data, var = _observe(Source(clumps=CLUMPS), 4)
    opts = AutoOptions(max_clumps=3, n_starts=3, host=False).validate()
    ctx, u = auto._setup(make_model, data, var, None, None, None, opts)
    for slot, c in enumerate(CENTERS):
        u = auto._set_clump(ctx, u, slot, c + 0.01, [2.5], 0.03)
    steps = []
    return auto._final(ctx, u, np.ones(3), steps) + (steps,)


def test_final_refit_caps_the_perturbed_starts(monkeypatch):
    """`auto._final`: the unperturbed start runs first, the perturbed ones get at most
    FINAL_STEP_FACTOR times its LM steps (at least FINAL_MIN_STEPS), and the start kept is
    the best, converged (one that beat the unperturbed start unconverged is carried on).
    Here the cap is set to the unperturbed start's own steps (6), and the perturbed starts
    are thrown 0.1 off in every entry (FINAL_START_SIGMA made huge, the clip binding), so
    that it binds: such a start takes 9 steps uncapped. The clumps start 0.01" off the true
    centres: the point is the cap's mechanics, not finding them."""
    monkeypatch.setattr(auto, "FINAL_STEP_FACTOR", 1)
    monkeypatch.setattr(auto, "FINAL_MIN_STEPS", 1)
    monkeypatch.setattr(auto, "FINAL_START_SIGMA", 1e6)
    us, lnls, oks, b, jtj, idx, steps = _final_near_truth()
    n = steps[-1]["starts_n_steps"]
    assert len(n) == len(lnls) == 3 and steps[-1]["n_steps"] == n[b]
    capped = [k for i, k in enumerate(n[1:], 1) if i != b]
    assert capped and max(capped) == n[0], (n, b)     # the cap reached, never passed
    assert b == int(np.argmax(lnls)) and oks[b]
    assert np.all(np.isfinite(jtj)) and jtj.shape == (idx.size, idx.size)


def test_final_starts_probe_the_optimums_basin():
    """`auto._final` with its defaults: the perturbed starts, drawn about the unperturbed
    optimum at 3 times its Fisher errors (its JᵀJ), all come back within Δln L 2 of the
    best, so the table's spread (starts within Δln L 2) is over every start, not the best
    alone, and each takes no more LM steps than the unperturbed start (here 5, 5 against 6;
    thrown 0.1 off in every entry, as before, 7 each). The clumps start 0.01" off the true
    centres: the point is the starts about the optimum, not finding it."""
    us, lnls, oks, b, jtj, idx, steps = _final_near_truth()
    assert len(lnls) == 3 and np.all(oks)
    assert np.all(lnls >= lnls.max() - 2.0), lnls
    n = steps[-1]["starts_n_steps"]
    assert max(n[1:]) <= n[0], n
    assert np.ptp(us[:, idx[idx < us.shape[1]]], axis=0).max() > 0     # they did start elsewhere


def test_final_start_offsets_follow_the_fisher_covariance():
    """`auto._start_offsets`: N(0, 9 Cov_u) over the fitted entries (Cov_u = (JᵀJ)⁻¹), zero on
    the others and on padding; an entry the data do not constrain (JᵀJ ~ 0 there) is clipped
    to ±FINAL_START_MAX_U instead of thrown to its huge variance."""
    rng = np.random.default_rng(3)
    a = rng.normal(size=(6, 3))
    jtj = np.zeros((5, 5))
    jtj[:3, :3] = a.T @ a * 1e4                       # σ ~ 0.01: well inside the clip
    jtj[3, 3] = 1e-30                                 # unconstrained
    idx = np.array([4, 0, 2, 6, 7])                   # entry 7 = size: padding
    off = auto._start_offsets(jtj, idx, 7, 20000, rng)
    assert off.shape == (20000, 7)
    assert np.all(off[:, [1, 3, 5]] == 0.0)
    want = auto.FINAL_START_SIGMA ** 2 * np.linalg.inv(jtj[:3, :3])
    got = np.cov(off[:, [4, 0, 2]].T)
    np.testing.assert_allclose(got, want, rtol=0.05, atol=0.05 * np.abs(want).max())
    assert np.abs(off[:, 6]).max() == pytest.approx(auto.FINAL_START_MAX_U)


def test_final_start_offsets_where_the_fisher_matrix_is_not_finite():
    """A refit that ended with a non-finite JᵀJ: the offsets fall back to N(0, 0.1²) per
    fitted entry (clipped), finite, instead of an eigendecomposition that raises."""
    jtj = np.full((3, 3), np.nan)
    off = auto._start_offsets(jtj, np.array([0, 2, 4]), 4, 500, np.random.default_rng(0))
    assert np.all(np.isfinite(off)) and np.all(off[:, [1, 3]] == 0.0)
    assert 0.05 < off[:, 0].std() < 0.1 and np.abs(off).max() <= auto.FINAL_START_MAX_U


def test_lm_reports_success_only_at_a_minimum():
    """inference/lm.py, the one Levenberg–Marquardt: a linear least-squares problem is solved
    exactly and reported converged; cut short (2 steps) it is not; and a point where every
    trial fails (damping at its maximum, gradient ≠ 0) is reported NOT converged (the
    solver this replaced counted that as converged)."""
    from clumpylen_jax.inference.lm import levenberg_marquardt
    a = jnp.array([[2.0, 1.0], [1.0, 3.0], [0.5, -1.0]])
    b = jnp.array([1.0, -2.0, 0.5])
    exact = np.linalg.lstsq(np.asarray(a), np.asarray(b), rcond=None)[0]
    r = levenberg_marquardt(lambda u: a @ u - b, jnp.zeros(2), 50, 1e-10)
    assert bool(r.success) and np.allclose(r.u, exact, atol=1e-8)
    assert not bool(levenberg_marquardt(lambda u: jnp.exp(a @ u) - 3.0, jnp.zeros(2), 2, 1e-10).success)
    stuck = levenberg_marquardt(lambda u: jnp.where(jnp.all(u == 0.0), u - 1.0, jnp.nan),
                                jnp.zeros(2), 100, 1e-10)
    assert not bool(stuck.success) and int(stuck.n_steps) < 100 and np.all(np.asarray(stuck.u) == 0)


def test_lm_brings_an_entry_that_ran_past_its_limit_back_and_linearises_there():
    """u_limits: x = sigmoid(u) fitted to data below its bound runs u off to −∞ (dx/du
    underflows, and JᵀJ with it); with the transforms' limits the result sits at the limit,
    its JᵀJ is that of the slope there (not 0), it is still converged, and the extra step is
    counted. A fit that stays inside its limits is unchanged to the bit."""
    from clumpylen_jax.inference.lm import levenberg_marquardt
    from clumpylen_jax.inference.transforms import U_EDGE
    resid = lambda u: 1e3 * (jax.nn.sigmoid(u) - jnp.array([-0.1, 0.3]))  # noqa: E731
    free = levenberg_marquardt(resid, jnp.zeros(2), 400, 1e-10)
    held = levenberg_marquardt(resid, jnp.zeros(2), 400, 1e-10, u_limits=(
        np.array([-U_EDGE, -U_EDGE]), np.array([U_EDGE, U_EDGE])))
    assert float(free.u[0]) < -U_EDGE - 5
    assert float(held.u[0]) == -U_EDGE and bool(held.success) == bool(free.success)
    slope = float(jax.nn.sigmoid(-U_EDGE) * (1 - jax.nn.sigmoid(-U_EDGE)))
    assert float(held.jtj[0, 0]) == pytest.approx((1e3 * slope) ** 2, rel=1e-6)
    assert int(held.n_steps) == int(free.n_steps) + 1 and float(held.u[1]) == float(free.u[1])
    inside = levenberg_marquardt(lambda u: jax.nn.sigmoid(u) - 0.3, jnp.zeros(1), 100, 1e-10)
    same = levenberg_marquardt(lambda u: jax.nn.sigmoid(u) - 0.3, jnp.zeros(1), 100, 1e-10,
                               u_limits=(np.array([-U_EDGE]), np.array([U_EDGE])))
    assert float(same.u[0]) == float(inside.u[0]) and int(same.n_steps) == int(inside.n_steps)


def test_lm_damps_an_entry_whose_jacobian_column_all_but_vanishes():
    """lm.DAMPING_FLOOR: the third entry moves the residual by ~1e-98 per unit (erf far in its
    tail, as a clump's position when its light sits in one PSF sub-pixel), and a huge step in
    it costs Δχ² 30. Damped by λ·Jᵢ² alone its trial step was ~1e98 whatever λ, every trial
    failed and the fit stopped at the start (χ² 5.5 where the minimum is 0.92), not
    converged. With the floor the other entries reach the least-squares solution and the fit
    is converged there, the third entry unmoved; cut short (2 steps) it is not converged."""
    from jax.scipy.special import erf
    from clumpylen_jax.inference.lm import levenberg_marquardt
    a = jnp.array([[2.0, 1.0], [1.0, 3.0], [0.5, -1.0]])
    b = jnp.array([1.0, -2.0, 0.5])
    exact = np.linalg.lstsq(np.asarray(a), np.asarray(b), rcond=None)[0]

    def resid(u):
        return jnp.concatenate([a @ u[:2] - b, jnp.atleast_1d(3.0 * erf(u[2]) - 2.5)])

    u0 = jnp.array([0.0, 0.0, 15.0])
    r = levenberg_marquardt(resid, u0, 100, 1e-10)
    assert bool(r.success) and int(r.n_steps) < 10
    assert np.allclose(r.u[:2], exact, atol=1e-8) and float(r.u[2]) == 15.0
    assert np.isclose(float(r.chi2), float(np.sum((np.asarray(a) @ exact - np.asarray(b))**2)) + 0.25)
    short = levenberg_marquardt(resid, u0, 2, 1e-10)
    assert not bool(short.success) and not np.allclose(short.u[:2], exact, atol=1e-8)


@pytest.mark.slow
def test_fisher_with_an_active_mask_is_the_fisher_of_the_active_clumps():
    """uncertainty.fisher_matrix(active=...) (the Fisher of the fixed-capacity fits): the
    block of the active clumps equals the Fisher matrix of a model holding only them, and
    inactive slots have zero rows."""
    from clumpylen_jax.inference.params import make_state, parametrize
    from clumpylen_jax.inference.uncertainty import fisher_matrix
    free = {"clumps.flux": True, "clumps.re_arcsec": True, "bulge.flux": True}
    src = Source(bulge=HOST, clumps=CLUMPS)
    param = parametrize(make_state(src, 1), free)
    f_masked = np.asarray(fisher_matrix(make_model(src), param, active=np.array([1.0, 0.0, 1.0])))
    keep = jax.tree_util.tree_map(lambda x: x[np.array([0, 2])], CLUMPS)
    src2 = Source(bulge=HOST, clumps=keep)
    f2 = np.asarray(fisher_matrix(make_model(src2), parametrize(make_state(src2, 1), free)))
    lab = list(param.labels)
    rows = [i for i, s in enumerate(lab) if "[1" not in s or s.startswith("bulge")]
    dead = [i for i in range(len(lab)) if i not in rows]
    assert len(dead) == 2 and np.all(f_masked[dead] == 0)
    assert np.allclose(f_masked[np.ix_(rows, rows)], f2, rtol=1e-8, atol=0)


def _host_disk_case(n_bands=1, diffuse_spacing_arcsec=None):
    """(model, data, param) of a bulge, a disk and three round-Gaussian clumps, the data
    1.1× the model, every host, clump and background entry free but the host's shape;
    n_bands bands (fluxes of another colour in each), an optional diffuse light."""
    from clumpylen_jax.inference.likelihood import make_data
    from clumpylen_jax.inference.params import make_state, parametrize
    from clumpylen_jax.source import Disk
    scale = 1.0 + 0.5 * np.arange(n_bands)       # a colour: fluxes differ between bands
    host = dataclasses.replace(HOST, flux=HOST.flux[0] * jnp.asarray(scale))
    src = Source(bulge=host, disk=Disk(dataclasses.replace(host, re_arcsec=jnp.asarray(0.4)),
                                       jnp.asarray(0.5)),
                 clumps=dataclasses.replace(CLUMPS, q=jnp.ones(3),
                                            flux=CLUMPS.flux[:, :1] * jnp.asarray(scale[::-1])))
    bands = BANDS if n_bands == 1 else toy_bands(n_bands, psf_sigma_pix=1.0)
    model = build_model(src, bands, field_arcsec=FIELD,
                        accuracy=dataclasses.replace(ACC, clump_pixels="round_gaussian"))
    imgs = [np.asarray(i) for i in eqx.filter_jit(lambda m, s: m.noiseless(s))(model, src)]
    data = make_data(model, [i * (1.1 + 0.1 * k) for k, i in enumerate(imgs)],
                     [np.ones_like(i) for i in imgs], kind="gaussian",
                     diffuse_spacing_arcsec=diffuse_spacing_arcsec)
    param = parametrize(make_state(src, n_bands), {
        "bulge.flux": True, "bulge.re_arcsec": True, "disk.sersic.flux": True,
        "clumps.flux": True, "clumps.center_arcsec": True, "clumps.re_arcsec": True,
        "background": True})
    return model, data, param


def test_blockwise_jacobian_is_the_jacobian():
    """lm.blockwise (host and background columns with the clumps held, clump columns with the
    host held) gives the Jacobian of one jacfwd over every entry, for a bulge, a disk and
    round-Gaussian clumps."""
    from clumpylen_jax.inference.likelihood import make_residuals
    from clumpylen_jax.inference.lm import blockwise, held_residuals
    from clumpylen_jax.inference.params import part_blocks
    model, data, param = _host_disk_case()
    u = param.initial() + 0.01
    host, clumps = part_blocks(param)
    assert host.size == 4 and clumps.size == 12
    r, J = jax.jit(blockwise(held_residuals(model, data, param), (host, clumps)))(u)
    resid = jax.jit(make_residuals(model, data, param))
    J0 = jax.jit(jax.jacfwd(resid))(u)
    assert np.abs(np.asarray(r) - np.asarray(resid(u))).max() <= 1e-12 * np.abs(np.asarray(r)).max()
    assert np.abs(np.asarray(J) - np.asarray(J0)).max() <= 1e-12 * np.abs(np.asarray(J0)).max()
    assert np.abs(np.asarray(J0)[:, clumps]).max() > 0 and np.abs(np.asarray(J0)[:, host]).max() > 0


def test_blockwise_jacobian_with_linear_groups_is_the_jacobian():
    """lm.blockwise with the per-band linear columns (host and clump fluxes, background) made
    by groups, one derivative each split by band (`lm.columns_by_kind`): the Jacobian of
    one jacfwd, with two bands of different colours and a diffuse light profiled out (each
    band's residuals, its diffuse entries too, move with its own fluxes only)."""
    from clumpylen_jax.inference.likelihood import make_residuals
    from clumpylen_jax.inference.lm import band_of_residuals, blockwise, held_residuals
    from clumpylen_jax.inference.params import entry_kinds, part_blocks
    for diffuse in (None, 0.3):
        model, data, param = _host_disk_case(n_bands=2, diffuse_spacing_arcsec=diffuse)
        u = param.initial() + 0.01
        kinds = entry_kinds(param, np.arange(param.size))
        assert sum(k[0] == "clumps.flux" for k in kinds) == 6 and \
            {k[2] for k in kinds if k[0] == "clumps.flux"} == {0, 1, 2}
        r, J = jax.jit(blockwise(held_residuals(model, data, param), part_blocks(param), kinds,
                                 band_of_residuals(data)))(u)
        resid = jax.jit(make_residuals(model, data, param))
        J0 = np.asarray(jax.jit(jax.jacfwd(resid))(u))
        assert np.abs(np.asarray(r) - np.asarray(resid(u))).max() <= 1e-12 * np.abs(np.asarray(r)).max()
        assert np.abs(np.asarray(J) - J0).max() <= 1e-12 * np.abs(J0).max()
        flux_cols = [p for p, k in enumerate(kinds) if k[0] is not None]
        assert np.all(np.abs(J0[:, flux_cols]).max(axis=0) > 0)


def test_lm_with_a_traced_zero_step_limit_takes_no_step():
    """A start that only pads the compiled batch (auto._step_limits gives it 0 steps) costs no
    step: u0 back, χ² = inf (ln L = −inf, never the best), not converged; a traced limit of 50
    in the same program solves the problem."""
    from clumpylen_jax.inference.lm import levenberg_marquardt
    a = jnp.array([[2.0, 1.0], [1.0, 3.0], [0.5, -1.0]])
    b = jnp.array([1.0, -2.0, 0.5])
    solve = jax.jit(lambda n: levenberg_marquardt(lambda u: a @ u - b, jnp.ones(2), n, 1e-10))
    pad, real = solve(jnp.asarray(0)), solve(jnp.asarray(50))
    assert int(pad.n_steps) == 0 and not bool(pad.success) and np.isinf(float(pad.chi2))
    assert np.all(np.asarray(pad.u) == 1.0)
    assert bool(real.success) and int(real.n_steps) > 0



def _rows_case():
    """Four round-Gaussian clumps (no host: its exact pixels would take long to compile),
    slot 2 inactive, rows 1 and 2 moved, in `capacity.solve_local_batch`'s layout (the
    background, then per row its flux, β, R_e; two padding rows, row 4, entries u.size):
    (model, data, param, u, active, slots, idx)."""
    from clumpylen_jax.inference.likelihood import make_data
    from clumpylen_jax.inference.params import make_state, parametrize
    cl = Clumps(jnp.asarray(np.r_[CENTERS, [[0.0, -0.3]]]), jnp.array([[4.0], [3.0], [2.0], [1.0]]),
                jnp.array([0.02, 0.04, 0.03, 0.05]), jnp.full(4, 0.5), jnp.ones(4), jnp.zeros(4))
    src = Source(clumps=cl)
    model = build_model(src, BANDS, field_arcsec=FIELD,
                        accuracy=dataclasses.replace(ACC, clump_pixels="round_gaussian"))
    data = make_data(model, [np.zeros((NPIX, NPIX))], [np.ones((NPIX, NPIX))], kind="gaussian")
    param = parametrize(make_state(src, 1), {
        "clumps.flux": True, "clumps.center_arcsec": True, "clumps.re_arcsec": True,
        "background": True})
    # u: flux [4], β [4, 2], R_e [4], background
    idx = np.r_[param.size - 1, np.ravel([[i, 4 + 2 * i, 5 + 2 * i, 12 + i] for i in (1, 2)]),
                np.full(8, param.size)]
    return (model, data, param, param.initial() + 0.01, jnp.array([1.0, 1.0, 0.0, 1.0]),
            jnp.array([1, 2, 4, 4]), jnp.asarray(idx))


def _local_normal_matches(model, data, param, u, active, slots, idx, n_host, chunks):
    """`capacity._local_normal` against one blockwise Jacobian of every slot with the mask,
    every column pushed through the model and with the per-band linear ones (fluxes,
    background) made by groups (`kinds`)."""
    from clumpylen_jax.inference import capacity
    from clumpylen_jax.inference.lm import blockwise, held_residuals
    from clumpylen_jax.inference.params import entry_kinds, part_blocks
    r0, J0 = (np.asarray(a) for a in jax.jit(blockwise(
        held_residuals(model, data, param, active=active), part_blocks(param)))(u))
    real = np.asarray(idx[idx < param.size])
    J = J0[:, real]
    held = capacity.held_light(model, param.state(u), slots, active)
    v = u.at[idx].get(mode="fill", fill_value=0.0)
    per_row = (idx.size - n_host) // slots.size
    kinds = (entry_kinds(param, np.asarray(idx[:n_host])),
             entry_kinds(param, np.asarray(idx[n_host:n_host + per_row])))
    assert any(k[0] is not None for k in kinds[1])
    for chunk, kind in [(c, k) for c in chunks for k in (None, kinds)]:
        normal, residual = capacity._local_normal(model, data, param, u, idx, slots, active,
                                                  held, n_host, chunk, kind)
        r, H, g = (np.asarray(a) for a in jax.jit(normal)(v))
        assert np.abs(np.asarray(jax.jit(residual)(v)) - r).max() <= 1e-12 * np.abs(r).max()
        n = real.size
        assert np.abs(r - r0).max() <= 1e-12 * np.abs(r0).max()
        assert np.abs(H[:n, :n] - J.T @ J).max() <= 1e-12 * np.abs(J.T @ J).max()
        assert np.abs(g[:n] - J.T @ r0).max() <= 1e-12 * np.abs(J.T @ r0).max()
        assert not np.any(H[n:]) and not np.any(H[:, n:]) and not np.any(g[n:])


def test_local_normal_equations_are_the_full_models():
    """capacity: a local solve draws only the clump rows it moves, a chunk of rows at a
    time, plus the held light of the other active clumps (`held_light`), and forms JᵀJ and
    Jᵀr by blocks; for a model whose clumps add linearly (round Gaussians) its residuals
    and normal equations are those of every slot rendered with the active mask, with one
    or two rows per chunk, and the padding columns are zero."""
    model, data, param, u, active, slots, idx = _rows_case()
    assert model.clumps.any_count
    _local_normal_matches(model, data, param, u, active, slots, idx, 1, (1, 2))


@pytest.mark.slow
def test_local_normal_equations_with_a_host():
    """The same (test above) with a bulge and a disk: the host drawn alone, its columns
    with every clump's light held."""
    model, data, param = _host_disk_case()
    host, per_slot, _ = auto._index_tables(param, 3)
    slots = np.array([2, 0, 3, 3])          # slot 1 held (active), one padding row
    idx = np.r_[host, per_slot[2], per_slot[0], np.full(2 * per_slot.shape[1], param.size)]
    _local_normal_matches(model, data, param, param.initial() + 0.01, jnp.ones(3),
                          jnp.asarray(slots), jnp.asarray(idx), host.size, (1,))


def test_final_refit_errors_are_the_full_models_fisher():
    """`auto._uncertainty` from a local solve's JᵀJ at its optimum (the final refit's: no
    program of its own) is the inverse of the kept block of the Fisher matrix of every slot
    with the active mask, in physical parameters; entries outside the solve are NaN. The
    data are the noiseless image of u and the solve starts 0.05 off it in every entry: the
    point is the errors at the optimum, not reaching it."""
    import types

    from clumpylen_jax.inference import capacity
    from clumpylen_jax.inference.likelihood import make_data, predicted_images
    from clumpylen_jax.inference.uncertainty import fisher_matrix, safe_inverse
    model, _, param, u, active, _, _ = _rows_case()
    truth = np.asarray(predicted_images(model, param.state(u))[0])
    data = make_data(model, [truth], [np.full(truth.shape, 0.01)], kind="gaussian")
    kept = np.array([0, 1, 3])
    idx = np.r_[param.size - 1, np.ravel([[i, 4 + 2 * i, 5 + 2 * i, 12 + i] for i in kept])]
    out, _, ok, n, jtj = capacity.solve_local_batch(
        model, data, param, (u + 0.05)[None], jnp.asarray(idx[None]), jnp.asarray(kept[None]),
        active[None], 1e-10, jnp.asarray([50]), 1, 3)
    assert bool(ok[0]) and int(n[0]) > 1
    u_opt = jnp.asarray(out[0])
    unc = auto._uncertainty(types.SimpleNamespace(param=param), u_opt, jtj[0], idx)
    f_all = np.asarray(fisher_matrix(model, param, param.physical_vector(u_opt), data,
                                     active=active))
    ref = np.asarray(safe_inverse(jnp.asarray(f_all[np.ix_(idx, idx)])))
    cov = np.asarray(unc.cov)
    d = np.sqrt(np.diag(ref))
    assert np.all(d > 0)
    # in units of each pair's σ_i σ_j: the same to 1e-8 (JᵀJ is made at the last accepted
    # trial, the optimum returned; the transforms' slopes divide out)
    assert np.allclose(cov[np.ix_(idx, idx)] / np.outer(d, d), ref / np.outer(d, d),
                       rtol=0, atol=1e-8)
    others = np.setdiff1d(np.arange(param.size), idx)
    assert np.all(np.isnan(cov[others])) and np.all(np.isnan(cov[:, others]))
    assert np.allclose(np.asarray(unc.x), np.asarray(param.physical_vector(u_opt)), rtol=1e-14)


def test_source_shape_undoes_the_lens_stretch():
    """seeding.source_shape: an image stretched 10× along θ2 by A = diag(1, 0.1) comes from
    a round clump; the identity keeps the shape; a rotation by φ turns the PA by −φ."""
    from clumpylen_jax.inference.seeding import source_shape
    q, _ = source_shape(0.1, np.pi / 2, np.diag([1.0, 0.1]))
    assert q == pytest.approx(1.0, abs=1e-9)
    q, pa = source_shape(0.5, 0.3, np.eye(2))
    assert q == pytest.approx(0.5) and np.cos(2 * (pa - 0.3)) == pytest.approx(1.0)
    phi = 0.4
    rot = np.array([[np.cos(phi), np.sin(phi)], [-np.sin(phi), np.cos(phi)]])
    q, pa = source_shape(0.5, 0.3, rot)
    assert q == pytest.approx(0.5) and np.cos(2 * (pa - (0.3 - phi))) == pytest.approx(1.0)


def test_merged_clump_is_the_pair_second_moment():
    """Two equal round clumps on the β1 axis: one clump at their midpoint, flux summed, major
    axis along β1 (PA 0) with σ² = c²R_e² + d², minor σ = cR_e (c: `profiles.sersic_axis_rms_per_re_np`)."""
    c = profiles.sersic_axis_rms_per_re_np(0.5)
    assert c == pytest.approx(np.sqrt(1 / (2 * np.log(2))), rel=1e-6)  # Gaussian: R_e = σ√(2 ln 2)
    beta, flux, re, q, pa = auto.merged_clump([[-0.02, 0.1], [0.02, 0.1]], [[1.0], [1.0]],
                                              [0.01, 0.01], 0.5, q_range=(0.0, 1.0))
    assert np.allclose(beta, [0.0, 0.1]) and np.allclose(flux, [2.0])
    assert re * c == pytest.approx(np.hypot(c * 0.01, 0.02))
    assert q == pytest.approx(c * 0.01 / np.hypot(c * 0.01, 0.02))
    assert np.sin(pa) == pytest.approx(0.0, abs=1e-9)


def _pair_fit(truth, seed, centers, re):
    """Context and state of a fit with two round clumps at `centers` solved locally (what the
    counting leaves when it splits one clump or finds two)."""
    data, var = _observe(truth, seed)
    opts = AutoOptions(max_clumps=3, n_starts=2, re_max_arcsec=4 * PIX).validate()
    ctx, u = auto._setup(make_model, data, var, None, None, None, opts)
    for slot, c in enumerate(centers):
        u = auto._set_clump(ctx, u, slot, c, [10.0], re)
    active = np.array([1.0, 1.0, 0.0])
    # host and the round pair solved with the moves' own program (its one elliptical slot is
    # the empty slot 2: zero columns), so that the test compiles one solve only
    shaped = np.array([False, False, True])
    us, lnl, _, _ = auto._fit_local(ctx, u[None], [[2, 0, 1]], active[None], [shaped])
    return ctx, us[0], float(lnl[0]), active


def test_merge_and_shape_moves_are_judged_by_the_counting_criterion():
    """BIC, n = 10⁴ pixels, one band (k = 4 per round clump): two round clumps against one
    elliptical (2 parameters fewer) are kept when ln L drops by more than ln n ≈ 9.2 on
    merging; against one round clump (no shape moves: 4 fewer), by more than 2 ln n."""
    import types
    ctx = types.SimpleNamespace(opts=AutoOptions().validate(), k_clump=4, n_pix=10_000,
                                shaped=np.zeros(3, bool), shape_index=np.zeros((3, 2), int))
    lnn = np.log(10_000)
    assert auto._judge(ctx, ("merge", 0, 1), 0.0, -0.9 * lnn)[1]          # merged
    assert not auto._judge(ctx, ("merge", 0, 1), 0.0, -1.1 * lnn)[1]      # pair kept
    assert auto._judge(ctx, ("shape", 0, -1), 0.0, 1.1 * lnn)[1]          # q, PA justified
    assert not auto._judge(ctx, ("shape", 0, -1), 0.0, 0.9 * lnn)[1]
    ctx.shape_index = None
    assert auto._judge(ctx, ("merge", 0, 1), 0.0, -1.9 * lnn)[1]
    assert not auto._judge(ctx, ("merge", 0, 1), 0.0, -2.1 * lnn)[1]


@pytest.mark.slow
def test_merge_move_joins_a_split_elongated_clump_not_two_clumps():
    """One elongated clump (q 0.35) fitted as two round ones: the merge move makes it one
    elliptical clump with the flux and R_e near the truth. Two round clumps 4 PSF σ apart are
    kept apart (their merge rejected by the criterion). Slow: one compiled LM solve, 160 s
    at load 8 on 2 cores on a first run (its compilation 56 s of it), 39 s on a later one."""
    elong = Clumps(jnp.array([[0.0, 0.05]]), jnp.array([[20.0]]), jnp.array([0.09]),
                   jnp.full(1, 0.5), jnp.array([0.35]), jnp.array([0.0]))
    ctx, u, lnl, active = _pair_fit(Source(bulge=HOST, clumps=elong), 3,
                                    [[-0.05, 0.05], [0.05, 0.05]], 0.04)
    steps = []
    u, _, active, _, _ = auto._refine(ctx, u, lnl, active, np.ones(3, int), steps)
    assert "merge" in [s["action"] for s in steps], steps
    assert active.sum() == 1
    cl = ctx.param.state(jnp.asarray(u)).source.clumps
    i = int(np.argmax(active))
    assert abs(float(cl.flux[i, 0]) / 20.0 - 1) < 0.1
    assert abs(float(cl.re_arcsec[i]) / 0.09 - 1) < 0.15 and float(cl.q[i]) < 0.5

    two = Clumps(jnp.array([[-0.06, 0.05], [0.06, 0.05]]), jnp.array([[10.0], [10.0]]),
                 jnp.array([0.03, 0.03]), jnp.full(2, 0.5), jnp.ones(2), jnp.zeros(2))
    # started off the truth (centres ~0.01" away, R_e 0.02 against 0.03), as the first case
    ctx, u, lnl, active = _pair_fit(Source(bulge=HOST, clumps=two), 4,
                                    [[-0.07, 0.055], [0.05, 0.045]], 0.02)
    steps = []
    _, _, active, _, _ = auto._refine(ctx, u, lnl, active, np.ones(3, int), steps)
    assert active.sum() == 2
    assert "reject_merge" in [s["action"] for s in steps], steps


def test_final_shape_starts_round_clumps_from_their_shape_trials():
    """AutoOptions.final_shape: before the final refit every kept round clump takes the R_e,
    q and PA of its best shape trial (q kept inside its bounds, so that it can move), one
    with no trial keeps its values, an inactive slot is untouched, and every kept clump's q
    and PA become entries of the final solve. No fit: any image sets the context up."""
    img = _blobs(np.array([[10, 12], [25, 30]]), [5.0, 3.0]) + 0.5
    data, var = [img], [np.full(img.shape, 0.01)]
    opts = AutoOptions(max_clumps=4, n_starts=2, re_max_arcsec=4 * PIX).validate()
    ctx, u = auto._setup(make_model, data, var, None, None, None, opts)
    assert ctx.shape_index is not None          # the Sérsic renderer draws q and PA
    for slot, c in enumerate(CENTERS):
        u = auto._set_clump(ctx, u, slot, c, [3.0], 0.03)
    active = np.array([1.0, 1.0, 1.0, 0.0])
    ctx.shaped = np.array([False, False, True, False])
    before = ctx.param.state(jnp.asarray(u)).source.clumps
    u2 = auto._shaped_start(ctx, u, active, {0: (12.0, 0.05, 0.55, 1.2), 3: (5.0, 0.02, 0.5, 0.1),
                                             2: (1.0, 0.02, 1.0, 0.0)})
    cl = ctx.param.state(jnp.asarray(u2)).source.clumps
    assert float(cl.re_arcsec[0]) == pytest.approx(0.05) and float(cl.q[0]) == pytest.approx(0.55)
    assert float(cl.pa_rad[0]) == pytest.approx(1.2)
    assert np.allclose(cl.center_arcsec[0], before.center_arcsec[0])
    assert np.allclose(cl.flux[0], before.flux[0])
    for i in (1, 2, 3):     # no trial; already shaped (its trial ignored); inactive
        for f in ("re_arcsec", "q", "pa_rad", "center_arcsec", "flux"):
            assert np.allclose(getattr(cl, f)[i], getattr(before, f)[i]), (i, f)
    assert ctx.shaped.tolist() == [True, True, True, False]
    idx, _ = auto._solve_layout(ctx, [0, 1, 2])
    kept = idx[idx < ctx.param.size]
    assert set(ctx.shape_index[:3].ravel()) <= set(kept.tolist())
    # a trial that went back to round starts inside the bound
    ctx.shaped[:] = False
    u3 = auto._shaped_start(ctx, u, active, {1: (0.5, 0.03, 0.9999999, 0.7)})
    q1 = float(ctx.param.state(jnp.asarray(u3)).source.clumps.q[1])
    assert q1 == pytest.approx(auto.CLUMP_Q_RANGE[1] - 0.01)
    assert np.all(np.isfinite(u3))


def test_host_moves_swap_roles_with_a_broader_clump_or_reseed_the_host():
    """`auto._host_moves`: a host that sits compact on a clump-like knot (R_e 0.03") beside a
    broader clump (0.1") holding the diffuse light: the swap gives the host that clump's
    centre and flux with R_e max(0.1", the moments' R_e), and the clump the host's centre,
    flux and R_e; a clump smaller than the host gets no swap; the reseed puts the host back
    on the data's moments and the old host into the first free slot. No fit."""
    img = _blobs(np.array([[10, 12], [25, 30]]), [5.0, 3.0]) + 0.5
    opts = AutoOptions(max_clumps=4, n_starts=4, re_max_arcsec=4 * PIX).validate()
    ctx, u0 = auto._setup(make_model, [img], [np.full(img.shape, 0.01)], None, None, None, opts)
    st = ctx.param.state(jnp.asarray(u0))
    knot = Sersic(jnp.array([7.0]), jnp.asarray(0.03), st.source.bulge.n, st.source.bulge.q,
                  st.source.bulge.pa_rad, jnp.array([0.2, -0.15]))
    u = np.asarray(ctx.param.initial(eqx.tree_at(lambda s: s.source.bulge, st, knot)))
    u = auto._set_clump(ctx, u, 0, [0.0, 0.0], [9.0], 0.1)
    u = auto._set_clump(ctx, u, 1, [-0.2, 0.1], [2.0], 0.02)
    active = np.array([1.0, 1.0, 0.0, 0.0])
    moves = auto._host_moves(ctx, u, u0, active)
    assert [(m[0], m[1]) for m in moves] == [("swap", 0), ("reseed", 2)]
    re0 = float(st.source.bulge.re_arcsec)
    swap = ctx.param.state(jnp.asarray(moves[0][2])).source
    assert np.allclose(swap.bulge.center_arcsec, [0.0, 0.0])
    assert float(swap.bulge.flux[0]) == pytest.approx(9.0)
    assert float(swap.bulge.re_arcsec) == pytest.approx(max(0.1, re0))
    assert np.allclose(swap.clumps.center_arcsec[0], [0.2, -0.15])
    assert float(swap.clumps.flux[0, 0]) == pytest.approx(7.0)
    assert float(swap.clumps.re_arcsec[0]) == pytest.approx(0.03)
    assert moves[0][3].tolist() == active.tolist() and moves[0][4][0] == 0
    reseed = ctx.param.state(jnp.asarray(moves[1][2])).source
    assert np.allclose(reseed.bulge.center_arcsec, st.source.bulge.center_arcsec)
    assert float(reseed.bulge.re_arcsec) == pytest.approx(re0)
    assert np.allclose(reseed.clumps.center_arcsec[2], [0.2, -0.15])
    assert moves[1][3].tolist() == [1.0, 1.0, 1.0, 0.0] and moves[1][4][0] == 2
    assert all(np.all(np.isfinite(m[2])) for m in moves)
    # no host fitted (host = false): nothing to swap
    ctx.opts = dataclasses.replace(ctx.opts, host=False)
    assert auto._host_moves(ctx, u, u0, active) == []


def test_a_host_with_a_cusp_gives_its_centre_to_a_clump():
    """`auto._host_moves`: a host whose Sérsic n (4) is above the moments' holds a compact
    clump's light in its cusp (the cluster arc's seed 0: n 5.0, R_e 0.025" on an S/N 30
    clump, truth n 1, 0.08"). The cusp move keeps the host's centre, R_e, q and PA, takes its
    n back to the moments' and CUSP_FLUX_FRACTION of its flux into a new clump at its
    centre with CUSP_RE_FRACTION of its R_e, in the first free slot. A host at the
    moments' n gets none (the test above). No fit."""
    img = _blobs(np.array([[10, 12], [25, 30]]), [5.0, 3.0]) + 0.5
    opts = AutoOptions(max_clumps=4, n_starts=4, re_max_arcsec=4 * PIX).validate()
    ctx, u0 = auto._setup(make_model, [img], [np.full(img.shape, 0.01)], None, None, None, opts)
    st = ctx.param.state(jnp.asarray(u0))
    n0 = float(st.source.bulge.n)
    cusp = eqx.tree_at(lambda h: (h.n, h.flux, h.re_arcsec, h.center_arcsec), st.source.bulge,
                       (jnp.asarray(4.0), jnp.array([10.0]), jnp.asarray(0.2),
                        jnp.array([0.05, -0.02])))
    u = np.asarray(ctx.param.initial(eqx.tree_at(lambda s: s.source.bulge, st, cusp)))
    u = auto._set_clump(ctx, u, 0, [-0.2, 0.1], [2.0], 0.02)
    active = np.array([1.0, 0.0, 0.0, 0.0])
    moves = auto._host_moves(ctx, u, u0, active)
    assert [(m[0], m[1]) for m in moves] == [("reseed", 1), ("cusp", 1)]
    got = ctx.param.state(jnp.asarray(moves[1][2])).source
    assert float(got.bulge.n) == pytest.approx(n0) and n0 < 4.0
    assert float(got.bulge.flux[0]) == pytest.approx((1 - auto.CUSP_FLUX_FRACTION) * 10.0)
    assert float(got.bulge.re_arcsec) == pytest.approx(0.2)
    assert np.allclose(got.bulge.center_arcsec, [0.05, -0.02])
    assert float(got.bulge.q) == pytest.approx(float(cusp.q))
    assert float(got.bulge.pa_rad) == pytest.approx(float(cusp.pa_rad))
    assert np.allclose(got.clumps.center_arcsec[1], [0.05, -0.02])
    assert float(got.clumps.flux[1, 0]) == pytest.approx(auto.CUSP_FLUX_FRACTION * 10.0)
    assert float(got.clumps.re_arcsec[1]) == pytest.approx(auto.CUSP_RE_FRACTION * 0.2)
    assert moves[1][3].tolist() == [1.0, 1.0, 0.0, 0.0] and moves[1][4][0] == 1
    assert np.all(np.isfinite(moves[1][2]))


def test_a_cusp_move_is_made_only_where_no_swap_or_reseed_is(monkeypatch):
    """`auto._rehost`: a reseed and a cusp move both accepted (ln L +41.5 and +41.8, as in a
    JWST pulls mock): the reseed is made (it puts the host back on the diffuse light). With
    the reseed short of the criterion (+10), the cusp is made. The local fits are stood in
    for (no fit)."""
    img = _blobs(np.array([[10, 12], [25, 30]]), [5.0, 3.0]) + 0.5
    opts = AutoOptions(max_clumps=4, n_starts=4, re_max_arcsec=4 * PIX).validate()
    ctx, u0 = auto._setup(make_model, [img], [np.full(img.shape, 0.01)], None, None, None, opts)
    u = auto._set_clump(ctx, np.asarray(u0), 0, [0.1, 0.0], [4.0], 0.05)
    active = np.array([1.0, 0.0, 0.0, 0.0])
    act = np.array([1.0, 1.0, 0.0, 0.0])
    trial = [auto._set_clump(ctx, u, 1, c, [2.5], 0.03) for c in ([-0.2, 0.1], [0.0, 0.0])]
    monkeypatch.setattr(auto, "_host_moves", lambda *a: [("reseed", 1, trial[0], act, [1, 0]),
                                                         ("cusp", 1, trial[1], act, [1, 0])])
    monkeypatch.setattr(auto, "_prune", lambda ctx, u, lnl, active, steps: (lnl, active))
    for gains, made in (((41.5, 41.8), "reseed"), ((10.0, 41.8), "cusp")):
        monkeypatch.setattr(auto, "_fit_local", lambda ctx, us, *a, g=gains: (
            np.asarray(us), -100.0 + np.array(g), np.array([True, True]), np.array([4, 4])))
        steps = []
        u_out, lnl, _, _ = auto._rehost(ctx, u, u0, -100.0, active, np.ones(4, int), steps)
        assert [s["action"] for s in steps if s["made"]] == [made]
        assert np.array_equal(u_out, trial[0 if made == "reseed" else 1])


def test_a_rejected_host_move_that_fits_as_well_is_kept_as_an_alternative(monkeypatch):
    """`auto._rehost`: a reseed that raises ln L by 5 (less than the criterion asks for its
    extra clump) is rejected and its clumps are recorded in its step ("alternative"), which
    `host_alternatives` reads back; one 3 below the kept fit's (beyond ALTERNATIVE_DLNL) is
    not recorded. The local fits are stood in for (no fit)."""
    img = _blobs(np.array([[10, 12], [25, 30]]), [5.0, 3.0]) + 0.5
    opts = AutoOptions(max_clumps=4, n_starts=4, re_max_arcsec=4 * PIX).validate()
    ctx, u0 = auto._setup(make_model, [img], [np.full(img.shape, 0.01)], None, None, None, opts)
    u = auto._set_clump(ctx, np.asarray(u0), 0, [0.1, 0.0], [4.0], 0.05)
    active = np.array([1.0, 0.0, 0.0, 0.0])
    alt = auto._set_clump(ctx, u, 1, [-0.2, 0.1], [2.5], 0.03)
    act = np.array([1.0, 1.0, 0.0, 0.0])
    monkeypatch.setattr(auto, "_host_moves", lambda *a: [("reseed", 1, alt, act, [1, 0])])
    for gain, recorded in ((5.0, True), (-3.0, False)):
        monkeypatch.setattr(auto, "_fit_local", lambda ctx, us, *a, g=gain: (
            np.asarray(us), np.array([-100.0 + g]), np.array([True]), np.array([4])))
        steps = []
        u_out, lnl, active_out, _ = auto._rehost(ctx, u, u0, -100.0, active, np.ones(4, int),
                                                  steps)
        assert steps[0]["action"] == "reject_reseed" and not steps[0]["accepted"]
        assert lnl == -100.0 and active_out.tolist() == active.tolist()
        assert ("alternative" in steps[0]) == recorded
        alts = auto.host_alternatives(steps)
        assert len(alts) == int(recorded)
    centres, fluxes = auto.host_alternatives([dict(alternative=dict(
        center_arcsec=[[0.1, 0.0], [-0.2, 0.1]], flux=[[4.0], [2.5]]))])[0]
    assert np.allclose(centres, [[0.1, 0.0], [-0.2, 0.1]]) and np.allclose(fluxes, [[4.0], [2.5]])


def test_host_alternative_flag_marks_clumps_whose_flux_the_alternative_moves():
    """`host_alternative_fluxes`' flags: flagged where the nearest alternative clump (within
    max(match, R_e)) has a flux more than ALTERNATIVE_SIGMA σ away in a band, or where the
    alternative has no clump there (its light went to the host); a band with NaN σ counts
    not; no alternatives flags nothing."""
    centre = np.array([[0.0, 0.0], [0.3, 0.0], [0.0, 0.3], [-0.3, 0.0]])
    flux = np.array([[10.0, 5.0], [10.0, 5.0], [10.0, 5.0], [10.0, 5.0]])
    err = np.array([[1.0, 1.0], [1.0, 1.0], [1.0, 1.0], [1.0, np.nan]])
    re = np.array([0.02, 0.02, 0.02, 0.02])
    alt = (np.array([[0.01, 0.0], [0.3, 0.005], [-0.3, 0.0]]),
           np.array([[10.5, 4.0], [6.0, 5.0], [10.0, 20.0]]))
    flag = auto.host_alternative_fluxes(centre, flux, err, re, [alt], 0.06)[0]
    # within 1σ; 4σ in the first band; no clump near (0, 0.3); 15σ only where σ is NaN
    assert flag.tolist() == [False, True, True, False]
    # the alternative's flux of each flagged clump (0: none there); of another, NaN; of two
    # alternatives, the one that moves the clump most (here a second one moving clump 1 by
    # 2.5σ, less than the first's 4σ, and clump 0 by 3σ)
    second = (np.array([[0.0, 0.0], [0.3, 0.0], [0.0, 0.3], [-0.3, 0.0]]),
              np.array([[13.0, 5.0], [7.5, 5.0], [10.0, 5.0], [10.0, 5.0]]))
    for alts in ([alt], [alt, second], [second, alt]):
        got, fl = auto.host_alternative_fluxes(centre, flux, err, re, alts, 0.06)
        assert got.tolist() == ([False, True, True, False] if len(alts) == 1 else
                                [True, True, True, False])
        assert np.allclose(fl[1], [6.0, 5.0]) and np.allclose(fl[2], 0.0)
        assert np.isnan(fl[3]).all()
        assert np.isnan(fl[0]).all() if len(alts) == 1 else np.allclose(fl[0], [13.0, 5.0])
    assert not auto.host_alternative_fluxes(centre, flux, err, re, [], 0.06)[0].any()
    # a broad clump matches farther than `match_arcsec`: R_e 0.1" reaches (0.08, 0)
    far = (np.array([[0.08, 0.0]]), np.array([[10.2, 5.1]]))
    for re_far, want in ((0.1, False), (0.02, True)):
        got = auto.host_alternative_fluxes(centre[:1], flux[:1], err[:1], [re_far], [far], 0.06)
        assert got[0].tolist() == [want]


@pytest.mark.slow
def test_without_errors_the_same_clumps_and_no_table():
    """AutoOptions(errors=False) (what `clumpylen fit` asks for): the same optimum, bit for
    bit, as errors=True, with no Fisher matrix and no table. A tiny scene drawn in numpy (an
    exponential host and a Gaussian knot, 21², no PSF, no exact pixels) so that little is
    compiled besides the fits' programs. Slow: two whole auto fits, 24–28 s on 2 cores
    (`make test` took 10 min 18 s with it); the observation fits' errors=False path
    still runs in test_observations."""
    n, pix = 21, 0.03
    field = ((-0.5 * n * pix, 0.5 * n * pix),) * 2
    acc = dataclasses.replace(TOY_ACCURACY, clump_pixels="round_gaussian", psf_oversampling=1)

    def mk(src):
        return build_model(src, toy_bands(1), field_arcsec=field, accuracy=acc)

    yy, xx = np.mgrid[:n, :n] - (n - 1) / 2
    host = 2.0 * np.exp(-np.hypot(xx / 4.0, yy / 3.0))
    knot = 1.5 * np.exp(-0.5 * ((xx - 3) ** 2 + (yy + 2) ** 2))
    sigma = 0.05
    data = [host + knot + np.random.default_rng(3).normal(0.0, sigma, (n, n))]
    var = [np.full((n, n), sigma**2)]
    opts = AutoOptions(max_clumps=1, n_starts=1)
    full = fit_without_truth(mk, data, var, options=opts)
    bare = fit_without_truth(mk, data, var, options=dataclasses.replace(opts, errors=False))
    assert len(full.table) == 1 and full.uncertainty is not None
    assert bare.table is None and bare.uncertainty is None
    assert np.array_equal(bare.u, full.u) and np.array_equal(bare.active, full.active)
    assert bare.log_likelihood == full.log_likelihood
    same = jax.tree_util.tree_map(lambda a, b: bool(np.array_equal(a, b)), bare.state, full.state)
    assert all(jax.tree_util.tree_leaves(same))


def test_profile_sigma_is_a_lower_bound_of_a_quadratic_profile():
    """profile_sigma: for refits on a quadratic ln L of width σ_p (Δln L = Δx²/2σ_p²) it
    returns σ_p whatever Δx, never less than the Fisher σ given, |Δx| for a refit within
    2Δln L < 1 (or better than the optimum), and ignores NaN refits."""
    sp = 0.3
    dx = np.array([0.1, 0.6, -1.5])
    assert auto.profile_sigma(0.01, dx, dx**2 / (2 * sp**2)) == pytest.approx(sp)
    assert auto.profile_sigma(0.5, dx, dx**2 / (2 * sp**2)) == pytest.approx(0.5)
    assert auto.profile_sigma(0.01, [0.2, np.nan], [0.1, np.nan]) == pytest.approx(0.2)
    assert auto.profile_sigma(0.01, [0.2], [-3.0]) == pytest.approx(0.2)
    assert auto.profile_sigma(0.01, [], []) == 0.01


def test_re_profile_trials_keep_the_measured_axis():
    """Same orientation: R_e·f with the minor axis q·R_e kept ("minor") or from
    SHAPE_START_Q ("open"); turned by 90°: the old major axis is the new minor one (q = 1/f).
    q stays inside the clump q range."""
    tr = auto.re_profile_trials(0.006, 0.3, 0.8, trials=((1.2, "minor"), (1.2, "open"),
                                                         (1.25, "turned"), (5.0, "minor")))
    (r0, q0, p0), (r1, q1, p1), (r2, q2, p2), (r3, q3, _) = tr
    assert r0 == pytest.approx(0.0072) and r0 * q0 == pytest.approx(0.006 * 0.3) and p0 == 0.8
    assert q1 == pytest.approx(auto.SHAPE_START_Q) and p1 == 0.8
    assert r2 == pytest.approx(0.0075) and r2 * q2 == pytest.approx(0.006)
    assert p2 == pytest.approx(0.8 + np.pi / 2)
    assert q3 == pytest.approx(auto.CLUMP_Q_RANGE[0] + 0.01)


def test_profile_raises_errors_keeps_fisher_ones_and_flags_a_degenerate_shape():
    """_apply_profile: the R_e and flux errors become the profile bound where it is larger
    (mag error with them), the Fisher ones stay in *_err_fisher, and "shape_degenerate" is
    set where the R_e error grew more than PROFILE_FLAG_RATIO times; a clump not profiled
    keeps its errors."""
    from astropy.table import Table
    t = Table({"re_arcsec": [0.005, 0.02, 0.01], "re_arcsec_err": [1e-4, 1e-3, 1e-3],
               "flux_X": [2.0, 1.0, 1.0], "flux_X_err": [0.03, 0.05, 0.05],
               "mag_X": [24.0, 25.0, 25.0], "mag_X_err": [0.016, 0.054, 0.054]})
    prof = {4: (np.array([0.8e-3, 2e-3]), np.array([[0.2], [0.02]]), np.array([2.0, 8.0])),
            7: (np.array([1e-3]), np.array([[0.01]]), np.array([50.0]))}
    flag = auto._apply_profile(t, prof, [4, 7, 9], ["X"])
    assert t["re_arcsec_err"][0] == pytest.approx(max(0.8e-3 / 2, 2e-3 / 4))
    assert t["flux_X_err"][0] == pytest.approx(0.2 / 2)
    assert t["mag_X_err"][0] == pytest.approx(2.5 / np.log(10) * 0.1 / 2.0)
    assert t["re_arcsec_err_fisher"][0] == 1e-4 and t["flux_X_err_fisher"][0] == 0.03
    assert t["re_arcsec_err"][1] == pytest.approx(1e-3) and t["flux_X_err"][1] == 0.05
    assert t["re_arcsec_err"][2] == 1e-3
    assert flag.tolist() == [auto.FLAGS["shape_degenerate"], 0, 0]


@pytest.mark.slow
def test_profile_refits_hold_r_e_and_do_not_beat_the_optimum():
    """_profile on a fitted elliptical clump: each refit keeps R_e exactly at its trial value
    (the held entry is not solved), none beats the optimum beyond the LM tolerance, and the
    flux changes are finite. Slow: the moves' compiled LM solve (as `test_merge_move_joins_a_split_elongated_clump_not_two_clumps`)."""
    elong = Clumps(jnp.array([[0.0, 0.05]]), jnp.array([[20.0]]), jnp.array([0.06]),
                   jnp.full(1, 0.5), jnp.array([0.5]), jnp.array([0.3]))
    data, var = _observe(Source(bulge=HOST, clumps=elong), 5)
    opts = AutoOptions(max_clumps=3, n_starts=2, re_max_arcsec=4 * PIX).validate()
    ctx, u = auto._setup(make_model, data, var, None, None, None, opts)
    u = auto._set_clump(ctx, u, 0, [0.005, 0.045], [15.0], 0.05, 0.6, 0.2)
    active = np.array([1.0, 0.0, 0.0])
    ctx.shaped = np.array([True, False, False])
    us, lnl, _, _ = auto._fit_local(ctx, u[None], [[0, 1, 2]], active[None])
    u, lnl = us[0], float(lnl[0])
    re0 = float(ctx.param.state(jnp.asarray(u)).source.clumps.re_arcsec[0])
    prof = auto._profile(ctx, u, lnl, active)
    d_re, d_flux, d_lnl = prof[0]
    cl = ctx.param.state(jnp.asarray(u)).source.clumps
    want = [r - re0 for r, _, _ in auto.re_profile_trials(re0, float(cl.q[0]), float(cl.pa_rad[0]))]
    assert np.allclose(d_re, want, rtol=1e-6), (d_re, want)
    # a refit with one entry held can reach no higher ln L than the optimum (LM tolerance)
    assert np.all(d_lnl > -0.5), d_lnl
    assert np.max(d_lnl) > 1.0, d_lnl    # and R_e is measured here: some trial costs ln L
    assert d_flux.shape == (len(want), 1) and np.all(np.isfinite(d_flux))


def test_the_fitted_host_goes_into_the_tables_header():
    """fit.ecsv's header holds the host (`catalog.host_meta`, the layout of every fit's
    table): a host with a cusp (high n) can hold a compact clump's light, which only its
    parameters show. Errors only where a parametrization's labels and 1σ are given."""
    import json

    from clumpylen_jax.inference.catalog import host_meta
    from clumpylen_jax.inference.params import make_state

    state = make_state(Source(bulge=HOST, clumps=CLUMPS), 1)
    h = host_meta(state)["bulge"]
    assert h["flux"] == [40.0] and h["re_arcsec"] == 0.25 and h["n"] == 1.0
    assert h["q"] == pytest.approx(float(HOST.q)) and len(h["center_arcsec"]) == 2
    assert not any(k.endswith("_err") for k in h)
    with_err = host_meta(state, ("bulge.n[]", "bulge.flux[0]"), [0.3, 2.0])["bulge"]
    assert with_err["n_err"] == 0.3 and with_err["flux_err"] == [2.0]
    json.dumps(host_meta(state))          # plain numbers: the ECSV header is YAML
    assert host_meta(make_state(Source(clumps=CLUMPS), 1)) == {}