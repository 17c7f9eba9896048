"""Stochastic clump population: masses, sizes, ages, shapes, positions → catalogue.

This is the one stochastic, non-differentiated stage of the model (DESIGN.md,
"Sampling is separate from rendering"). It follows the paper's section "The
stellar clumps":

* masses from the generalised Schechter cluster mass function (CMF)
  dN/dM ∝ M^β exp[−δ (M/M_cut)^γ] on [M_min, M_max], drawn until the clumps hold
  a fraction Q of the host component's mass; the host keeps the rest;
* half-light radii from the Brown & Gnedin (2021) young-cluster relation
  R_e = 2.55 pc (M / 10⁴ M☉)^0.24 with lognormal scatter σ = 0.3 (natural log);
* ages from p(t) ∝ t^α_t on [t_min, t_max] (α_t = −0.5, 1–500 Myr);
* axis ratios U[q_min, q_max), position angles U[0, π), Sérsic n = 0.5;
* positions following the host component's surface brightness in the source
  plane, drawn continuously (no pixel quantisation).

All randomness comes from an explicit ``numpy.random.Generator`` (made from the
scene seed by the caller), so the same generator state gives the same catalogue.
The result is an ``astropy.table.Table``; the renderer treats its columns as
smooth parameters.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Mapping

import numpy as np
from astropy import units as u
from astropy.table import Table

from . import defaults as D
from .errors import ConfigError, require

__all__ = [
    "ClumpConfig",
    "CATALOG_COLUMNS",
    "COLUMN_UNITS",
    "clump_config_from_scene",
    "sample_power_law",
    "sample_cmf_masses",
    "sample_sizes_pc",
    "sample_ages_myr",
    "sample_positions",
    "sample_clumps",
    "read_clump_catalog",
]

# The catalogue contract (SCENE.md, catalog.ecsv), in column order.
CATALOG_COLUMNS = (
    "id",
    "beta1_arcsec",
    "beta2_arcsec",
    "mass_msun",
    "re_pc",
    "re_arcsec",
    "q",
    "pa_rad",
    "age_myr",
    "sersic_n",
)

COLUMN_UNITS = {
    "beta1_arcsec": u.arcsec,
    "beta2_arcsec": u.arcsec,
    "mass_msun": u.Msun,
    "re_pc": u.pc,
    "re_arcsec": u.arcsec,
    "pa_rad": u.rad,
    "age_myr": u.Myr,
}

COLUMN_DESCRIPTIONS = {
    "id": "clump index, 0-based",
    "beta1_arcsec": "source-plane position beta1 relative to the lens centre",
    "beta2_arcsec": "source-plane position beta2 relative to the lens centre",
    "mass_msun": "stellar mass",
    "re_pc": "half-light radius along the major axis (physical)",
    "re_arcsec": "half-light radius along the major axis (angular, source plane)",
    "q": "axis ratio b/a",
    "pa_rad": "position angle of the major axis, counter-clockwise from +beta1",
    "age_myr": "age of the clump's stellar population",
    "sersic_n": "Sersic index",
}


# ----------------------------------------------------------------------------
# Settings
# ----------------------------------------------------------------------------


@dataclass(frozen=True)
class ClumpConfig:
    """Settings of the clump population (paper defaults; SCENE.md [source.clumps]).

    Attributes (units in the names):
        cmf_slope: β, power-law slope of dN/dM.
        cmf_m_cut_msun: M_cut of the exponential cut-off.
        cmf_delta: δ ≥ 0, strength of the cut-off.
        cmf_gamma: γ > 0, steepness of the cut-off.
        cmf_m_min_msun, cmf_m_max_msun: sampling range of the CMF.
        size_norm_pc, size_slope, size_pivot_msun: R_e = norm (M/pivot)^slope
            (Brown & Gnedin 2021: 2.55 pc, 0.24, 1e4 M☉).
        size_scatter_ln: σ of the lognormal size scatter (natural log).
        age_slope: α_t of p(t) ∝ t^α_t.
        age_min_myr, age_max_myr: age range.
        q_range: [q_min, q_max) of the uniform axis-ratio distribution.
        sersic_n: Sérsic index of every clump.
    """

    cmf_slope: float = D.CMF["slope"]
    cmf_m_cut_msun: float = D.CMF["m_cut_msun"]
    cmf_delta: float = D.CMF["delta"]
    cmf_gamma: float = D.CMF["gamma"]
    cmf_m_min_msun: float = D.CMF["m_min_msun"]
    cmf_m_max_msun: float = D.CMF["m_max_msun"]
    size_norm_pc: float = D.SIZE["norm_pc"]
    size_slope: float = D.SIZE["slope"]
    size_pivot_msun: float = D.SIZE["pivot_msun"]
    size_scatter_ln: float = D.SIZE["scatter_ln"]
    age_slope: float = D.AGES["slope"]
    age_min_myr: float = D.AGES["min_myr"]
    age_max_myr: float = D.AGES["max_myr"]
    q_range: tuple[float, float] = D.CLUMPS["q_range"]
    sersic_n: float = D.CLUMPS["sersic_n"]

    def validate(self, prefix: str = "source.clumps") -> "ClumpConfig":
        """Raise ConfigError (naming the scene key) for any invalid setting."""
        _validate_cmf(
            self.cmf_slope,
            self.cmf_m_cut_msun,
            self.cmf_delta,
            self.cmf_gamma,
            self.cmf_m_min_msun,
            self.cmf_m_max_msun,
            prefix=f"{prefix}.cmf",
        )
        _finite_positive(self.size_norm_pc, f"{prefix}.size.norm_pc")
        _finite(self.size_slope, f"{prefix}.size.slope")
        _finite_positive(self.size_pivot_msun, f"{prefix}.size.pivot_msun")
        require(
            _is_real(self.size_scatter_ln) and math.isfinite(self.size_scatter_ln) and self.size_scatter_ln >= 0,
            f"{prefix}.size.scatter_ln",
            self.size_scatter_ln,
            "a finite number >= 0",
        )
        validate_age_range(self.age_slope, self.age_min_myr, self.age_max_myr, prefix=f"{prefix}.ages")
        qr = self.q_range
        require(
            isinstance(qr, (tuple, list))
            and len(qr) == 2
            and all(_is_real(x) for x in qr)
            and 0.0 < qr[0] <= qr[1] <= 1.0,
            f"{prefix}.q_range",
            qr,
            "[q_min, q_max] with 0 < q_min <= q_max <= 1",
        )
        require(
            _is_real(self.sersic_n) and 0.2 <= self.sersic_n <= 10.0,
            f"{prefix}.sersic_n",
            self.sersic_n,
            "a number in [0.2, 10]",
        )
        return self


_SCENE_KEYS = {
    # scene sub-table -> {scene key: ClumpConfig field}
    "cmf": {
        "slope": "cmf_slope",
        "m_cut_msun": "cmf_m_cut_msun",
        "delta": "cmf_delta",
        "gamma": "cmf_gamma",
        "m_min_msun": "cmf_m_min_msun",
        "m_max_msun": "cmf_m_max_msun",
    },
    "size": {
        "relation": None,  # only "brown-gnedin-2021"; checked below
        "scatter_ln": "size_scatter_ln",
        "norm_pc": "size_norm_pc",
        "slope": "size_slope",
        "pivot_msun": "size_pivot_msun",
    },
    "ages": {"slope": "age_slope", "min_myr": "age_min_myr", "max_myr": "age_max_myr"},
}

SIZE_RELATIONS = D.SIZE_RELATIONS


def clump_config_from_scene(section: Mapping, prefix: str = "source.clumps") -> ClumpConfig:
    """Build a validated ClumpConfig from the `[source.clumps]` table of a scene.

    Reads the sub-tables `cmf`, `size`, `ages` and the keys `sersic_n`,
    `q_range`; other keys of the section (mass_fraction, host, sfh, metallicity,
    catalog) belong to the caller and are ignored here. Unknown keys inside the
    sub-tables raise ConfigError.
    """
    kwargs: dict = {}
    for sub, mapping in _SCENE_KEYS.items():
        table = section.get(sub, {}) or {}
        require(isinstance(table, Mapping), f"{prefix}.{sub}", table, "a table")
        for key, value in table.items():
            require(key in mapping, f"{prefix}.{sub}.{key}", value, f"one of {sorted(mapping)}")
            if key == "relation":
                require(value in SIZE_RELATIONS, f"{prefix}.size.relation", value, f"one of {SIZE_RELATIONS}")
                continue
            require(_is_real(value), f"{prefix}.{sub}.{key}", value, "a number")
            kwargs[mapping[key]] = float(value)
    if "sersic_n" in section:
        kwargs["sersic_n"] = section["sersic_n"]
    if "q_range" in section:
        qr = section["q_range"]
        require(isinstance(qr, (list, tuple)) and len(qr) == 2, f"{prefix}.q_range", qr, "[q_min, q_max]")
        kwargs["q_range"] = tuple(qr)
    return ClumpConfig(**kwargs).validate(prefix)


# ----------------------------------------------------------------------------
# Validation helpers
# ----------------------------------------------------------------------------


def _is_real(x) -> bool:
    return isinstance(x, (int, float, np.integer, np.floating)) and not isinstance(x, bool)


def _finite(x, setting: str) -> None:
    require(_is_real(x) and math.isfinite(x), setting, x, "a finite number")


def _finite_positive(x, setting: str) -> None:
    require(_is_real(x) and math.isfinite(x) and x > 0, setting, x, "a finite number > 0")


def _validate_cmf(slope, m_cut, delta, gamma, m_min, m_max, *, prefix: str) -> None:
    _finite(slope, f"{prefix}.slope")
    _finite_positive(m_cut, f"{prefix}.m_cut_msun")
    # δ < 0 would turn the cut-off into exponential growth; δ = 0 is a pure power law.
    require(_is_real(delta) and math.isfinite(delta) and delta >= 0, f"{prefix}.delta", delta, "a finite number >= 0")
    _finite_positive(gamma, f"{prefix}.gamma")
    _finite_positive(m_min, f"{prefix}.m_min_msun")
    _finite_positive(m_max, f"{prefix}.m_max_msun")
    require(m_min < m_max, f"{prefix}.m_min_msun", m_min, f"a value below m_max_msun = {m_max}")


def validate_age_range(slope, t_min, t_max, *, prefix: str) -> None:
    _finite(slope, f"{prefix}.slope")
    _finite_positive(t_min, f"{prefix}.min_myr")
    _finite_positive(t_max, f"{prefix}.max_myr")
    require(t_min < t_max, f"{prefix}.min_myr", t_min, f"a value below max_myr = {t_max}")


# ----------------------------------------------------------------------------
# Elementary samplers
# ----------------------------------------------------------------------------


def sample_power_law(rng: np.random.Generator, slope: float, x_min: float, x_max: float, size) -> np.ndarray:
    """Draw from p(x) ∝ x^slope on [x_min, x_max] by the analytic inverse CDF.

    With a = slope + 1, the CDF is (x^a − x_min^a)/(x_max^a − x_min^a); at a = 0
    (slope = −1) it is ln(x/x_min)/ln(x_max/x_min). Written in log space so that
    it stays accurate for |a| → 0 and for wide ranges: x = x_min · exp(L(u)) with
    L(u) = log1p(u · expm1(a·ln r))/a, r = x_max/x_min.
    """
    uni = rng.random(size)
    a = slope + 1.0
    log_r = math.log(x_max / x_min)
    if abs(a * log_r) < 1e-12:
        log_x = uni * log_r
    else:
        log_x = np.log1p(uni * math.expm1(a * log_r)) / a
    # Rounding can push the end points an ulp outside the range.
    return np.clip(x_min * np.exp(log_x), x_min, x_max)


def _cmf_acceptance(m: np.ndarray, m_cut: float, delta: float, gamma: float) -> np.ndarray:
    """The Schechter-like factor exp[−δ (M/M_cut)^γ] ∈ (0, 1] for δ ≥ 0."""
    return np.exp(-delta * (m / m_cut) ** gamma)


def _draw_cmf_batch(rng, n: int, slope, m_cut, delta, gamma, m_min, m_max) -> np.ndarray:
    """n exact draws from the CMF by rejection from the truncated power law.

    The proposal is the pure power law M^β on [M_min, M_max] (sampled exactly by
    its inverse CDF); accepting with probability exp[−δ (M/M_cut)^γ] ≤ 1 leaves
    exactly the density M^β exp[−δ (M/M_cut)^γ]. Accepted draws keep the order
    in which they were proposed.
    """
    out = np.empty(0)
    # The acceptance rate is the mean cut-off factor under the proposal; with the
    # paper's values it is ≈ 0.99, so one or two rounds suffice.
    while out.size < n:
        need = n - out.size
        prop = sample_power_law(rng, slope, m_min, m_max, max(2 * need, 64))
        keep = rng.random(prop.size) < _cmf_acceptance(prop, m_cut, delta, gamma)
        out = np.concatenate([out, prop[keep]])
    return out[:n]


def sample_cmf_masses(
    rng: np.random.Generator,
    budget_msun: float,
    *,
    slope: float = D.CMF["slope"],
    m_cut_msun: float = D.CMF["m_cut_msun"],
    delta: float = D.CMF["delta"],
    gamma: float = D.CMF["gamma"],
    m_min_msun: float = D.CMF["m_min_msun"],
    m_max_msun: float = D.CMF["m_max_msun"],
    host_mass_msun: float | None = None,
) -> np.ndarray:
    """Clump masses [M☉] drawn from the CMF until they fill the mass budget.

    The density is dN/dM ∝ M^β exp[−δ (M/M_cut)^γ] on [M_min, M_max] (paper,
    Eq. "lum_func"), sampled exactly by rejection from the truncated power law.

    Stopping rule: clumps are drawn one after another (in batches, consumed in
    order) and sampling stops right after the first clump that brings the running
    total to ≥ ``budget_msun``. The clumps therefore exceed the budget by less
    than the last clump's mass: 0 ≤ Σ M − budget < M_last. A budget ≤ 0 gives no
    clumps.

    Host-mass guard: if ``host_mass_msun`` is given and the clump that would
    complete the budget would also push Σ M above the host mass, that clump is
    discarded and sampling stops, so that the host never gets a negative mass
    (Σ M ≤ M_host). The total then falls short of the budget by less than
    M_max. This only happens when M_host − budget < M_max, i.e. for Q close to 1
    or a host not much heavier than the heaviest allowed clump; discarding
    (rather than rescaling) keeps every returned mass an exact CMF draw.

    Returns a float64 array in drawing order.
    """
    _validate_cmf(slope, m_cut_msun, delta, gamma, m_min_msun, m_max_msun, prefix="source.clumps.cmf")
    require(_is_real(budget_msun) and math.isfinite(budget_msun), "budget_msun", budget_msun, "a finite number")
    if host_mass_msun is not None:
        _finite_positive(host_mass_msun, "host_mass_msun")
    if budget_msun <= 0:
        return np.empty(0)
    masses: list[np.ndarray] = []
    total = 0.0
    # Batch size from the expected count (budget / mean mass bounded by M_min);
    # batching changes nothing in distribution: draws are consumed in order.
    batch = int(min(max(budget_msun / max(m_min_msun, 1.0) / 4.0, 16), 100_000))
    while True:
        draws = _draw_cmf_batch(rng, batch, slope, m_cut_msun, delta, gamma, m_min_msun, m_max_msun)
        cum = total + np.cumsum(draws)
        hit = np.flatnonzero(cum >= budget_msun)
        if hit.size == 0:
            masses.append(draws)
            total = float(cum[-1])
            continue
        k = int(hit[0])
        if host_mass_msun is not None and cum[k] > host_mass_msun:
            masses.append(draws[:k])  # the completing clump would overdraw the host
        else:
            masses.append(draws[: k + 1])
        return np.concatenate(masses)


def sample_sizes_pc(
    rng: np.random.Generator,
    mass_msun: np.ndarray,
    *,
    norm_pc: float = D.SIZE["norm_pc"],
    slope: float = D.SIZE["slope"],
    pivot_msun: float = D.SIZE["pivot_msun"],
    scatter_ln: float = D.SIZE["scatter_ln"],
) -> np.ndarray:
    """Half-light radii [pc]: R_e = norm (M/pivot)^slope · exp(σ ε), ε ~ N(0, 1).

    Defaults: Brown & Gnedin (2021, MNRAS 508, 5935) young-cluster relation as
    used by the paper, with σ = 0.3 in natural log. The median is the relation.
    """
    mass_msun = np.asarray(mass_msun, dtype=float)
    eps = rng.standard_normal(mass_msun.shape)
    return norm_pc * (mass_msun / pivot_msun) ** slope * np.exp(scatter_ln * eps)


def sample_ages_myr(
    rng: np.random.Generator,
    size,
    *,
    slope: float = D.AGES["slope"],
    min_myr: float = D.AGES["min_myr"],
    max_myr: float = D.AGES["max_myr"],
) -> np.ndarray:
    """Ages [Myr] from p(t) ∝ t^α_t on [t_min, t_max] (continuous inverse CDF).

    α_t = −1 (flat in log t) is handled exactly.
    """
    validate_age_range(slope, min_myr, max_myr, prefix="source.clumps.ages")
    return sample_power_law(rng, slope, min_myr, max_myr, size)


# ----------------------------------------------------------------------------
# Positions: rejection sampling of the host light
# ----------------------------------------------------------------------------

# Envelope: the bounding box is cut into cells; each cell's envelope height is
# the largest brightness seen on a (sub x sub) grid inside the cell (edges
# included) times SAFETY, floored at FLOOR x the largest value seen in the cell
# and its 8 neighbours, so that cells next to light keep a non-zero probability
# even where the sub-grid saw none. A candidate is drawn by picking a
# cell with probability ∝ height (equal areas) and a uniform point in it, and
# accepted with probability f/height. This is exact whenever f ≤ height
# everywhere; the sampler checks every candidate and, if one ever exceeds its
# cell's height (e.g. an unresolved cusp), raises that height and starts over.
_ENVELOPE_CELLS = 128
_ENVELOPE_SUB = 5
_ENVELOPE_SAFETY = 1.2
_ENVELOPE_FLOOR = 1e-3
_MAX_RESTARTS = 20
_PROBE_CELLS = 64
_PROBE_POINTS = 256


def _brightness(host_brightness, b1, b2) -> np.ndarray:
    values = np.asarray(host_brightness(b1, b2), dtype=float)
    values = np.broadcast_to(values, np.shape(b1))
    return values


def _envelope(host_brightness, bbox) -> np.ndarray:
    """Per-cell envelope heights (shape cells x cells, index [i1, i2])."""
    (x0, x1), (y0, y1) = bbox
    nc, ns = _ENVELOPE_CELLS, _ENVELOPE_SUB
    # A grid with (ns − 1) intervals per cell; cell (i, j) covers nodes
    # [i(ns−1), (i+1)(ns−1)] in each axis, so shared edges are seen by both cells.
    n_nodes = nc * (ns - 1) + 1
    g1 = np.linspace(x0, x1, n_nodes)
    g2 = np.linspace(y0, y1, n_nodes)
    b1, b2 = np.meshgrid(g1, g2, indexing="ij")
    f = _brightness(host_brightness, b1, b2)
    if not np.all(np.isfinite(f)) or np.any(f < 0):
        raise ConfigError("host_brightness", "non-finite or negative values", "a finite, non-negative surface brightness")
    peak = float(f.max())
    if peak <= 0:
        raise ConfigError("host_brightness", "zero everywhere in the bounding box", "some light inside bbox_arcsec")
    # Max over each cell's (ns x ns) block of nodes.
    idx = np.arange(nc)[:, None] * (ns - 1) + np.arange(ns)[None, :]
    blocks = f[idx[:, :, None, None], idx[None, None, :, :]]  # (nc, ns, nc, ns)
    cell_max = blocks.max(axis=(1, 3))
    # Floor from the neighbourhood (3 x 3 cells), not the global peak: it guards
    # cells next to light that the sub-grid may have missed, without spending
    # proposals on empty sky far from the galaxy (which a global floor would do
    # for a cuspy, compact host in a wide box).
    padded = np.pad(cell_max, 1)
    neighbours = np.max(
        [padded[1 + d0 : 1 + d0 + nc, 1 + d1 : 1 + d1 + nc] for d0 in (-1, 0, 1) for d1 in (-1, 0, 1)], axis=0
    )
    return np.maximum(_ENVELOPE_SAFETY * cell_max, _ENVELOPE_FLOOR * neighbours)


def sample_positions(
    rng: np.random.Generator,
    n: int,
    host_brightness: Callable[[np.ndarray, np.ndarray], np.ndarray],
    bbox_arcsec,
) -> tuple[np.ndarray, np.ndarray]:
    """n positions (β1, β2) [arcsec] distributed as the host surface brightness.

    ``host_brightness(beta1_arcsec, beta2_arcsec)`` is a vectorised callable
    (numpy arrays in and out, any positive normalisation) giving the host
    component's surface brightness in the source plane; it may vanish on whole
    regions (between spiral arms). ``bbox_arcsec = ((β1_min, β1_max), (β2_min,
    β2_max))`` bounds the sampled region: light outside it gets no clumps, so
    choose it to enclose essentially all of the host light.

    Method: rejection sampling under a piecewise-constant envelope (128 x 128
    cells, each 1.2 x the largest brightness on a 5 x 5 sub-grid of the cell,
    floored at 1e-3 of the largest value in the cell and its 8 neighbours;
    cells whose whole neighbourhood shows zero light are never proposed; the 64
    brightest cells are probed with random points first). Positions are continuous; the result is an
    exact draw from the density restricted to the box as long as the envelope
    bounds it, which the sampler verifies on every candidate (a violating cell
    is raised and the whole draw restarted, so the returned sample was drawn
    under an envelope that was never seen to be violated).
    """
    require(isinstance(n, (int, np.integer)) and n >= 0, "n", n, "an integer >= 0")
    _validate_bbox(bbox_arcsec)
    (x0, x1), (y0, y1) = bbox_arcsec
    if n == 0:
        return np.empty(0), np.empty(0)
    height = _envelope(host_brightness, bbox_arcsec)
    nc = _ENVELOPE_CELLS
    w1, w2 = (x1 - x0) / nc, (y1 - y0) / nc
    _probe_envelope(rng, height, host_brightness, x0, y0, w1, w2)
    for _ in range(_MAX_RESTARTS):
        drawn = _rejection_pass(rng, n, height, host_brightness, x0, y0, w1, w2)
        if drawn is not None:
            return drawn
    raise RuntimeError("sample_positions: the rejection envelope kept being violated; is host_brightness bounded?")


def _rejection_pass(rng, n, height, host_brightness, x0, y0, w1, w2):
    """One rejection-sampling pass under the envelope ``height`` (cells w1 x w2 arcsec
    from the box corner (x0, y0) arcsec): n positions (β1, β2) [arcsec], or None when a
    candidate exceeded its cell's height; those cells are then raised in place (to 2 x
    the brightness seen) and the caller restarts the whole draw."""
    nc = height.shape[1]
    cdf = np.cumsum(height.ravel())
    cdf /= cdf[-1]
    acc1, acc2 = [], []
    got = proposed = 0
    while got < n:
        # Batch sized from the acceptance rate seen so far (the envelope's
        # mass over the light's), so that a low rate does not mean many calls.
        rate = max(got / proposed, 1e-3) if proposed else 0.5
        m = int(min(1.2 * (n - got) / rate + 256, 2_000_000))
        proposed += m
        cell = np.minimum(np.searchsorted(cdf, rng.random(m), side="right"), cdf.size - 1)
        i1, i2 = np.divmod(cell, nc)
        b1 = x0 + (i1 + rng.random(m)) * w1
        b2 = y0 + (i2 + rng.random(m)) * w2
        f = _brightness(host_brightness, b1, b2)
        h = height[i1, i2]
        bad = f > h
        if np.any(bad):
            # Raise the offending cells well above what was seen, then redo.
            np.maximum.at(height, (i1[bad], i2[bad]), 2.0 * f[bad])
            return None
        keep = rng.random(m) * h < f
        acc1.append(b1[keep])
        acc2.append(b2[keep])
        got += int(keep.sum())
    return np.concatenate(acc1)[:n], np.concatenate(acc2)[:n]


def _probe_envelope(rng, height, host_brightness, x0, y0, w1, w2) -> None:
    """Raise the heights of the brightest cells where random probes exceed them.

    The brightest cells are where an unresolved peak (a cuspy bulge, a compact
    host in a wide box) hides between sub-grid nodes. Probing them before any
    sample is drawn costs little and makes the restarts of the sampler rare;
    it draws no samples, so it cannot bias them.
    """
    order = np.argsort(height.ravel())[::-1][:_PROBE_CELLS]
    i1, i2 = np.divmod(np.repeat(order, _PROBE_POINTS), height.shape[1])
    b1 = x0 + (i1 + rng.random(i1.size)) * w1
    b2 = y0 + (i2 + rng.random(i2.size)) * w2
    f = _brightness(host_brightness, b1, b2)
    np.maximum.at(height, (i1, i2), _ENVELOPE_SAFETY * f)


def _validate_bbox(bbox) -> None:
    ok = False
    try:
        (x0, x1), (y0, y1) = bbox
        ok = all(_is_real(v) and math.isfinite(v) for v in (x0, x1, y0, y1)) and x0 < x1 and y0 < y1
    except (TypeError, ValueError):
        ok = False
    require(ok, "bbox_arcsec", bbox, "((beta1_min, beta1_max), (beta2_min, beta2_max)) with min < max")


# ----------------------------------------------------------------------------
# The catalogue
# ----------------------------------------------------------------------------


def _make_table(columns: dict, meta: dict) -> Table:
    table = Table(meta=meta)
    for name in CATALOG_COLUMNS:
        table[name] = columns[name]
        if name in COLUMN_UNITS:
            table[name].unit = COLUMN_UNITS[name]
        table[name].description = COLUMN_DESCRIPTIONS[name]
    return table


def sample_clumps(
    rng: np.random.Generator,
    *,
    host_mass_msun: float,
    mass_fraction: float,
    host_brightness: Callable[[np.ndarray, np.ndarray], np.ndarray],
    bbox_arcsec,
    arcsec_per_pc: float,
    config: ClumpConfig = ClumpConfig(),
) -> Table:
    """Sample a clump population for one host component.

    Args:
        rng: numpy Generator made from the scene seed (the only source of
            randomness; the same state gives the same table).
        host_mass_msun: stellar mass of the host component (e.g. the disk).
        mass_fraction: Q ∈ [0, 1], fraction of the host mass put into clumps.
        host_brightness: vectorised callable (β1, β2) [arcsec] → host surface
            brightness (numpy in/out); positions follow it.
        bbox_arcsec: ((β1_min, β1_max), (β2_min, β2_max)) enclosing the host.
        arcsec_per_pc: angular scale at the source redshift (from the
            cosmology, e.g. ``cosmology.arcsec_per_pc(z_source)``).
        config: ClumpConfig (CMF, size, age, shape settings).

    Returns:
        astropy Table with columns ``id, beta1_arcsec, beta2_arcsec,
        mass_msun, re_pc, re_arcsec, q, pa_rad, age_myr, sersic_n`` (units set on
        the columns) and ``meta`` holding ``host_mass_msun``,
        ``host_mass_remaining_msun`` (= M_host − Σ M_clumps ≥ 0),
        ``clump_mass_budget_msun`` (= Q M_host) and ``mass_fraction``.

    Draw order (fixed, so that a seed reproduces a catalogue): masses, sizes,
    ages, axis ratios, position angles, positions.
    """
    _check_sample_inputs(config, host_mass_msun, mass_fraction, arcsec_per_pc, bbox_arcsec,
                         host_brightness)
    # the draw order is part of the seed's contract (docstring): keep these calls in order
    mass = _sample_masses(rng, mass_fraction * host_mass_msun, host_mass_msun, config)
    n = mass.size
    re_pc, age, q, pa = _sample_shapes(rng, mass, config)
    beta1, beta2 = sample_positions(rng, n, host_brightness, bbox_arcsec)

    columns = {
        "id": np.arange(n, dtype=np.int64),
        "beta1_arcsec": beta1,
        "beta2_arcsec": beta2,
        "mass_msun": mass,
        "re_pc": re_pc,
        "re_arcsec": re_pc * arcsec_per_pc,
        "q": q,
        "pa_rad": pa,
        "age_myr": age,
        "sersic_n": np.full(n, float(config.sersic_n)),
    }
    return _make_table(columns, _mass_meta(host_mass_msun, mass, mass_fraction, arcsec_per_pc))


def _mass_meta(host_mass_msun, mass_msun, mass_fraction, arcsec_per_pc) -> dict:
    """The catalogue's meta: host mass, what the clumps left of it, their budget [M☉]."""
    return {
        "host_mass_msun": float(host_mass_msun),
        "host_mass_remaining_msun": float(max(host_mass_msun - mass_msun.sum(), 0.0)),
        "clump_mass_budget_msun": float(mass_fraction * host_mass_msun),
        "mass_fraction": float(mass_fraction),
        "arcsec_per_pc": float(arcsec_per_pc),
    }


def _check_sample_inputs(config, host_mass_msun, mass_fraction, arcsec_per_pc, bbox_arcsec,
                         host_brightness) -> None:
    """Refuse bad `sample_clumps` arguments (ConfigError naming the setting), in that order."""
    config.validate()
    _finite_positive(host_mass_msun, "host_mass_msun")
    require(
        _is_real(mass_fraction) and 0.0 <= mass_fraction <= 1.0,
        "source.clumps.mass_fraction",
        mass_fraction,
        "a number in [0, 1]",
    )
    _finite_positive(arcsec_per_pc, "arcsec_per_pc")
    _validate_bbox(bbox_arcsec)
    require(callable(host_brightness), "host_brightness", host_brightness, "a callable (beta1, beta2) -> brightness")


def _sample_masses(rng, budget_msun, host_mass_msun, config: ClumpConfig) -> np.ndarray:
    """Clump masses [M☉] from the configured CMF until they fill budget_msun."""
    return sample_cmf_masses(
        rng,
        budget_msun,
        slope=config.cmf_slope,
        m_cut_msun=config.cmf_m_cut_msun,
        delta=config.cmf_delta,
        gamma=config.cmf_gamma,
        m_min_msun=config.cmf_m_min_msun,
        m_max_msun=config.cmf_m_max_msun,
        host_mass_msun=host_mass_msun,
    )


def _sample_shapes(rng, mass_msun, config: ClumpConfig):
    """(R_e [pc], age [Myr], axis ratio q, PA [rad]) per clump, drawn in that order."""
    n = mass_msun.size
    re_pc = sample_sizes_pc(
        rng,
        mass_msun,
        norm_pc=config.size_norm_pc,
        slope=config.size_slope,
        pivot_msun=config.size_pivot_msun,
        scatter_ln=config.size_scatter_ln,
    )
    age = sample_ages_myr(rng, n, slope=config.age_slope, min_myr=config.age_min_myr, max_myr=config.age_max_myr)
    q_min, q_max = config.q_range
    q = q_min + (q_max - q_min) * rng.random(n)
    pa = math.pi * rng.random(n)
    return re_pc, age, q, pa


# ----------------------------------------------------------------------------
# Reading a user catalogue
# ----------------------------------------------------------------------------

_REQUIRED_ALWAYS = ("beta1_arcsec", "beta2_arcsec", "q", "pa_rad")


def read_clump_catalog(
    path,
    *,
    arcsec_per_pc: float | None = None,
    bands=None,
    sersic_n_default: float = 0.5,
    setting: str = "source.clumps.catalog",
) -> Table:
    """Read a user clump catalogue (ECSV or FITS) and validate it.

    Columns (SCENE.md): ``beta1_arcsec, beta2_arcsec, q, pa_rad`` always;
    ``re_arcsec``, or ``re_pc`` together with the ``arcsec_per_pc`` argument;
    ``mass_msun`` and ``age_myr`` unless every band's flux is set by a
    ``mag_<FILTER>`` column (AB magnitudes; with ``bands`` given, each band
    needs either its ``mag_`` column or mass and age). Optional: ``id``
    (default 0..N−1), ``sersic_n`` (default ``sersic_n_default``), ``re_pc``.

    Returns a Table in the sampler's layout (missing optional columns filled,
    ``re_pc`` computed when possible, ``mag_*`` columns kept). Invalid files,
    missing columns and invalid values raise ConfigError naming the column.
    """
    path = Path(path)
    table = _read_table(path, setting)
    names = set(table.colnames)
    mag_cols = [c for c in table.colnames if c.startswith("mag_")]
    _require_catalog_columns(names, mag_cols, arcsec_per_pc, bands, setting)
    n = len(table)
    # the checks below run in the columns' order: a file with several faults names the first
    out: dict = {}
    out["beta1_arcsec"] = _catalog_column(table, "beta1_arcsec", setting)
    out["beta2_arcsec"] = _catalog_column(table, "beta2_arcsec", setting)
    out["q"] = _bounded_column(table, "q", setting, lambda q: (q > 0) & (q <= 1), "0 < q <= 1")
    out["pa_rad"] = _catalog_column(table, "pa_rad", setting)
    out["re_pc"], out["re_arcsec"] = _catalog_sizes(table, names, arcsec_per_pc, setting)
    for name in ("mass_msun", "age_myr"):
        if name in names:
            out[name] = _bounded_column(table, name, setting, lambda v: v > 0, "values > 0")
        else:
            out[name] = np.full(n, np.nan)  # flux comes from the mag_ columns
    if "sersic_n" in names:
        out["sersic_n"] = _bounded_column(table, "sersic_n", setting,
                                          lambda sn: (sn >= 0.2) & (sn <= 10), "values in [0.2, 10]")
    else:
        out["sersic_n"] = np.full(n, float(sersic_n_default))
    out["id"] = _catalog_ids(table, names, setting)

    result = _make_table(out, {"source_file": str(path)})
    _add_mag_columns(result, table, mag_cols, setting)
    return result


def _read_table(path: Path, setting: str) -> Table:
    """The catalogue file as a Table: FITS by its ending, else ECSV."""
    require(path.is_file(), setting, str(path), "an existing ECSV or FITS file")
    suffix = "".join(path.suffixes).lower()
    try:
        if suffix.endswith((".fits", ".fit", ".fits.gz", ".fts")):
            return Table.read(path, format="fits")
        return Table.read(path, format="ascii.ecsv")
    except Exception as exc:  # astropy raises many types for bad files
        raise ConfigError(setting, str(path), f"a readable ECSV or FITS table ({exc})") from exc


def _require_catalog_columns(names: set, mag_cols: list, arcsec_per_pc, bands, setting: str) -> None:
    """Refuse a catalogue without the columns SCENE.md asks for (ConfigError naming one)."""
    for col in _REQUIRED_ALWAYS:
        require(col in names, f"{setting}:{col}", "missing", "a column named " + col)
    require(
        "re_arcsec" in names or ("re_pc" in names and arcsec_per_pc is not None),
        f"{setting}:re_arcsec",
        "missing",
        "a re_arcsec column (or re_pc plus the source redshift's arcsec_per_pc)",
    )
    has_sps = "mass_msun" in names and "age_myr" in names
    require(
        has_sps or mag_cols,
        f"{setting}:mass_msun",
        "missing",
        "mass_msun and age_myr columns, or mag_<FILTER> columns",
    )
    if bands is not None and not has_sps:
        for band in bands:
            require(f"mag_{band}" in names, f"{setting}:mag_{band}", "missing", f"a mag_{band} column (or mass_msun and age_myr)")


def _catalog_column(table: Table, name: str, setting: str) -> np.ndarray:
    """A column as finite floats (ConfigError naming it otherwise)."""
    try:
        values = np.asarray(table[name], dtype=float)
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"{setting}:{name}", "non-numeric", "numbers") from exc
    require(np.all(np.isfinite(values)), f"{setting}:{name}", "NaN or inf", "finite values")
    return values


def _bounded_column(table: Table, name: str, setting: str, ok, expected: str) -> np.ndarray:
    """`_catalog_column` whose every value passes ok(values) (a mask); the error shows the first
    that does not."""
    values = _catalog_column(table, name, setting)
    good = ok(values)
    require(np.all(good), f"{setting}:{name}", _first_bad(values, good), expected)
    return values


def _catalog_sizes(table: Table, names: set, arcsec_per_pc, setting: str):
    """(re_pc, re_arcsec) per clump: each from its column, else from the other through
    arcsec_per_pc; re_pc NaN where neither it nor the scale is given."""
    positive = lambda v: v > 0  # noqa: E731
    if "re_arcsec" in names:
        re_arcsec = _bounded_column(table, "re_arcsec", setting, positive, "values > 0")
    if "re_pc" in names:
        re_pc = _bounded_column(table, "re_pc", setting, positive, "values > 0")
    if arcsec_per_pc is not None:
        _finite_positive(arcsec_per_pc, "arcsec_per_pc")
    if "re_arcsec" not in names:
        re_arcsec = re_pc * arcsec_per_pc
    if "re_pc" not in names:
        re_pc = re_arcsec / arcsec_per_pc if arcsec_per_pc is not None else np.full(len(table), np.nan)
    return re_pc, re_arcsec


def _catalog_ids(table: Table, names: set, setting: str) -> np.ndarray:
    """The id column (unique integers), or 0..N−1 without one."""
    n = len(table)
    if "id" not in names:
        return np.arange(n, dtype=np.int64)
    ids = np.asarray(table["id"])
    require(np.issubdtype(ids.dtype, np.integer), f"{setting}:id", str(ids.dtype), "integers")
    require(np.unique(ids).size == n, f"{setting}:id", "duplicates", "unique ids")
    return ids.astype(np.int64)


def _add_mag_columns(result: Table, table: Table, mag_cols: list, setting: str) -> None:
    """Copy the mag_<FILTER> columns (AB magnitudes, checked against the scene's range)."""
    from .scene import AB_MAG_RANGE
    lo, hi = AB_MAG_RANGE
    for name in mag_cols:
        m = _bounded_column(table, name, setting, lambda v: (v >= lo) & (v <= hi),
                            f"AB magnitudes in [{lo:g}, {hi:g}]")
        result[name] = m
        result[name].unit = u.mag  # AB


def _first_bad(values: np.ndarray, ok: np.ndarray):
    bad = np.flatnonzero(~ok)
    return float(values[bad[0]]) if bad.size else None
