"""Tests of the clump population sampler against analytic distributions."""

import math

import numpy as np
import pytest
from astropy.table import Table
from scipy import stats

from clumpylen_jax.errors import ConfigError
from clumpylen_jax.population import (
    CATALOG_COLUMNS,
    ClumpConfig,
    clump_config_from_scene,
    read_clump_catalog,
    sample_ages_myr,
    sample_clumps,
    sample_cmf_masses,
    sample_positions,
    sample_power_law,
    sample_sizes_pc,
)

# p-values below this fail; with ~20 KS tests a false alarm is ~2e-5 per run.
P_MIN = 1e-3

_GL_X, _GL_W = np.polynomial.legendre.leggauss(200)


def cmf_cdf(m, slope, m_cut, delta, gamma, m_min, m_max):
    """CDF of dN/dM ∝ M^β exp[−δ (M/M_cut)^γ] by 200-point Gauss–Legendre in ln M.

    Independent of the sampler (which uses rejection from a power law): the
    integrand in u = ln M is smooth, so the quadrature is accurate to ~1e-14.
    """

    def integral(upper):
        a = math.log(m_min)
        b = np.log(np.atleast_1d(upper))[:, None]
        half = 0.5 * (b - a)
        uu = a + half * (_GL_X[None, :] + 1.0)
        f = np.exp((slope + 1.0) * uu - delta * np.exp(gamma * (uu - math.log(m_cut))))
        return (half[:, 0]) * (f @ _GL_W)

    m = np.clip(np.asarray(m, dtype=float), m_min, m_max)
    return integral(m) / integral(np.array([m_max]))[0]


def power_law_cdf(x, slope, x_min, x_max):
    a = slope + 1.0
    if abs(a) < 1e-12:
        return np.log(x / x_min) / math.log(x_max / x_min)
    return (x**a - x_min**a) / (x_max**a - x_min**a)


# ----------------------------------------------------------------------------- masses


@pytest.mark.parametrize(
    "cmf",
    [
        dict(slope=-2.0, m_cut_msun=5e6, delta=1.0, gamma=1.0, m_min_msun=1e4, m_max_msun=1e7),  # paper
        dict(slope=-1.0, m_cut_msun=1e5, delta=2.0, gamma=0.5, m_min_msun=1e4, m_max_msun=1e7),  # strong cut
        dict(slope=-1.5, m_cut_msun=3e5, delta=1.0, gamma=2.0, m_min_msun=1e3, m_max_msun=1e6),
        dict(slope=0.5, m_cut_msun=1e6, delta=0.0, gamma=1.0, m_min_msun=1e4, m_max_msun=1e6),  # no cut
    ],
)
def test_cmf_masses_follow_analytic_cdf(cmf):
    rng = np.random.default_rng(12345)
    # Large budget: ~10^4 clumps; the stopping rule only touches the last one.
    masses = sample_cmf_masses(rng, 1.0, **cmf)  # warm-up: a tiny budget gives one clump
    assert masses.size == 1
    mean = np.mean(sample_cmf_masses(rng, 2e3 * cmf["m_max_msun"], **cmf))
    masses = sample_cmf_masses(rng, 1.5e4 * mean, **cmf)
    assert 1.2e4 < masses.size < 1.8e4
    assert masses.min() >= cmf["m_min_msun"] and masses.max() <= cmf["m_max_msun"]
    args = (cmf["slope"], cmf["m_cut_msun"], cmf["delta"], cmf["gamma"], cmf["m_min_msun"], cmf["m_max_msun"])
    p = stats.kstest(masses, lambda m: cmf_cdf(m, *args)).pvalue
    assert p > P_MIN, p


def test_cmf_budget_rule():
    rng = np.random.default_rng(7)
    for budget in [1e4, 3.3e5, 8e7, 2.5e8]:
        m = sample_cmf_masses(rng, budget)
        excess = m.sum() - budget
        assert 0.0 <= excess < m[-1]
        # Every clump before the last one leaves the total below the budget.
        assert m[:-1].sum() < budget


def test_cmf_zero_budget_and_host_guard():
    rng = np.random.default_rng(3)
    assert sample_cmf_masses(rng, 0.0).size == 0
    # Q = 1: the completing clump would overdraw the host, so it is discarded.
    host = 3e7
    for _ in range(20):
        m = sample_cmf_masses(rng, host, host_mass_msun=host)
        assert m.sum() <= host
        assert host - m.sum() < 1e7  # short of the budget by less than M_max


def test_power_law_sampler_slope_minus_one_and_near():
    rng = np.random.default_rng(11)
    for slope in [-1.0, -1.0 + 1e-14, -0.5, -2.5]:
        x = sample_power_law(rng, slope, 1.0, 500.0, 20000)
        p = stats.kstest(x, lambda t: power_law_cdf(t, slope, 1.0, 500.0)).pvalue
        assert p > P_MIN, (slope, p)


# ----------------------------------------------------------------------------- sizes, ages


def test_sizes_relation_and_lognormal_scatter():
    rng = np.random.default_rng(5)
    mass = sample_cmf_masses(rng, 5e8)
    re = sample_sizes_pc(rng, mass, scatter_ln=0.3)
    resid = np.log(re / (2.55 * (mass / 1e4) ** 0.24))
    assert abs(np.mean(resid)) < 0.02
    assert abs(np.std(resid) - 0.3) < 0.02
    p = stats.kstest(resid / 0.3, "norm").pvalue
    assert p > P_MIN, p
    # No scatter: exactly the Brown & Gnedin (2021) relation.
    np.testing.assert_allclose(sample_sizes_pc(rng, np.array([1e4, 1e6]), scatter_ln=0.0), [2.55, 2.55 * 100**0.24])


@pytest.mark.parametrize("slope", [-0.5, -1.0, 0.3])
def test_ages_follow_power_law(slope):
    rng = np.random.default_rng(99)
    t = sample_ages_myr(rng, 20000, slope=slope, min_myr=1.0, max_myr=500.0)
    assert t.min() >= 1.0 and t.max() <= 500.0
    p = stats.kstest(t, lambda x: power_law_cdf(x, slope, 1.0, 500.0)).pvalue
    assert p > P_MIN, p


# ----------------------------------------------------------------------------- positions


def test_positions_follow_exponential_disk():
    h = 0.1  # scale length, arcsec; off-centre to exercise the bbox arithmetic
    c1, c2 = -13.7, 3.6

    def disk(b1, b2):
        return np.exp(-np.hypot(b1 - c1, b2 - c2) / h)

    rng = np.random.default_rng(2024)
    b1, b2 = sample_positions(rng, 20000, disk, ((c1 - 2.0, c1 + 2.0), (c2 - 2.0, c2 + 2.0)))
    x = np.hypot(b1 - c1, b2 - c2) / h
    # Enclosed light of an exponential disk: 1 − (1+x) e^−x (the box at 20 h
    # truncates < 1e-7 of the light).
    p = stats.kstest(x, lambda s: 1.0 - (1.0 + s) * np.exp(-s)).pvalue
    assert p > P_MIN, p
    # Isotropy.
    phi = np.arctan2(b2 - c2, b1 - c1)
    assert stats.kstest(phi, stats.uniform(-np.pi, 2 * np.pi).cdf).pvalue > P_MIN


def test_positions_follow_spiral_arms_with_zero_light():
    def arms(b1, b2):
        r = np.hypot(b1, b2)
        th = np.arctan2(b2, b1)
        return np.exp(-r / 0.15) * np.clip(np.cos(2 * th - 8 * r), 0.0, None) ** 2

    rng = np.random.default_rng(8)
    n = 30000
    b1, b2 = sample_positions(rng, n, arms, ((-1.0, 1.0), (-1.0, 1.0)))
    assert np.all(arms(b1, b2) > 0)  # nothing between the arms
    # Chi-square of counts in 8 x 8 cells against the integrated light.
    edges = np.linspace(-1, 1, 9)
    counts, _, _ = np.histogram2d(b1, b2, bins=[edges, edges])
    fine = np.linspace(-1, 1, 1601)
    mid = 0.5 * (fine[1:] + fine[:-1])
    g1, g2 = np.meshgrid(mid, mid, indexing="ij")
    light = arms(g1, g2).reshape(8, 200, 8, 200).sum(axis=(1, 3))
    expected = n * light / light.sum()
    ok = expected > 20
    chi2 = np.sum((counts[ok] - expected[ok]) ** 2 / expected[ok])
    p = stats.chi2.sf(chi2, ok.sum() - 1)
    assert p > P_MIN, (chi2, ok.sum(), p)
    assert counts[~ok].sum() < 0.01 * n


def test_positions_unresolved_peak_triggers_envelope_repair():
    # A Gaussian far narrower than the envelope's sub-grid (cell 1/64 of the
    # box, nodes every 1/4 cell): the grid underestimates the peak, candidates
    # violate the envelope, the sampler raises it and restarts.
    sigma = 0.001
    c = 0.0123  # between grid nodes

    def spike(b1, b2):
        return np.exp(-((b1 - c) ** 2 + (b2 - c) ** 2) / (2 * sigma**2))

    rng = np.random.default_rng(1)
    b1, b2 = sample_positions(rng, 5000, spike, ((-1.0, 1.0), (-1.0, 1.0)))
    s = ((b1 - c) ** 2 + (b2 - c) ** 2) / (2 * sigma**2)  # ~ Exp(1)
    p = stats.kstest(s, "expon").pvalue
    assert p > P_MIN, p


# ----------------------------------------------------------------------------- catalogue


def _disk(b1, b2):
    return np.exp(-np.hypot(b1, b2) / 0.1)


def _sample(seed, **kw):
    args = dict(
        host_mass_msun=1e8,
        mass_fraction=0.8,
        host_brightness=_disk,
        bbox_arcsec=((-1.0, 1.0), (-1.0, 1.0)),
        arcsec_per_pc=1.0 / 5600.0,
    )
    args.update(kw)
    return sample_clumps(np.random.default_rng(seed), **args)


def test_sample_clumps_table_contract_and_mass_bookkeeping():
    t = _sample(42)
    assert tuple(t.colnames) == CATALOG_COLUMNS
    assert str(t["re_arcsec"].unit) == "arcsec" and str(t["mass_msun"].unit) == "solMass"
    np.testing.assert_allclose(t["re_arcsec"], t["re_pc"] / 5600.0)
    total = float(np.sum(t["mass_msun"]))
    assert 0 <= total - 8e7 < t["mass_msun"][-1]
    assert math.isclose(t.meta["host_mass_remaining_msun"], 1e8 - total)
    assert np.all((t["q"] >= 0.3) & (t["q"] < 1.0))
    assert np.all((t["pa_rad"] >= 0) & (t["pa_rad"] < np.pi))
    assert np.all(t["sersic_n"] == 0.5)
    assert np.all((t["age_myr"] >= 1) & (t["age_myr"] <= 500))
    assert list(t["id"]) == list(range(len(t)))


def test_sample_clumps_deterministic():
    a, b, c = _sample(7), _sample(7), _sample(8)
    for name in CATALOG_COLUMNS:
        np.testing.assert_array_equal(a[name], b[name])
    assert len(a) != len(c) or not np.array_equal(a["mass_msun"], c["mass_msun"])


def test_sample_clumps_zero_fraction():
    t = _sample(1, mass_fraction=0.0)
    assert len(t) == 0 and tuple(t.colnames) == CATALOG_COLUMNS
    assert t.meta["host_mass_remaining_msun"] == 1e8


@pytest.mark.parametrize(
    "kw, setting",
    [
        (dict(mass_fraction=1.2), "source.clumps.mass_fraction"),
        (dict(mass_fraction=-0.1), "source.clumps.mass_fraction"),
        (dict(host_mass_msun=-1.0), "host_mass_msun"),
        (dict(arcsec_per_pc=0.0), "arcsec_per_pc"),
        (dict(bbox_arcsec=((1.0, -1.0), (-1.0, 1.0))), "bbox_arcsec"),
        (dict(config=ClumpConfig(cmf_m_min_msun=1e7, cmf_m_max_msun=1e4)), "source.clumps.cmf.m_min_msun"),
        (dict(config=ClumpConfig(cmf_m_min_msun=-5.0)), "source.clumps.cmf.m_min_msun"),
        (dict(config=ClumpConfig(cmf_delta=-1.0)), "source.clumps.cmf.delta"),
        (dict(config=ClumpConfig(q_range=(0.0, 1.0))), "source.clumps.q_range"),
        (dict(config=ClumpConfig(age_min_myr=600.0)), "source.clumps.ages.min_myr"),
        (dict(config=ClumpConfig(size_scatter_ln=-0.3)), "source.clumps.size.scatter_ln"),
        (dict(host_brightness=lambda b1, b2: 0.0 * b1), "host_brightness"),
    ],
)
def test_sample_clumps_validation(kw, setting):
    with pytest.raises(ConfigError) as err:
        _sample(0, **kw)
    assert err.value.setting == setting


def test_clump_config_from_scene():
    cfg = clump_config_from_scene(
        {
            "mass_fraction": 0.8,
            "host": "disk",
            "cmf": {"slope": -1.8, "m_cut_msun": 1e6},
            "size": {"relation": "brown-gnedin-2021", "scatter_ln": 0.2},
            "ages": {"slope": -1.0, "min_myr": 2.0, "max_myr": 300.0},
            "sersic_n": 1.0,
            "q_range": [0.5, 1.0],
        }
    )
    assert cfg.cmf_slope == -1.8 and cfg.size_scatter_ln == 0.2 and cfg.age_min_myr == 2.0
    assert cfg.q_range == (0.5, 1.0) and cfg.sersic_n == 1.0
    with pytest.raises(ConfigError) as err:
        clump_config_from_scene({"cmf": {"slop": -2.0}})
    assert err.value.setting == "source.clumps.cmf.slop"
    with pytest.raises(ConfigError) as err:
        clump_config_from_scene({"size": {"relation": "claeyssens"}})
    assert err.value.setting == "source.clumps.size.relation"


@pytest.mark.filterwarnings("ignore::astropy.io.fits.verify.VerifyWarning")
@pytest.mark.parametrize("ext", ["ecsv", "fits"])
def test_catalog_round_trip(tmp_path, ext):
    t = _sample(3)
    t["mag_F200W"] = np.linspace(26, 30, len(t))
    path = tmp_path / f"clumps.{ext}"
    t.write(path, overwrite=True)
    back = read_clump_catalog(path)
    for name in CATALOG_COLUMNS:
        np.testing.assert_allclose(back[name], t[name])
    np.testing.assert_allclose(back["mag_F200W"], t["mag_F200W"])


def test_catalog_minimal_with_magnitudes(tmp_path):
    t = Table(
        {
            "beta1_arcsec": [0.0, 0.1],
            "beta2_arcsec": [0.0, -0.1],
            "re_pc": [3.0, 5.0],
            "q": [1.0, 0.5],
            "pa_rad": [0.0, 1.0],
            "mag_F115W": [27.0, 28.0],
        }
    )
    path = tmp_path / "c.ecsv"
    t.write(path)
    back = read_clump_catalog(path, arcsec_per_pc=2e-4, bands=["F115W"])
    np.testing.assert_allclose(back["re_arcsec"], [6e-4, 1e-3])
    assert list(back["id"]) == [0, 1] and np.all(back["sersic_n"] == 0.5)
    with pytest.raises(ConfigError) as err:
        read_clump_catalog(path, arcsec_per_pc=2e-4, bands=["F115W", "F200W"])
    assert err.value.setting.endswith("mag_F200W")
    with pytest.raises(ConfigError) as err:
        read_clump_catalog(path)  # re_pc without arcsec_per_pc
    assert err.value.setting.endswith("re_arcsec")


@pytest.mark.parametrize(
    "change, column",
    [
        (lambda t: t.remove_column("beta2_arcsec"), "beta2_arcsec"),
        (lambda t: t.remove_column("age_myr"), "mass_msun"),
        (lambda t: t["q"].__setitem__(0, 1.5), "q"),
        (lambda t: t["re_arcsec"].__setitem__(0, -1.0), "re_arcsec"),
        (lambda t: t["mass_msun"].__setitem__(0, np.nan), "mass_msun"),
        (lambda t: t["mass_msun"].__setitem__(0, 0.0), "mass_msun"),
    ],
)
def test_catalog_invalid(tmp_path, change, column):
    t = _sample(4)
    change(t)
    path = tmp_path / "bad.ecsv"
    t.write(path)
    with pytest.raises(ConfigError) as err:
        read_clump_catalog(path)
    assert err.value.setting == f"source.clumps.catalog:{column}"


def test_catalog_missing_file(tmp_path):
    with pytest.raises(ConfigError):
        read_clump_catalog(tmp_path / "nope.ecsv")


def test_positions_cuspy_sersic_bulge_in_wide_box():
    # n = 4 Sérsic, R_e = 0.1": a cusp far sharper than the envelope grid in a
    # box of 60 R_e. Enclosed light: P(2n, b (r/R_e)^(1/n)) (regularised γ).
    from scipy import special

    n, re = 4.0, 0.1
    b = special.gammaincinv(2 * n, 0.5)

    def bulge(b1, b2):
        return np.exp(-b * ((np.hypot(b1, b2) / re) ** (1 / n) - 1))

    rng = np.random.default_rng(3)
    b1, b2 = sample_positions(rng, 10000, bulge, ((-3.0, 3.0), (-3.0, 3.0)))
    r = np.hypot(b1, b2)
    r_max = 2.9  # the largest circle inside the box; condition on it
    inside = r < r_max
    norm = special.gammainc(2 * n, b * (r_max / re) ** (1 / n))
    p = stats.kstest(r[inside], lambda s: special.gammainc(2 * n, b * (s / re) ** (1 / n)) / norm).pvalue
    assert p > P_MIN, p
